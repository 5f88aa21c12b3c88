"""What replicate ('edge') padding costs DLCTUS's residual trunk on XLA:CPU.

    python experiments/conv_padding.py            # 1080p at 4x: 270x480 maps, 32 channels
    python experiments/conv_padding.py --size 180 320 --name conv_padding-720p
    python experiments/conv_padding.py --train --name conv_padding-train   # training shapes

Writes ``docs/results/<name>/result.{md,json}``.

Times the trunk (four residual blocks of two 3x3 32->32 convolutions) jitted, warm,
medians of round-robin repeats, with the ways of padding: zero padding (the SAME
convolution alone, not DLCTUS's function), jtus's ``layers.conv_edge`` (the SAME
convolution plus the border ring's terms placed by masks), edge pad + SAME + crop (what
``layers.conv_edge_fast`` does under differentiation, where the padded input is its
saved residual), the same with ``jnp.pad``, edge pad + VALID, and the border ring's terms
added in place on the border lines. The edge-padded variants are checked equal first.

``--train`` times instead the gradient of a loss over the trunk scanned over frames (a
recurrent carry, as DLCTUS's training window; default 8 frames of 4x32x32x32, crop 128
at 4x's network size) with the forward padded (``conv_edge_fast``, which keeps the padded
input for its backward) and with the ring form's forward, which keeps ``x`` and pads it
in the backward; both backward passes are the same code.
"""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
import numpy as np
from common import write

from jtus import timing
from jtus.models import layers
from jtus.sampling import pad_edge


def _pad(x):
    return jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")


def _reference(x, kernel, bias):
    return layers.conv(_pad(x), kernel, bias, padding="VALID")


def conv_border(x, kernel, bias):
    """Edge-padded 3x3 convolution as a zero-padded one plus the border ring's terms,
    each a strip convolution added in place on its border line (``.at[].add``)."""
    y = layers.conv(x, kernel, bias)

    def strip(v, k):
        return layers.conv(v, k)

    def row(r):
        return jnp.pad(r, ((0, 0), (0, 0), (1, 1), (0, 0)), mode="edge")

    top = strip(row(x[:, :1]), kernel[0:1])[:, :, 1:-1]  # padded row -1, kernel row 0
    bottom = strip(row(x[:, -1:]), kernel[2:3])[:, :, 1:-1]
    left = strip(x[:, :, :1], kernel[:, 0:1])  # padded column -1 (corners are in top/bottom)
    right = strip(x[:, :, -1:], kernel[:, 2:3])
    y = y.at[:, :1].add(top).at[:, -1:].add(bottom)
    return y.at[:, :, :1].add(left).at[:, :, -1:].add(right)


VARIANTS = {
    "zero padding (SAME only; not DLCTUS's function)": lambda x, k, b: layers.conv(x, k, b),
    "SAME + border ring by masks (jtus: layers.conv_edge)": layers.conv_edge,
    "edge pad + SAME + crop (pad_edge; conv_edge_fast under differentiation)":
        lambda x, k, b: layers.conv(pad_edge(x, 1), k, b)[:, 1:-1, 1:-1],
    "jnp.pad(mode='edge') + SAME + crop":
        lambda x, k, b: layers.conv(_pad(x), k, b)[:, 1:-1, 1:-1],
    "edge pad + VALID": lambda x, k, b: layers.conv(_pad(x), k, b, padding="VALID"),
    "SAME + border ring added in place": conv_border,
}


def _timed_rows(fns, repeats, key, vs):
    """Time ``fns`` in turn (ratios from one machine); the table rows and JSON records,
    each against the first."""
    sec = timing.timeit_round_robin(fns, repeats)
    base = sec[next(iter(sec))]
    rows = [f"| {name} | {1e3 * s:.1f} | {s / base:.2f}x |" for name, s in sec.items()]
    data = [{key: name, "ms": 1e3 * s, vs: s / base} for name, s in sec.items()]
    return rows, data


def _edge_backward(xp, kernel, g):
    """The gradients of an edge-padded 3x3 convolution from its padded input ``xp``
    (``conv_edge_fast``'s backward, written out here so that both training forms share
    it): the kernel gradient as a VALID convolution with channels as the batch, the
    input gradient as a SAME convolution with the flipped kernel, folded through the
    edge padding's adjoint."""
    dn = ("NHWC", "HWIO", "NHWC")
    dk = jax.lax.conv_general_dilated(xp.transpose(3, 1, 2, 0), g.transpose(1, 2, 0, 3),
                                      (1, 1), "VALID", dimension_numbers=dn)
    flipped = jnp.flip(kernel, (0, 1)).transpose(0, 1, 3, 2)
    dxp = layers.conv(jnp.pad(g, ((0, 0), (1, 1), (1, 1), (0, 0))), flipped)
    _, fold = jax.vjp(lambda v: pad_edge(v, 1), xp[:, 1:-1, 1:-1])
    return fold(dxp)[0], dk.transpose(1, 2, 0, 3), g.sum((0, 1, 2))


