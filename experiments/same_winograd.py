"""NSRR's zero-padded 3x3 convolutions differentiated by Winograd's F(4x4, 3x3)
(``layers.conv_same_winograd``) or directly (``layers.conv_same_fast``): layer by layer
and in the training steps. Where ``nsrr.Config.conv_backward="auto"`` comes from.

    taskset -c 0 python experiments/same_winograd.py           # per layer, one core
    python experiments/same_winograd.py --in-step nsrr nsrr-fast --name same-winograd-in-step

Per layer (the default): each of NSRR's and NSRR-fast's 3x3 layers at crop 128 (a
device's batch of 2: the U-Net's 128x128 to 32x32 levels, the reweighting network's
128x128 layers, the extractors' 64x64 layers at 2x), its forward pass and both gradients
(one jitted VJP) in either form, medians of ``--rounds`` rounds of ``--repeats``
round-robin calls. Run it on one core: a split training step runs each device's
convolutions on one core (``python -m jtus.train`` from crop 128 on).

``--in-step MODEL ...``: each model's training step (2x, the ``diverse`` preset's window:
crop 128, batch 4, 8 frames, the batch split over a device per core) with
``conv_backward="winograd"`` (the layers of at least ``nsrr.WINOGRAD_CHANNELS``) and
``"custom"``, round-robin in one process, ``--rounds`` rounds; ``--channels IN OUT``
replaces ``nsrr.WINOGRAD_CHANNELS`` for the run.

Writes ``docs/results/<name>/result.{md,json}`` (default ``same-winograd``).
"""

from __future__ import annotations

import argparse
import sys

import jax
import jax.numpy as jnp
import numpy as np
from common import rounds_ms, write

from jtus import bench, recipe, sharding
from jtus import config as run_config
from jtus.models import layers, nsrr

# (map side, in, out) at crop 128, 2x: NSRR's U-Net, reweighting and extractors, then
# NSRR-fast's U-Net (its other layers are NSRR's)
NSRR = [(128, 60, 64), (128, 64, 32), (64, 32, 64), (64, 64, 64), (32, 64, 128),
        (32, 128, 128), (64, 192, 64), (128, 96, 32), (128, 32, 3),
        (128, 20, 32), (128, 32, 32), (128, 32, 4), (64, 4, 32), (64, 32, 32), (64, 32, 8)]
NSRR_FAST = [(128, 60, 32), (128, 32, 16), (64, 16, 32), (64, 32, 32), (32, 32, 64),
             (32, 64, 64), (64, 96, 32), (128, 48, 16), (128, 16, 3)]
BATCH = 2  # a device's part of the diverse preset's batch of 4


def per_layer(rng, repeats, rounds):
    rows, data = [], []
    for model, shapes in (("nsrr", NSRR), ("nsrr-fast", NSRR_FAST)):
        for side, c_in, c_out in shapes:
            x = jnp.asarray(rng.normal(size=(BATCH, side, side, c_in)), jnp.float32)
            k = jnp.asarray(rng.normal(size=(3, 3, c_in, c_out)) * 0.05, jnp.float32)
            b = jnp.zeros((c_out,), jnp.float32)
            g = jnp.asarray(rng.normal(size=(BATCH, side, side, c_out)), jnp.float32)
            fns = {}
            for form, fn in (("direct", layers.conv_same_fast),
                             ("winograd", layers.conv_same_winograd)):
                f = jax.jit(lambda x, k, b, g, fn=fn: jax.vjp(fn, x, k, b)[1](g))
                jax.block_until_ready(f(x, k, b, g))
                fns[form] = lambda f=f: jax.block_until_ready(f(x, k, b, g))
            ms = {f: float(np.median(v)) for f, v in rounds_ms(fns, repeats, rounds).items()}
            rows.append(f"| {model} | {BATCH} x {side} x {side} | {c_in} | {c_out} | "
                        f"{ms['direct']:.2f} | {ms['winograd']:.2f} | "
                        f"{ms['direct'] / ms['winograd']:.2f} |")
            data.append({"model": model, "side": side, "c_in": c_in, "c_out": c_out, "ms": ms})
            print(rows[-1], file=sys.stderr)
    return ("Each 3x3 layer's forward pass and both gradients (one jitted VJP), ms, medians "
            f"of {rounds} rounds of {repeats} round-robin calls.\n\n| model | map | in | "
            "out | direct ms | Winograd ms | direct / Winograd |\n| --- | --- | --- | --- | "
            "--- | --- | --- |\n" + "\n".join(rows)), {"rows": data}


def in_step(names, repeats, rounds):
    cfg = run_config.PRESETS["diverse"]
    plan = recipe.plan(cfg)
    fns = {}
    for model in names:
        for form in ("custom", "winograd"):
            run, _, _ = bench.train_workload(2, cfg.crop, cfg.batch, plan.window,
                                             plan.loss_frames, conv_backward=form, name=model)
            run()  # compiled
            fns[(model, form)] = run
    ms = rounds_ms(fns, repeats, rounds)
    rows, data = [], []
    for model in names:
        d, w = ms[(model, "custom")], ms[(model, "winograd")]
        rows.append(f"| {model} | {' '.join(f'{v / 1e3:.2f}' for v in d)} | "
                    f"{' '.join(f'{v / 1e3:.2f}' for v in w)} | "
                    f"{np.median(d) / np.median(w):.2f} |")
        data.append({"model": model, "direct_ms": d, "winograd_ms": w})
    return (f"Training steps (2x, crop {cfg.crop}, batch {cfg.batch}, {plan.window} frames, "
            f"{len(jax.devices())} CPU device(s)), s/step in each of {rounds} rounds of "
            f"{repeats} round-robin calls; Winograd: every 3x3 layer from at least "
            f"{nsrr.WINOGRAD_CHANNELS[0]} channels to at least {nsrr.WINOGRAD_CHANNELS[1]} "
            "(`conv_backward=\"winograd\"`), direct: `\"custom\"`.\n\n| model | direct s/step | "
            "Winograd s/step | direct / Winograd (medians) |\n| --- | --- | --- | --- |\n"
            + "\n".join(rows)), {"rows": data}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--name", default="same-winograd", help="docs/results/<name>/")
    p.add_argument("--in-step", nargs="+", metavar="MODEL",
                   help="time these models' training steps with and without Winograd")
    p.add_argument("--channels", nargs=2, type=int, metavar=("IN", "OUT"),
                   help="--in-step: the fewest channels of a Winograd layer in place of "
                        "nsrr.WINOGRAD_CHANNELS")
    args = p.parse_args(argv)
    if args.channels:
        nsrr.WINOGRAD_CHANNELS = tuple(args.channels)  # read when a step is traced
    if args.in_step:
        # the split training step's devices, set before JAX's first computation
        sharding.use_host_devices(None, run_config.PRESETS["diverse"].batch)
        table, data = in_step(args.in_step, args.repeats, args.rounds)
    else:
        table, data = per_layer(np.random.default_rng(0), args.repeats, args.rounds)
    write(args.name, table, data)
    return 0


if __name__ == "__main__":
    sys.exit(main())
