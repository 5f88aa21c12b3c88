"""Sequence length against BPTT, truncated BPTT and BPTT with remat: time per training
step, compiled memory, and quality over whole videos, including after 300+ frames.

    python experiments/sweep_seqlen.py                      # lengths 2 4 8 16 30
    python experiments/sweep_seqlen.py --lengths 4 8 --steps 200 --long-frames 320

Training and quality use the ``long`` data (40-frame videos at 128x128, generated into
``data/long.h5`` in about two minutes when missing): the ``default`` data's training
videos have 24 frames, too few for 30-frame sequences.

Memory is XLA's own account of the compiled train step (arguments, outputs and
temporaries, ``compiled.memory_analysis()``): the peak the step needs, independent of
what else the process holds. The long-horizon video (a built-in scene rendered for
``--long-frames`` frames) is scored on its last 20 frames.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from common import ROOT, write

from jtus import evaluate, metrics, recipe, rollout, train
from jtus.config import PRESETS
from jtus.data.dataset import Dataset
from jtus.sim import generate

MODES = ("bptt", "tbptt", "bptt+remat")


def _config(base, length, mode):
    if mode == "tbptt":
        k = max(1, length // 2)
        return dataclasses.replace(base, seq_len=length, mode="tbptt", k1=k, k2=k,
                                   loss_frames=min(base.loss_frames, length))
    return dataclasses.replace(base, seq_len=length, mode="bptt", remat=mode == "bptt+remat",
                               loss_frames=min(base.loss_frames, length))


def _long_video(factor, frames, size):
    from jtus import sim
    from jtus.frame import Frame
    v = sim.render_video(sim.get_scene("plaza_day"), "test", 7, frames, size=(size, size),
                         factors=(factor,), spp=4)
    x = v[f"x{factor}"]
    reset = np.zeros(frames, bool)
    reset[0] = True
    return (Frame(x["color"][:, None], x["depth"][:, None], x["motion"][:, None],
                  x["jitter"][:, None], reset[:, None]), v["target"][:, None])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--lengths", type=int, nargs="+", default=[2, 4, 8, 16, 30])
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    p.add_argument("--factor", type=int, default=4)
    p.add_argument("--crop", type=int, default=64)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--steps", type=int, default=150, help="training steps per configuration")
    p.add_argument("--long-frames", type=int, default=320)
    p.add_argument("--long-size", type=int, default=128)
    p.add_argument("--dataset", default=os.path.join(ROOT, "data", "long.h5"),
                   help="generated from the `long` preset (40-frame videos) when missing")
    p.add_argument("--max-videos", type=int, default=4)
    args = p.parse_args(argv)
    base = dataclasses.replace(PRESETS["default"], factor=args.factor, crop=args.crop,
                               batch=args.batch, dataset=args.dataset, data_preset="long")
    generate.ensure_dataset(base.dataset, base.data_preset, progress=sys.stderr.isatty())
    long_frames, long_targets = jax.tree_util.tree_map(
        jnp.asarray, _long_video(args.factor, args.long_frames, args.long_size))
    rows = []
    for length in args.lengths:
        for mode in args.modes:
            config = _config(base, length, mode)
            model, loss_fn = recipe.model_for(config), recipe.loss_for(config)
            opt = optax.adam(config.lr)
            window, lf, keep, windows = recipe.plan(config)
            step = train.make_train_step(model, loss_fn, opt, loss_frames=lf, keep_at=keep,
                                         remat=config.remat)
            ts = train.create_train_state(model.init(jax.random.PRNGKey(0)), opt)
            rng = np.random.default_rng(0)
            times, mem = [], None
            with Dataset(args.dataset) as ds:
                for i in range(args.steps):
                    fr, tg = jax.tree_util.tree_map(jnp.asarray, ds.crops(
                        "train", config.factor, config.batch, config.seq_len, config.crop, rng))
                    carry = recipe.start_carry(model, fr, tg)
                    t0 = time.perf_counter()
                    for w in windows:
                        sl = jax.tree_util.tree_map(lambda x: x[w.start:w.stop], (fr, tg))
                        if mem is None:
                            m = step.lower(ts, carry, *sl).compile().memory_analysis()
                            mem = (m.argument_size_in_bytes + m.output_size_in_bytes
                                   + m.temp_size_in_bytes) if m is not None else float("nan")
                        ts, carry, stats = step(ts, carry, *sl)
                    stats["loss"].block_until_ready()
                    if i > 0:
                        times.append(time.perf_counter() - t0)
                q = evaluate.video_means(model, ts.params, args.dataset, args.factor,
                                    max_videos=args.max_videos)
            outs = rollout.video(model, ts.params, long_frames, check=False)
            tail = slice(-20, None)
            long_psnr = float(jnp.mean(metrics.psnr(outs[tail, 0], long_targets[tail, 0])))
            rows.append({"length": length, "mode": mode, "s_per_step": float(np.median(times)),
                         "memory_mb": mem / 2**20, "psnr": q["psnr"], "ssim": q["ssim"],
                         "temporal": q["temporal"], "long_psnr": long_psnr})
            print(rows[-1])
    table = ["| sequence | mode | s / step | memory (MiB) | PSNR (dB) | SSIM | temporal | "
             f"PSNR after {args.long_frames - 20} frames |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        table.append(f"| {r['length']} | {r['mode']} | {r['s_per_step']:.3f} | "
                     f"{r['memory_mb']:.0f} | {r['psnr']:.2f} | {r['ssim']:.4f} | "
                     f"{r['temporal']:.5f} | {r['long_psnr']:.2f} |")
    d = write("seqlen", "\n".join(table), rows,
              f"DLCTUS {args.factor}x, crop {args.crop}, batch {args.batch}, {args.steps} "
              f"steps per row (TBPTT: k1 = k2 = length / 2); trained on "
              f"`{os.path.relpath(args.dataset, ROOT)}`, "
              f"quality on {args.max_videos} of its test videos.")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.5))
    for mode in args.modes:
        rs = [r for r in rows if r["mode"] == mode]
        L = [r["length"] for r in rs]
        ax[0].plot(L, [r["s_per_step"] for r in rs], marker="o", label=mode)
        ax[1].plot(L, [r["memory_mb"] for r in rs], marker="o", label=mode)
        ax[2].plot(L, [r["psnr"] for r in rs], marker="o", label=mode)
    for a, t in zip(ax, ("seconds per step", "compiled memory (MiB)", "test PSNR (dB)")):
        a.set_title(t)
        a.set_xlabel("sequence length")
        a.grid(alpha=0.3)
    ax[0].legend()
    fig.tight_layout()
    fig.savefig(os.path.join(d, "seqlen.png"), dpi=100)


if __name__ == "__main__":
    main()