def _training_forms():
    @jax.custom_vjp
    def padded(x, k, b):
        return layers.conv_edge(x, k, b)

    def padded_fwd(x, k, b):
        xp = pad_edge(x, 1)
        return layers.conv(xp, k, b)[:, 1:-1, 1:-1], (xp, k)

    padded.defvjp(padded_fwd, lambda res, g: _edge_backward(*res, g))

    @jax.custom_vjp
    def ring(x, k, b):
        return layers.conv_edge(x, k, b)

    ring.defvjp(lambda x, k, b: (layers.conv_edge(x, k, b), (x, k)),
                lambda res, g: _edge_backward(pad_edge(res[0], 1), res[1], g))
    return {"pad + SAME + crop forward (jtus: conv_edge_fast)": layers.conv_edge_fast,
            "the same, backward written here": padded,
            "ring forward (conv_edge), x kept, padded in the backward": ring}


def _train(args):
    r = np.random.default_rng(0)
    xs = jnp.asarray(r.normal(size=(args.frames, args.batch, *args.size, 32)), jnp.float32)
    k = jnp.asarray(r.normal(size=(3, 3, 32, 32)) * 0.05, jnp.float32)
    b = jnp.asarray(r.normal(size=(32,)) * 0.05, jnp.float32)
    fns, grads = {}, {}
    for name, conv in _training_forms().items():
        def loss(k, b, conv=conv):
            def body(c, x):
                h = x + c
                for _ in range(4):
                    h = h + conv(jax.nn.relu(conv(h, k, b)), k, b)
                return 0.5 * h, (h ** 2).mean()
            return jax.lax.scan(body, jnp.zeros_like(xs[0]), xs)[1].sum()

        f = jax.jit(jax.grad(loss, (0, 1)))
        grads[name] = f(k, b)
        fns[name] = lambda f=f: jax.block_until_ready(f(k, b))
    ref = jax.tree_util.tree_leaves(next(iter(grads.values())))
    for name, g in grads.items():
        for a, c in zip(ref, jax.tree_util.tree_leaves(g)):
            err = float(jnp.abs(a - c).max() / jnp.abs(a).max())
            if err > 1e-4:
                raise AssertionError(f"{name}: gradients differ by {err} (relative)")
    rows, data = _timed_rows(fns, args.repeats, "form", "vs_jtus")
    table = (f"Gradient of a loss over the trunk scanned over {args.frames} frames of "
             f"{args.batch}x{args.size[0]}x{args.size[1]}x32, medians of {args.repeats} "
             "round-robin repeats.\n\n| forward | ms | vs jtus |\n| --- | --- | --- |\n"
             + "\n".join(rows))
    write(args.name, table, {"size": list(args.size), "batch": args.batch,
                             "frames": args.frames, "rows": data})
    return 0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, nargs=2, default=None, metavar=("H", "W"),
                   help="maps' size (default 270 480, with --train 32 32)")
    p.add_argument("--batch", type=int, default=None, help="default 1, with --train 4")
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--train", action="store_true", help="time the training gradient")
    p.add_argument("--frames", type=int, default=8, help="frames scanned with --train")
    p.add_argument("--name", default="conv_padding", help="docs/results/<name>/")
    args = p.parse_args(argv)
    args.size = args.size or ((32, 32) if args.train else (270, 480))
    args.batch = args.batch or (4 if args.train else 1)
    if args.train:
        return _train(args)
    r = np.random.default_rng(0)
    x = jnp.asarray(r.normal(size=(args.batch, *args.size, 32)), jnp.float32)
    k = jnp.asarray(r.normal(size=(3, 3, 32, 32)) * 0.05, jnp.float32)
    b = jnp.asarray(r.normal(size=(32,)) * 0.05, jnp.float32)
    ref = _reference(x, k, b)
    for name in list(VARIANTS)[1:]:
        err = float(jnp.abs(VARIANTS[name](x, k, b) - ref).max())
        if err > 1e-4:
            raise AssertionError(f"{name}: differs from edge pad + VALID by {err}")
    fns = {}
    for name, conv in VARIANTS.items():
        def trunk(x, conv=conv):
            for _ in range(4):
                x = x + conv(jax.nn.relu(conv(x, k, b)), k, b)
            return x

        f = jax.jit(trunk)
        fns[name] = lambda f=f: f(x).block_until_ready()
    rows, data = _timed_rows(fns, args.repeats, "padding", "vs_zero")
    table = (f"Trunk of 8 convolutions at {args.batch}x{args.size[0]}x{args.size[1]}x32, "
             f"medians of {args.repeats} round-robin repeats.\n\n"
             "| padding | ms | vs zero padding |\n"
             "| --- | --- | --- |\n" + "\n".join(rows))
    write(args.name, table, {"size": list(args.size), "batch": args.batch, "rows": data})
    return 0


if __name__ == "__main__":
    sys.exit(main())
