"""``python -m jtus.sim``: list the built-in scenes, preview them as image strips.

    python -m jtus.sim list
    python -m jtus.sim preview --scene fence_pan --out docs/img/fence_pan.png
    python -m jtus.sim preview --all --out docs/img/scenes.png --size 128 --factor 4
    python -m jtus.sim fps --preset default
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def _to_u8(x):
    from jtus.data.exr import _srgb
    return np.round(_srgb(x) * 255).astype(np.uint8)


def strip(scene_name, size=128, factor=4, frame=12, spp=16, split="test"):
    """One row: input (nearest-upscaled), target, motion (x red, y green, 0.5 = still;
    ±2 LR pixels full scale), linear depth (near dark); linear RGB in [0,1]."""
    from jtus.data.conventions import linearize_depth
    from jtus.sim import get_scene
    from jtus.sim.video import VideoRenderer

    scene = get_scene(scene_name)
    r = VideoRenderer(scene, (size, size), (factor,), spp)
    v = r.video(split, 0, frame + 1)
    x = v[f"x{factor}"]
    up = lambda a: np.repeat(np.repeat(a, factor, 0), factor, 1)  # noqa: E731
    mv = np.clip(0.5 + x["motion"][-1] / 4.0, 0, 1)
    mv = np.concatenate([mv, np.full(mv.shape[:2] + (1,), 0.5)], -1)
    lin = linearize_depth(x["depth"][-1].astype(np.float64), scene.near, scene.far)
    lin = np.clip(lin / max(np.percentile(lin, 95), 1e-6), 0, 1)
    return np.concatenate([up(x["color"][-1]), v["target"][-1], up(mv), up(np.repeat(lin, 3, -1))
                           ], 1)


def main(argv=None):
    from PIL import Image

    from jtus.sim import SCENES, get_scene

    p = argparse.ArgumentParser(prog="python -m jtus.sim", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list", help="the built-in scenes and their effects")
    v = sub.add_parser("preview", help="input | target | motion | depth strip")
    v.add_argument("--scene", choices=SCENES)
    v.add_argument("--all", action="store_true")
    v.add_argument("--out", required=True)
    v.add_argument("--size", type=int, default=128)
    v.add_argument("--factor", type=int, default=4)
    v.add_argument("--frame", type=int, default=12)
    v.add_argument("--spp", type=int, default=16)
    f = sub.add_parser("fps", help="rendering speed of a dataset preset on this machine")
    f.add_argument("--preset", default="default")
    f.add_argument("--frames", type=int, default=6)
    args = p.parse_args(argv)
    if args.cmd == "list":
        for name in SCENES:
            print(f"{name:14s} {', '.join(get_scene(name).effects)}")
        return 0
    if args.cmd == "preview":
        if not args.all and not args.scene:
            p.error("preview: give --scene NAME or --all")
        names = SCENES if args.all else (args.scene,)
        rows = [strip(n, args.size, args.factor, args.frame, args.spp) for n in names]
        Image.fromarray(_to_u8(np.concatenate(rows, 0))).save(args.out)
        print(f"wrote {args.out}")
        return 0
    return _fps(args.preset, args.frames)


def _fps(preset_name, frames):
    """Frames per second of rendering a preset's videos (every factor and the
    target), warm, averaged over the built-in scenes."""
    import platform

    from jtus.data.dataset import preset
    from jtus.sim import SCENES, get_scene
    from jtus.sim.video import VideoRenderer

    p = preset(preset_name)
    total, n = 0.0, 0
    for name in SCENES:
        r = VideoRenderer(get_scene(name), p.size, p.factors, p.spp, p.spp_match)
        r.video("train", 0, 1)  # compile
        t0 = time.perf_counter()
        r.video("train", 1, frames)
        total += time.perf_counter() - t0
        n += frames
    print(f"preset {preset_name}: {p.size[0]}x{p.size[1]}, factors {p.factors}, {p.spp} spp: "
          f"{n / total:.2f} frames/s over {len(SCENES)} scenes x {frames} frames "
          f"({platform.processor() or platform.machine()})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
