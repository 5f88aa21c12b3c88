"""Adaptive target supersampling against the uniform 16-sample targets: closeness to a
64-sample reference (PSNR) and rays per pixel, on one frame of each of a few built-in
and randomized scenes at 192x192.

    python experiments/adaptive_targets.py
    python experiments/adaptive_targets.py --configs 9,16,0.0078125 4,36,0.015625

Each adaptive configuration ``base,refined,threshold`` renders ``base`` stratified
samples per pixel, then ``refined`` samples in the pixels whose samples disagree by
more than ``threshold`` (tone-mapped) and their neighbours
(``VideoRenderer.adaptive_target``). Writes ``docs/results/adaptive-targets/``.
"""

from __future__ import annotations

import argparse

import numpy as np
from common import write

from jtus import sim
from jtus.sim import paths
from jtus.sim.randomized import random_scene
from jtus.sim.video import VideoRenderer, subsample_offsets

SCENES = {"fence_pan": lambda: sim.get_scene("fence_pan"),
          "moire_dolly": lambda: sim.get_scene("moire_dolly"),
          "everything": lambda: sim.get_scene("everything"),
          "random_3": lambda: random_scene(3), "random_11": lambda: random_scene(11),
          "random_5 (thin geometry)": lambda: random_scene(
              5, effects=("camera_motion", "thin_geometry", "texture_detail", "shadows"))}


def psnr(a, b):
    return float(-10 * np.log10(np.mean((np.asarray(a, np.float64) - b) ** 2)))


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--configs", nargs="+", default=["4,36,0.015625", "4,36,0.00390625",
                                                    "9,16,0.0078125", "9,25,0.0078125",
                                                    "4,16,0.001953125"])
    p.add_argument("--size", type=int, default=192)
    args = p.parse_args()
    configs = [(int(b), int(r), float(t)) for b, r, t in (c.split(",") for c in args.configs)]
    n = args.size
    rows, data = [], []
    for name, make in SCENES.items():
        scene = make()
        r = VideoRenderer(scene, (n, n), (4,), 16)
        st = paths.timeline(scene, "test", 0, 1, 1.0)[0]
        ref = _reference(r, st, n)
        rec = {"scene": name, "uniform16": psnr(r.target(st), ref)}
        cells = [f"{rec['uniform16']:.2f} (16)"]
        for c in configs:
            t, share = r.adaptive_target(st, *c)
            rec[str(c)] = {"psnr": psnr(t, ref), "spp": c[0] + share * c[1], "share": share}
            cells.append(f"{rec[str(c)]['psnr']:.2f} ({rec[str(c)]['spp']:.1f})")
        data.append(rec)
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
        print(rows[-1], flush=True)
    head = "| scene | uniform 16 | " + " | ".join(
        f"adaptive {b}/{r}, {t:.4g}" for b, r, t in configs) + " |"
    table = "\n".join([head, "| --- " * (len(configs) + 2) + "|"] + rows)
    write("adaptive-targets", table, data,
          note=f"Each cell: PSNR (dB) against a 64-sample target of the same frame, then "
               f"the average samples per pixel in brackets; {n}x{n}, the first frame of "
               f"each scene's test video.")


def _reference(r, state, n):
    """The 64-sample (8x8 stratified) target of the frame."""
    jy, jx = np.divmod(np.arange(n * n, dtype=np.float32), np.float32(n))
    acc = np.zeros((n * n, 3))
    offsets = subsample_offsets(64)
    for ox, oy in offsets:
        acc += r.points(state, np.stack([(jx + ox) / n, (jy + oy) / n], -1))["color"]
    return (acc / len(offsets)).reshape(n, n, 3)


if __name__ == "__main__":
    main()
