"""Adaptive target supersampling against the uniform 16-sample targets: closeness to
64-sample references (PSNR), rays per pixel and time, on one frame of each of a few
built-in and randomized scenes at 192x192, and of game levels.

    python experiments/adaptive_targets.py --levels oa_dm1 oa_dm4 oacmpdm3 delta
        # test frames and test levels, the default thresholds
    python experiments/adaptive_targets.py --split train --name adaptive-targets-train \\
        --levels aggressor am_galmevish ctf_gate1 kaos oa_dm2 oa_shine --thresholds \\
        0.125,0.25 0.03125,0.25 0.03125,0.125 0.03125,0.0625 0.015625,0.0625
        # how the default was chosen: on train frames and train levels
    python experiments/adaptive_targets.py --picture docs/img/adaptive_targets.png \\
        --levels oa_dm4 delta       # each target beside its samples per pixel

Each column ``t1,t2`` is ``VideoRenderer.adaptive_target`` with those thresholds:
4 rotated-grid samples per pixel, the rest of the 4x4 grid where they disagree by
more than ``t1`` (and around those pixels), an 8x8 grid where the 16 disagree by more
than ``t2``. The references are stratified *jittered* (one uniformly random point in
each cell of an 8x8 and a 24x24 grid per pixel; ``VideoRenderer.jittered_reference``),
so that no estimator shares their sample positions: a regular 8x8 reference would
equal the adaptive target wherever that takes 64 samples, and a regular grid's
aliasing of periodic textures would favour the grids that divide it. The time is the
adaptive target's over the uniform one's, timed alternately in this process (median
of ``--repeats``). Writes ``docs/results/<name>/``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from common import write

from jtus import sim
from jtus.sim import game
from jtus.sim.randomized import random_scene
from jtus.sim.video import ADAPTIVE_THRESHOLDS, VideoRenderer

SCENES = {"fence_pan": lambda: sim.get_scene("fence_pan"),
          "moire_dolly": lambda: sim.get_scene("moire_dolly"),
          "everything": lambda: sim.get_scene("everything"),
          "random_3": lambda: random_scene(3), "random_11": lambda: random_scene(11),
          "random_5 (thin geometry)": lambda: random_scene(
              5, effects=("camera_motion", "thin_geometry", "texture_detail", "shadows"))}


def psnr(a, b):
    return float(-10 * np.log10(np.mean((np.asarray(a, np.float64) - b) ** 2)))


def rays_per_pixel(count):
    """Rays cast per pixel from ``adaptive_target``'s sample counts: a 64-sample pixel
    cast the 16 before them too."""
    return float(np.where(count == 64, 80, count).mean())


def time_ratio(renderer, state, thresholds, repeats):
    """Median over ``repeats`` of the adaptive target's seconds over the uniform's,
    timed one after the other."""
    ratios = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        renderer.target(state)
        t1 = time.perf_counter()
        renderer.adaptive_target(state, thresholds)
        ratios.append((time.perf_counter() - t1) / (t1 - t0))
    return float(np.median(ratios))


def scene_row(name, scene, configs, size, split, repeats):
    """One scene's table row and record: the uniform target and each configuration
    against both references."""
    r = VideoRenderer(scene, (size, size), (4,), 16)
    st = r.timeline(split, 0, 1)[0]
    refs = {"jittered 64": r.jittered_reference(st, 8, seed=1),
            "jittered 576": r.jittered_reference(st, 24, seed=2)}
    uniform = r.target(st)
    rec = {"scene": name, "uniform16": {k: psnr(uniform, v) for k, v in refs.items()}}
    cells = ["{:.2f} / {:.2f}".format(*rec["uniform16"].values())]
    for c in configs:
        t, count = r.adaptive_target(st, c)
        rays = rays_per_pixel(count)
        got = {k: psnr(t, v) for k, v in refs.items()}
        rec[str(c)] = {**got, "rays_per_pixel": rays,
                       "time_ratio": time_ratio(r, st, c, repeats)}
        cells.append("{:.2f} / {:.2f} ({:.1f}; {:.2f}x)".format(
            *got.values(), rays, rec[str(c)]["time_ratio"]))
    return rec, f"| {name} | " + " | ".join(cells) + " |"


def picture(scenes, split, out):
    """Each scene's adaptive target (sRGB) beside its samples per pixel (4 black, 16 grey,
    64 white), one row per scene, as a PNG at ``out``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jtus.data.exr import linear_to_srgb

    fig, axes = plt.subplots(len(scenes), 2, figsize=(4.2, 2.1 * len(scenes)), dpi=100,
                             squeeze=False)
    for row, (name, make, size) in zip(axes, scenes):
        r = VideoRenderer(make(), (size, size), (4,), 16, targets="adaptive")
        target, count = r.adaptive_target(r.timeline(split, 0, 1)[0])
        rays = rays_per_pixel(count)
        row[0].imshow(linear_to_srgb(np.clip(target, 0, 1)), interpolation="nearest")
        row[1].imshow(np.log2(count), cmap="gray", vmin=2, vmax=6, interpolation="nearest")
        row[0].set_ylabel(name, fontsize=9)
        row[1].set_title(f"{rays:.1f} rays per pixel", fontsize=8)
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
    axes[0, 0].set_title("adaptive target", fontsize=8)
    fig.tight_layout(pad=0.3)
    fig.savefig(out)
    plt.close(fig)
    print(f"wrote {out}")


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--thresholds", nargs="+", default=[",".join(map(str, ADAPTIVE_THRESHOLDS))],
                   help="t1,t2 pairs, one column each")
    p.add_argument("--size", type=int, default=192)
    p.add_argument("--levels", nargs="*", default=[], metavar="MAP",
                   help="OpenArena levels to add, rendered at --level-size "
                        "(data/fetch_game_assets.sh first)")
    p.add_argument("--level-size", type=int, default=128)
    p.add_argument("--split", default="test", choices=("train", "val", "test"))
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--name", default="adaptive-targets")
    p.add_argument("--picture", metavar="PNG",
                   help="write each scene's target and samples per pixel here instead")
    args = p.parse_args()
    configs = [tuple(float(x) for x in c.split(",")) for c in args.thresholds]
    if any(len(c) != 2 for c in configs):
        raise SystemExit(f"--thresholds: expected t1,t2 pairs, got {args.thresholds}")
    rows, data = [], []
    scenes = [(name, make, args.size) for name, make in SCENES.items()] + [
        (f"oa:{m}", lambda m=m: game.scene_of(f"oa:{m}"), args.level_size) for m in args.levels]
    if args.picture:
        return picture(scenes, args.split, args.picture)
    for name, make, size in scenes:
        rec, row = scene_row(name, make(), configs, size, args.split, args.repeats)
        data.append(rec)
        rows.append(row)
        print(row, flush=True)
    head = "| scene | uniform 16 | " + " | ".join(
        f"adaptive {t1:.4g}, {t2:.4g}" for t1, t2 in configs) + " |"
    table = "\n".join([head, "| --- " * (len(configs) + 2) + "|"] + rows)
    write(args.name, table, data,
          note=f"Each cell: PSNR (dB) against the jittered 64-sample / 576-sample reference "
               f"of the same frame; for adaptive targets then the rays per pixel and the "
               f"time over the uniform target's in brackets. {args.size}x{args.size} "
               f"({args.level_size}x{args.level_size} for game levels), the first frame of "
               f"each scene's {args.split} video; uniform 16 is 16 rays per pixel.")


if __name__ == "__main__":
    main()
