"""The kernel gradient of a convolution on XLA:CPU in three forms, at the training
steps' shapes: one VALID convolution with the channels as its batch
(``layers.kernel_grad_conv``), one matmul per kernel tap (``layers.kernel_grad_matmuls``)
and one matmul per kernel column over the row-shifted input (``layers.kernel_grad_columns``).

    python experiments/kernel_grad.py
    python experiments/kernel_grad.py --in-step kpn nsrr nsrr-fast dlctus --name kernel-grad-in-step

Writes ``docs/results/kernel-grad/result.{md,json}``. Each shape is (kernel size, batch,
map side, input channels, output channels): DLCTUS's trunk at crop 128 (32x32, 32
channels, a device's batch of 2 or the whole 4), NSRR's layers at crop 128 (128x128 down
to the U-Net's 32x32, a device's batch of 2) and KPN's at crop 128 (its first layer on a
device's batch of 2, its switched layers one batch element at a time, 5x5 kernels to
12 and 50 channels). The forms are checked equal first (1e-4 of the largest value);
times are medians of round-robin repeats, jitted and warm. The last column is the form
``layers.kernel_grad_form`` picks for the shape.

``--in-step MODEL ...`` times instead each model's training step (2x, the ``diverse``
preset's window: crop 128, batch 4, 8 frames, split over a device per core as
``jtus.train`` does), round-robin in one process, under three rules: ``layers``'s own,
the same without the column form (the convolution in its place), and the column form
wherever a kernel writes 32 or more channels on a map of 64x64 or more.
"""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
import numpy as np
from common import write

from jtus import bench, recipe, sharding, timing
from jtus import config as run_config
from jtus.models import layers

# (kernel, batch, map side, in, out)
SHAPES = [(3, 2, 32, 32, 32), (3, 4, 32, 32, 32),                         # DLCTUS
          (3, 2, 128, 20, 32), (3, 2, 128, 32, 32), (3, 2, 128, 32, 4),    # NSRR
          (3, 2, 128, 60, 64), (3, 2, 128, 64, 32), (3, 2, 128, 96, 32), (3, 2, 128, 32, 3),
          (3, 2, 64, 32, 64), (3, 2, 64, 64, 64), (3, 2, 64, 192, 64),
          (3, 2, 32, 64, 128), (3, 2, 32, 128, 128),
          (3, 2, 128, 14, 12), (3, 1, 128, 12, 12), (5, 1, 128, 12, 12),   # KPN
          (5, 1, 128, 12, 50)]
FORMS = {"convolution": layers.kernel_grad_conv, "matmul per tap": layers.kernel_grad_matmuls,
         "matmul per column": layers.kernel_grad_columns}


def _rules():
    """``{name: rule}``: ``layers.kernel_grad_form`` and two alternatives."""
    own = layers.kernel_grad_form

    def no_columns(k, h, w, c_in, c_out):
        form = own(k, h, w, c_in, c_out)
        return "conv" if form == "columns" else form

    def wide_columns(k, h, w, c_in, c_out):
        form = own(k, h, w, c_in, c_out)
        return "columns" if form == "conv" and c_out >= 32 and h * w >= 64 * 64 else form

    return {"layers' rule": own, "no column form": no_columns,
            "column form from 32 channels": wide_columns}


def in_step(names, repeats, name):
    """The training steps of ``names`` under each of ``_rules()``, round-robin."""
    cfg = run_config.PRESETS["diverse"]
    plan = recipe.plan(cfg)
    sharding.use_host_devices(None, cfg.batch)
    own = layers.kernel_grad_form
    fns = {}
    try:
        for model in names:
            for rule_name, rule in _rules().items():
                layers.kernel_grad_form = rule  # read when the step is traced
                run, _, _ = bench.train_workload(2, cfg.crop, cfg.batch, plan.window,
                                                 plan.loss_frames, name=model)
                run()  # compile under this rule
                fns[(model, rule_name)] = run
    finally:
        layers.kernel_grad_form = own
    sec = timing.timeit_round_robin(fns, repeats)
    rows, data = [], []
    for model in names:
        base = sec[(model, "layers' rule")]
        for rule_name in _rules():
            s = sec[(model, rule_name)]
            rows.append(f"| {model} | {rule_name} | {s:.3f} | {s / base:.2f} |")
            data.append({"model": model, "rule": rule_name, "s_per_step": s})
    table = (f"Training steps (2x, crop {cfg.crop}, batch {cfg.batch}, {plan.window} frames, "
             f"{len(jax.devices())} CPU device(s)) under three kernel-gradient rules, "
             f"medians of {repeats} round-robin repeats.\n\n| model | rule | s/step | "
             "x layers' rule |\n| --- | --- | --- | --- |\n" + "\n".join(rows))
    write(name, table, {"rows": data})
    return 0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--name", default="kernel-grad", help="docs/results/<name>/")
    p.add_argument("--in-step", nargs="+", metavar="MODEL",
                   help="time these models' training steps under three rules instead")
    args = p.parse_args(argv)
    if args.in_step:
        return in_step(args.in_step, args.repeats, args.name)
    r = np.random.default_rng(0)
    forms = {k: jax.jit(f) for k, f in FORMS.items()}
    rows, data = [], []
    for k, b, n, c, o in SHAPES:
        xp = jnp.asarray(r.normal(size=(b, n + k - 1, n + k - 1, c)), jnp.float32)
        g = jnp.asarray(r.normal(size=(b, n, n, o)), jnp.float32)
        ref = forms["convolution"](xp, g)
        for name, f in forms.items():
            err = float(jnp.abs(f(xp, g) - ref).max() / jnp.abs(ref).max())
            if err > 1e-4:
                raise AssertionError(f"{(k, b, n, c, o)}: {name} differs by {err} (relative)")
        sec = timing.timeit_round_robin(
            {name: (lambda f=f: f(xp, g).block_until_ready()) for name, f in forms.items()},
            args.repeats)
        ms = {name: 1e3 * s for name, s in sec.items()}
        chosen = layers.KERNEL_GRAD_FORMS[layers.kernel_grad_form(k, n, n, c, o)]
        fastest = min(ms, key=ms.get)
        rows.append(f"| {k}x{k} | {b} | {n}x{n} | {c} | {o} | "
                    + " | ".join(f"{ms[f]:.2f}" for f in FORMS)
                    + f" | {fastest} | {chosen} ({ms[chosen] / ms[fastest]:.2f}x the fastest) |")
        data.append({"kernel": k, "batch": b, "side": n, "c_in": c, "c_out": o,
                     "ms": ms, "fastest": fastest, "chosen": chosen})
    table = (f"Kernel gradient of a convolution, ms, medians of {args.repeats} round-robin "
             "repeats.\n\n| kernel | batch | map | in | out | "
             + " | ".join(FORMS) + " | fastest | `layers` uses |\n"
             + "| --- " * (len(FORMS) + 7) + "|\n" + "\n".join(rows))
    write(args.name, table, {"rows": data})
    return 0


if __name__ == "__main__":
    sys.exit(main())
