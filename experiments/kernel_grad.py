"""The kernel gradient of a 3x3 convolution on XLA:CPU: one VALID convolution with the
channels as its batch (``layers.kernel_grad_conv``) against one matmul per kernel tap
(``layers.kernel_grad_matmuls``), at the training steps' shapes.

    python experiments/kernel_grad.py

Writes ``docs/results/kernel-grad/result.{md,json}``. Each shape is (batch, map side,
input channels, output channels): DLCTUS's trunk at crop 128 (32x32, 32 channels, a
device's batch of 2 or the whole 4) and NSRR's layers at crop 128 (128x128 down to the
U-Net's 32x32). Both forms are checked equal first (1e-4 of the
largest value); times are medians of round-robin repeats, jitted and warm.
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

# (batch, map side, in, out): DLCTUS's trunk (a device's batch of 2, and 4), then NSRR's
# layers at crop 128 on a device's batch of 2: reweighting and U-Net at 128x128, the
# U-Net's lower levels at 64x64 and 32x32
SHAPES = [(2, 32, 32, 32), (4, 32, 32, 32),
          (2, 128, 20, 32), (2, 128, 32, 32), (2, 128, 32, 4), (2, 128, 60, 64),
          (2, 128, 64, 32), (2, 128, 96, 32), (2, 128, 32, 3),
          (2, 64, 32, 64), (2, 64, 64, 64), (2, 64, 192, 64),
          (2, 32, 64, 128), (2, 32, 128, 128)]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--name", default="kernel-grad", help="docs/results/<name>/")
    args = p.parse_args(argv)
    r = np.random.default_rng(0)
    forms = {"convolution": jax.jit(layers.kernel_grad_conv),
             "matmul per tap": jax.jit(layers.kernel_grad_matmuls)}
    rows, data = [], []
    for b, n, c, o in SHAPES:
        xp = jnp.asarray(r.normal(size=(b, n + 2, n + 2, c)), jnp.float32)
        g = jnp.asarray(r.normal(size=(b, n, n, o)), jnp.float32)
        ref = forms["convolution"](xp, g)
        err = float(jnp.abs(forms["matmul per tap"](xp, g) - ref).max() / jnp.abs(ref).max())
        if err > 1e-4:
            raise AssertionError(f"{(b, n, c, o)}: the forms differ by {err} (relative)")
        sec = timing.timeit_round_robin(
            {k: (lambda f=f: f(xp, g).block_until_ready()) for k, f in forms.items()},
            args.repeats)
        conv, mm = sec["convolution"], sec["matmul per tap"]
        chosen = "matmul per tap" if layers.kernel_grad_by_matmuls(3, n, n, c, o) else "convolution"
        rows.append(f"| {b} | {n}x{n} | {c} | {o} | {1e3 * conv:.2f} | {1e3 * mm:.2f} | "
                    f"{mm / conv:.2f} | {chosen} |")
        data.append({"batch": b, "side": n, "c_in": c, "c_out": o, "conv_ms": 1e3 * conv,
                     "matmul_ms": 1e3 * mm, "chosen": chosen})
    table = (f"Kernel gradient of a 3x3 convolution, medians of {args.repeats} round-robin "
             "repeats.\n\n| batch | map | in | out | convolution ms | matmul per tap ms | "
             "ratio | `layers` uses |\n| --- | --- | --- | --- | --- | --- | --- | --- |\n"
             + "\n".join(rows))
    write(args.name, table, {"rows": data})
    return 0


if __name__ == "__main__":
    sys.exit(main())
