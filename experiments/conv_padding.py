"""What replicate ('edge') padding costs DLCTUS's residual trunk on XLA:CPU.

    python experiments/conv_padding.py            # 1080p at 4x: 270x480 maps, 32 channels
    python experiments/conv_padding.py --size 32 32 --batch 4 --name conv_padding_crop

Writes ``docs/results/<name>/result.{md,json}``.

Times the trunk (four residual blocks of two 3x3 32->32 convolutions) jitted, warm,
medians of round-robin repeats, with four ways of padding: zero padding (the SAME convolution
alone: a lower bound, not DLCTUS's function), jtus's edge pad + SAME + crop
(``layers.conv_edge``), edge pad + VALID, and a zero-padded SAME convolution plus a
correction computed on the one-pixel border ring. The three edge-padded variants are
checked equal first.
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


def _pad(x):
    return jnp.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")


def conv_border(x, kernel, bias):
    """Edge-padded 3x3 convolution as a zero-padded one plus the border ring's terms."""
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
    "zero padding (SAME only; lower bound)": lambda x, k, b: layers.conv(x, k, b),
    "edge pad + SAME + crop (jtus: pad_edge, one concatenation per axis)": layers.conv_edge,
    "jnp.pad(mode='edge') + SAME + crop (jtus before the ONNX export)":
        lambda x, k, b: layers.conv(_pad(x), k, b)[:, 1:-1, 1:-1],
    "edge pad + VALID": lambda x, k, b: layers.conv(_pad(x), k, b, padding="VALID"),
    "zero padding + border-ring correction": conv_border,
}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, nargs=2, default=(270, 480), metavar=("H", "W"))
    p.add_argument("--batch", type=int, default=1)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--name", default="conv_padding", help="docs/results/<name>/")
    args = p.parse_args(argv)
    r = np.random.default_rng(0)
    x = jnp.asarray(r.normal(size=(args.batch, *args.size, 32)), jnp.float32)
    k = jnp.asarray(r.normal(size=(3, 3, 32, 32)) * 0.05, jnp.float32)
    b = jnp.asarray(r.normal(size=(32,)) * 0.05, jnp.float32)
    ref = layers.conv_edge(x, k, b)
    for name in list(VARIANTS)[2:]:
        err = float(jnp.abs(VARIANTS[name](x, k, b) - ref).max())
        if err > 1e-4:
            raise AssertionError(f"{name}: differs from conv_edge by {err}")
    fns = {}
    for name, conv in VARIANTS.items():
        def trunk(x, conv=conv):
            for _ in range(4):
                x = x + conv(jax.nn.relu(conv(x, k, b)), k, b)
            return x

        f = jax.jit(trunk)
        fns[name] = lambda f=f: f(x).block_until_ready()
    sec = timing.timeit_round_robin(fns, args.repeats)  # in turn: ratios from one machine
    base = sec[next(iter(sec))]
    rows = [f"| {name} | {1e3 * s:.1f} | {s / base:.2f}x |" for name, s in sec.items()]
    data = [{"padding": name, "ms": 1e3 * s, "vs_zero": s / base} for name, s in sec.items()]
    table = (f"Trunk of 8 convolutions at {args.batch}x{args.size[0]}x{args.size[1]}x32, "
             f"medians of {args.repeats} round-robin repeats.\n\n"
             "| padding | ms | vs zero padding |\n"
             "| --- | --- | --- |\n" + "\n".join(rows))
    write(args.name, table, {"size": list(args.size), "batch": args.batch, "rows": data})
    return 0


if __name__ == "__main__":
    sys.exit(main())
