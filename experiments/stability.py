"""The long stability runs: a texture moving at constant sub-pixel speed for 3600
frames through DLCTUS (shipped weights) and TUS with each reprojection warp, and
DLCTUS's float16 / bfloat16 rollouts of 1000 frames against float32.

    python experiments/stability.py
    python experiments/stability.py --frames 600 --size 64        # a quicker look

The video is analytic (``moving_texture_video``): LR samples of three translating
sinusoids taken at the thesis jitter positions, the target a 16-sample box filter, the
motion exact and constant, so what changes over time is the methods' accumulated
error alone.
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np
from common import WARPS, write

from jtus import loading, metrics, models, rollout, sampling
from jtus.frame import Frame


def moving_texture_video(frames, size, factor, speed=(0.37, 0.11)):
    """A sum of three sinusoids (wavelengths 9, 11 and 13 HR pixels) translating at
    ``speed`` LR pixels per frame: LR samples at the thesis jitters, a 16-sample
    box-filtered target, exact constant backward motion."""
    h = size // factor
    seq = sampling.jitter_sequence("thesis", factor)

    def f(x, y, t):  # x, y in HR pixels
        x = x - speed[0] * factor * t
        y = y - speed[1] * factor * t
        return (0.5 + 0.15 * np.cos(2 * np.pi * x / 9) + 0.15 * np.cos(2 * np.pi * y / 11)
                + 0.1 * np.cos(2 * np.pi * (x + y) / 13))

    jj, ii = np.meshgrid(np.arange(h), np.arange(h))
    off = (np.stack(np.meshgrid(np.arange(4), np.arange(4)), -1).reshape(-1, 2) + 0.5) / 4
    YY, XX = np.mgrid[0:size, 0:size]
    color, target, jit = [], [], []
    for t in range(frames):
        j = seq[t % len(seq)]
        v = f((jj + j[0]) * factor, (ii + j[1]) * factor, t)
        color.append(np.repeat(v[..., None], 3, -1))
        acc = sum(f(XX + o[0], YY + o[1], t) for o in off) / len(off)
        target.append(np.repeat(acc[..., None], 3, -1))
        jit.append(j)
    T = frames
    motion = np.broadcast_to(-np.asarray(speed, np.float32), (T, 1, h, h, 2))
    reset = np.zeros((T, 1), bool)
    reset[0] = True
    fr = Frame(np.asarray(color, np.float32)[:, None], np.full((T, 1, h, h, 1), 0.9, np.float32),
               np.ascontiguousarray(motion), np.asarray(jit, np.float32)[:, None], reset)
    return (jax.tree_util.tree_map(jnp.asarray, fr),
            jnp.asarray(np.asarray(target, np.float32)[:, None]))


def reprojection_growth(method, a, alpha, frames, size=64, motion=(0.37, -0.21)):
    """A zone plate warped ``frames`` times by a constant sub-pixel motion with no new
    input (``alpha`` = 0) or blended with the fresh image by ``alpha``: the peak
    magnitude ``max |x|`` after each warp (the image starts in [0.1, 0.9])."""
    yy, xx = np.mgrid[0:size, 0:size] / size
    img = 0.5 + 0.4 * np.cos(40 * ((xx - 0.3) ** 2 + (yy - 0.4) ** 2))
    img = jnp.asarray(np.repeat(img[None, ..., None], 3, -1), jnp.float32)
    xy = sampling.pixel_grid(1, size, size) + jnp.asarray(motion, jnp.float32)

    def body(x, _):
        x = (1 - alpha) * sampling.sample(x, xy, method, a=a) + alpha * img
        return x, jnp.abs(x).max()

    return np.asarray(jax.jit(lambda x: jax.lax.scan(body, x, None, length=frames)[1])(img))


def _curve(model, params, frames, targets):
    def fn(out, target, *rest):
        return {"psnr": metrics.psnr(out, target), "min": out.min(), "max": out.max()}
    run = jax.jit(lambda p, s, f, t: rollout.metrics(model.step, p, s, f, t, fn, check=False)[0])
    return {k: np.asarray(v).reshape(len(targets), -1)[:, 0] for k, v in
            run(params, rollout.first_state(model, frames), frames, targets).items()}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=3600)
    p.add_argument("--precision-frames", type=int, default=1000)
    p.add_argument("--size", type=int, default=96)
    p.add_argument("--factor", type=int, default=4)
    args = p.parse_args(argv)
    frames, targets = moving_texture_video(args.frames, args.size, args.factor)
    shipped = loading.load("shipped", args.factor)
    rows, curves = [], {}
    marks = [m for m in (100, 1000, args.frames) if m <= args.frames]
    for system in ("tus", "dlctus"):
        if system == "dlctus" and shipped is None:
            continue
        for w, a in WARPS:
            m = models.build(system, args.factor, warp=w, warp_a=a)
            params = shipped.params if system == "dlctus" else {}
            c = _curve(m, params, frames, targets)
            label = f"{system} {w} a={a}"
            curves[label] = c["psnr"]
            rows.append({"label": label, "finite": bool(np.all(np.isfinite(c["psnr"]))),
                         "min": float(c["min"].min()), "max": float(c["max"].max()),
                         **{f"psnr@{t}": float(np.mean(c["psnr"][t - 20:t])) for t in marks}})
            print(rows[-1])
    growth = []
    kernels = WARPS + (("bicubic", -0.5), ("bicubic5", -0.5))
    for alpha in (0.0, 0.05):
        for w, a in kernels:
            peaks = reprojection_growth(w, a, alpha, args.frames)
            growth.append({"warp": w, "a": a, "alpha": alpha,
                           "finite": bool(np.all(np.isfinite(peaks))),
                           **{f"peak@{t}": float(peaks[:t].max()) for t in marks}})
            print(growth[-1])
    prec = []
    if shipped is not None:
        n = min(args.precision_frames, args.frames)
        sub = jax.tree_util.tree_map(lambda x: x[:n], (frames, targets))
        ref = None
        for dt in ("float32", "bfloat16", "float16"):
            m = models.build("dlctus", args.factor, dtype=dt)
            outs = np.asarray(rollout.video(m, shipped.params, sub[0], check=False))
            if ref is None:
                ref = outs
            prec.append({"dtype": dt, "finite": bool(np.all(np.isfinite(outs))),
                         "max_abs_vs_f32": float(np.abs(outs - ref).max()),
                         "mean_abs_vs_f32": float(np.abs(outs - ref).mean())})
            print(prec[-1])
    table = ["| system, warp | finite | output range | " + " | ".join(
        f"PSNR at frame {t}" for t in marks) + " |", "| --- | --- | --- |" + " --- |" * len(marks)]
    for r in rows:
        table.append(f"| {r['label']} | {r['finite']} | [{r['min']:.3f}, {r['max']:.3f}] | "
                     + " | ".join(f"{r[f'psnr@{t}']:.2f}" for t in marks) + " |")
    table += ["", "Pure reprojection (α = 0: the history warped again and again with no new "
              "input) and with α = 0.05 of fresh input, a zone plate in [0.1, 0.9] at 64x64 "
              "moved (0.37, -0.21) px per warp: the largest |value| reached by each frame "
              "(1 = no growth beyond the image's own overshoot).", "",
              "| warp | a | α | finite | " + " | ".join(f"peak by frame {t}" for t in marks)
              + " |", "| --- | --- | --- | --- |" + " --- |" * len(marks)]
    table += [f"| {g['warp']} | {g['a']} | {g['alpha']} | {g['finite']} | "
              + " | ".join(f"{g[f'peak@{t}']:.3g}" for t in marks) + " |" for g in growth]
    if prec:
        table += ["", f"| DLCTUS dtype ({min(args.precision_frames, args.frames)} frames) | "
                      "finite | max abs diff vs float32 | mean abs diff |",
                  "| --- | --- | --- | --- |"]
        table += [f"| {r['dtype']} | {r['finite']} | {r['max_abs_vs_f32']:.4f} | "
                  f"{r['mean_abs_vs_f32']:.5f} |" for r in prec]
    d = write("stability", "\n".join(table), {"warps": rows, "precision": prec,
                                              "reprojection_growth": growth},
              f"{args.frames} frames of a texture moving (0.37, 0.11) LR px per frame at "
              f"{args.size}x{args.size}, {args.factor}x; PSNR averaged over the 20 frames "
              f"before each mark.")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(9, 4))
    for lab, c in curves.items():
        ax.plot(np.convolve(c, np.ones(20) / 20, mode="valid"), label=lab, lw=1)
    ax.set_xlabel("frame")
    ax.set_ylabel("PSNR (dB), 20-frame mean")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(os.path.join(d, "stability.png"), dpi=100)


if __name__ == "__main__":
    main()
