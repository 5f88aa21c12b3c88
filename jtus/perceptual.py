"""VGG-16 perceptual loss (Johnson et al. 2016) for NSRR's training loss.

NSRR (seed ``001``, eq. 1) trains with ``1 - SSIM + w * sum_i ||conv_i(x) - conv_i(x_ref)||^2``
with ``w = 0.1`` and five VGG-16 layers. The pretrained weights cannot be downloaded
on the machines jtus is built for, so this module never fetches anything: the term is
on only when the user gives a weights file (``python -m jtus.train --perceptual-weights
FILE``), and off otherwise.

The file is an ``.npz`` holding the 13 convolution layers of torchvision's
``vgg16().features`` under their torchvision names (``features.0.weight``
``[64,3,3,3]``, ``features.0.bias``, ... ``features.28.bias``), which a machine with
torchvision writes with::

    import numpy as np, torchvision
    sd = torchvision.models.vgg16(weights="IMAGENET1K_V1").features.state_dict()
    np.savez("vgg16.npz", **{"features." + k: v.numpy() for k, v in sd.items()})

The features are taken after the ReLU that ends each of the five blocks (relu1_2,
relu2_2, relu3_3, relu4_3, relu5_3), each term normalized by its size ``C*H*W`` as in
Johnson et al. (``mean`` of the squared difference), on images normalized with the
ImageNet mean and standard deviation that the weights were trained with.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np

# torchvision vgg16().features: conv indices, with "M" for the 2x2 max-pools
_LAYOUT = (0, 2, "M", 5, 7, "M", 10, 12, 14, "M", 17, 19, 21, "M", 24, 26, 28)
_WIDTHS = {0: (3, 64), 2: (64, 64), 5: (64, 128), 7: (128, 128), 10: (128, 256),
           12: (256, 256), 14: (256, 256), 17: (256, 512), 19: (512, 512), 21: (512, 512),
           24: (512, 512), 26: (512, 512), 28: (512, 512)}
# the ReLU outputs at the end of each block: relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
FEATURE_LAYERS = (2, 7, 14, 21, 28)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def load_vgg16(path: str) -> dict:
    """Conv weights ``{index: (w [3,3,Cin,Cout] HWIO, b [Cout])}`` from an ``.npz`` with
    torchvision names; clear errors for a missing file, missing keys or wrong shapes."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"perceptual weights: no file {path!r} (an .npz of "
                                "torchvision vgg16().features, see jtus/perceptual.py)")
    try:
        with np.load(path) as data:
            arrays = {k: data[k] for k in data.files}
    except Exception as e:  # noqa: BLE001  zip/pickle errors of a corrupt file
        raise ValueError(f"perceptual weights: {path!r} is not a readable .npz ({e})") from e
    params = {}
    for i, (cin, cout) in _WIDTHS.items():
        wk, bk = f"features.{i}.weight", f"features.{i}.bias"
        for k in (wk, bk):
            if k not in arrays:
                raise ValueError(f"perceptual weights: {path!r} lacks {k!r} "
                                 f"(expected torchvision vgg16().features names)")
        w, b = arrays[wk], arrays[bk]
        if w.shape != (cout, cin, 3, 3) or b.shape != (cout,):
            raise ValueError(f"perceptual weights: {wk} has shape {w.shape} and {bk} "
                             f"{b.shape}; expected {(cout, cin, 3, 3)} and {(cout,)}")
        if not (np.isfinite(w).all() and np.isfinite(b).all()):
            raise ValueError(f"perceptual weights: {wk} or {bk} holds NaN or Inf")
        params[i] = (jnp.asarray(np.transpose(w, (2, 3, 1, 0)), jnp.float32),
                     jnp.asarray(b, jnp.float32))
    return params


def features(params: dict, x, layers=FEATURE_LAYERS):
    """VGG-16 ReLU features of ``x [B,H,W,3]`` (RGB in [0, 1]) at ``layers``."""
    mean = jnp.asarray(IMAGENET_MEAN, x.dtype)
    std = jnp.asarray(IMAGENET_STD, x.dtype)
    h = (x - mean) / std
    out = []
    last = max(layers)
    for item in _LAYOUT:
        if item == "M":
            h = jax.lax.reduce_window(h, -jnp.inf, jax.lax.max, (1, 2, 2, 1), (1, 2, 2, 1),
                                      "VALID")
            continue
        w, b = params[item]
        h = jax.lax.conv_general_dilated(h, w.astype(h.dtype), (1, 1), "SAME",
                                         dimension_numbers=("NHWC", "HWIO", "NHWC"))
        h = jax.nn.relu(h + b.astype(h.dtype))
        if item in layers:
            out.append(h)
        if item == last:
            break
    return out


def loss(params: dict, out, target, layers=FEATURE_LAYERS):
    """``sum_i mean((phi_i(out) - phi_i(target))^2)`` over the chosen layers."""
    fo = features(params, out, layers)
    ft = features(params, jax.lax.stop_gradient(target), layers)
    return sum(jnp.mean(jnp.square(a - b)) for a, b in zip(fo, ft))
