"""The VGG-16 perceptual term against a PyTorch VGG-16 with the same (random) weights,
and its input checks. Pretrained weights are never needed: the term is checked on
whatever weights the file holds."""

import numpy as np
import pytest
import torch

from jtus import losses, perceptual


def _torch_vgg(seed=0):
    torch.manual_seed(seed)
    layers, cin = [], 3
    for item in perceptual._LAYOUT:
        if item == "M":
            layers.append(torch.nn.MaxPool2d(2, 2))
        else:
            cout = perceptual._WIDTHS[item][1]
            conv = torch.nn.Conv2d(cin, cout, 3, padding=1)
            torch.nn.init.kaiming_normal_(conv.weight, nonlinearity="relu")
            torch.nn.init.uniform_(conv.bias, -0.05, 0.05)
            layers += [conv, torch.nn.ReLU()]
            cin = cout
    net = torch.nn.Sequential(*layers).double().requires_grad_(False)
    # torchvision numbering: conv at 0, 2, 5, ...; our Sequential has the same indices
    assert all(isinstance(net[i], torch.nn.Conv2d) for i in perceptual._WIDTHS)
    return net


@pytest.fixture(scope="module")
def vgg_file(tmp_path_factory):
    net = _torch_vgg()
    path = tmp_path_factory.mktemp("vgg") / "vgg16.npz"
    np.savez(path, **{"features." + k: v.numpy() for k, v in net.state_dict().items()})
    return net, str(path)


def _torch_loss(net, x, y):
    mean = torch.tensor(perceptual.IMAGENET_MEAN, dtype=torch.float64).view(1, 3, 1, 1)
    std = torch.tensor(perceptual.IMAGENET_STD, dtype=torch.float64).view(1, 3, 1, 1)
    hx = (torch.from_numpy(x).permute(0, 3, 1, 2) - mean) / std
    hy = (torch.from_numpy(y).permute(0, 3, 1, 2) - mean) / std
    total = 0.0
    for i, layer in enumerate(net):
        hx, hy = layer(hx), layer(hy)
        # the ReLU after conv k sits at index k + 1
        if i - 1 in perceptual.FEATURE_LAYERS and isinstance(layer, torch.nn.ReLU):
            total = total + torch.mean((hx - hy) ** 2)
    return float(total)


def test_perceptual_matches_torch(vgg_file):
    net, path = vgg_file
    rng = np.random.default_rng(1)
    x = rng.random((2, 32, 48, 3))
    y = np.clip(x + 0.1 * rng.standard_normal(x.shape), 0, 1)
    params = perceptual.load_vgg16(path)
    got = float(perceptual.loss(params, x.astype(np.float32), y.astype(np.float32)))
    want = _torch_loss(net, x, y)
    assert want > 0
    np.testing.assert_allclose(got, want, rtol=2e-5)
    assert float(perceptual.loss(params, x.astype(np.float32), x.astype(np.float32))) == 0.0


def test_nsrr_loss_adds_weighted_term(vgg_file):
    _, path = vgg_file
    rng = np.random.default_rng(2)
    out = rng.random((1, 32, 32, 3)).astype(np.float32)
    tgt = rng.random((1, 32, 32, 3)).astype(np.float32)
    base = losses.make("ssim", 4)(out, tgt, None, None, None, None)
    full = losses.make("ssim", 4, perceptual_weights=path, perceptual_weight=0.1)(
        out, tgt, None, None, None, None)
    term = perceptual.loss(perceptual.load_vgg16(path), out, tgt)
    np.testing.assert_allclose(float(full), float(base) + 0.1 * float(term), rtol=1e-6)
    assert float(term) > 0
    # NSRR's weight of the perceptual term, 0.1, is the default
    default = losses.make("ssim", 4, perceptual_weights=path)(out, tgt, None, None, None, None)
    assert float(default) == float(full)
    # the same default in with_perceptual itself (the wrapper the recipe calls)
    ssim = losses.make("ssim", 4)
    wrapped = losses.with_perceptual(ssim, path)(out, tgt, None, None, None, None)
    assert float(wrapped) == float(full)
    # a weight of 0 is allowed (the term is off), a negative one is refused by name
    zero = losses.with_perceptual(ssim, path, weight=0.0)(out, tgt, None, None, None, None)
    assert float(zero) == float(base)
    with pytest.raises(ValueError, match=r"perceptual_weight: expected a value >= 0, got -0.1"):
        losses.with_perceptual(ssim, path, weight=-0.1)


def test_bad_weight_files(tmp_path, vgg_file):
    _, path = vgg_file
    with pytest.raises(FileNotFoundError, match="perceptual weights"):
        perceptual.load_vgg16(str(tmp_path / "missing.npz"))
    data = dict(np.load(path))
    del data["features.14.weight"]
    np.savez(tmp_path / "partial.npz", **data)
    with pytest.raises(ValueError, match="features.14.weight"):
        perceptual.load_vgg16(str(tmp_path / "partial.npz"))
    data = dict(np.load(path))
    data["features.0.weight"] = data["features.0.weight"][:, :, :2]
    np.savez(tmp_path / "shape.npz", **data)
    with pytest.raises(ValueError, match=r"features.0.weight has shape"):
        perceptual.load_vgg16(str(tmp_path / "shape.npz"))
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable"):
        perceptual.load_vgg16(str(tmp_path / "junk.npz"))


@pytest.mark.parametrize("loss", ["l1", "kpn"])
def test_training_config_adds_the_term_to_any_loss(vgg_file, loss):
    import dataclasses

    import jax.numpy as jnp

    from jtus import recipe
    from jtus.config import Config
    from jtus.frame import Frame

    _, path = vgg_file
    rng = np.random.default_rng(3)
    out = jnp.asarray(rng.random((1, 32, 32, 3)), jnp.float32)
    tgt = jnp.asarray(rng.random((1, 32, 32, 3)), jnp.float32)
    frame = Frame(jnp.asarray(rng.random((1, 8, 8, 3)), jnp.float32), jnp.ones((1, 8, 8, 1)),
                  jnp.zeros((1, 8, 8, 2)), jnp.full((1, 2), 0.5))
    args = (out, tgt, out, tgt, jnp.asarray([True]), frame)
    base = Config(loss=loss)
    with_term = dataclasses.replace(base, perceptual_weights=path, perceptual_weight=0.5)
    term = perceptual.loss(perceptual.load_vgg16(path), out, tgt)
    np.testing.assert_allclose(float(recipe.loss_for(with_term)(*args)),
                               float(recipe.loss_for(base)(*args)) + 0.5 * float(term), rtol=1e-5)
