"""``python -m jtus.sim``: list, preview and render scenes; time the renderer.

    python -m jtus.sim list
    python -m jtus.sim preview --scene fence_pan --out docs/img/fence_pan.png
    python -m jtus.sim preview --all --out docs/img/scenes.png --size 128 --factor 4
    python -m jtus.sim preview --random 0 1 2 3 --out random.png
    python -m jtus.sim show --random 7 > my_scene.json        # a spec to edit
    python -m jtus.sim render --scene my_scene.json --out my.h5 --frames 24
    python -m jtus.sim render --random 123 --effects camera_motion,texture_detail --out r.h5
    python -m jtus.sim fps --preset default
    python -m jtus.sim render --random 123 --targets adaptive --out r.h5   # fewer rays
    python -m jtus.sim cost --out docs/results/sim_cost.json
    python -m jtus.sim render --scene my_level.gltf --out mine.h5 --frames 24
    python -m jtus.sim render --scene oa:oa_dm4 --out dm4.h5   # after data/fetch_game_assets.sh
    python -m jtus.sim levels                                  # the installed game levels

A scene is a built-in name, ``random_<seed>``, a JSON file (``show`` prints one), a
mesh file (``.gltf``, ``.glb``, ``.obj``) or a game level ``oa:<map>``.
``render`` writes the dataset layout of ``docs/data.md`` (the videos in ``--split``),
which ``train``, ``evaluate`` and ``upsample`` read like any generated dataset.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time

import numpy as np
from PIL import Image
from tqdm import tqdm

from jtus import cli, timing
from jtus.data.conventions import linearize_depth
from jtus.data.dataset import SPLITS
from jtus.data.exr import linear_to_srgb
from jtus.files import atomic_path, check_budget, check_out_file
from jtus.sampling.jitter import VARIETY, jitter_sequence
from jtus.sim import SCENES, from_json, game, get_scene, meshfile, random_scene, render, to_json
from jtus.sim.generate import Preset, default_workers, generate, preset, render_budget
from jtus.sim.mesh import MESH_EFFECTS, MeshScene
from jtus.sim.scene import EFFECTS, Scene
from jtus.sim.video import TARGETS, VideoRenderer


def _to_u8(x):
    return np.round(linear_to_srgb(x) * 255).astype(np.uint8)


def resolve(spec, effects=None):
    """A ``Scene`` from a built-in name, ``random_<seed>``, a ``.json`` path or a seed
    (int); or a ``MeshScene`` from a game level ``oa:<map>`` or a ``.gltf``/``.glb``/
    ``.obj`` file. ``effects`` (names) replaces the scene's declared effects."""

    if game.is_level(str(spec)) or str(spec).lower().endswith(meshfile.SUFFIXES):
        if effects is not None:
            bad = [e for e in effects if e not in MESH_EFFECTS]
            if bad:
                raise ValueError(f"effects: unknown {bad}; a mesh scene takes names from "
                                 f"{MESH_EFFECTS}")
        if game.is_level(str(spec)):
            return game.scene_of(str(spec), effects)
        return meshfile.load(spec, effects)
    if effects is not None:
        bad = [e for e in effects if e not in EFFECTS]
        if bad:
            raise ValueError(f"effects: unknown {bad}; expected names from {EFFECTS}")
    if isinstance(spec, int):
        return random_scene(spec, effects)
    if str(spec).endswith(".json") or os.path.sep in str(spec):
        if not os.path.isfile(spec):
            raise FileNotFoundError(f"scene: {spec} does not exist")
        try:
            scene = from_json(spec)
        except json.JSONDecodeError as e:
            raise ValueError(f"scene: {spec} is not valid JSON ({e})") from e
    else:
        scene = get_scene(str(spec))
    return dataclasses.replace(scene, effects=tuple(effects)) if effects is not None else scene


def strip(scene, size=128, factor=4, frame=12, spp=16, split="test"):
    """One row: input (nearest-upscaled), target, motion (x red, y green, 0.5 = still;
    ±2 LR pixels full scale), linear depth (near dark); linear RGB in [0,1].
    ``scene``: a ``Scene`` or anything ``resolve`` takes."""

    scene = scene if isinstance(scene, (Scene, MeshScene)) else resolve(scene)
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


def _scenes_from(args):
    """The scenes an invocation names: ``--scene`` (several), ``--random`` seeds,
    ``--all``; each with ``--effects`` when given."""
    effects = None
    if getattr(args, "effects", None):
        effects = [e.strip() for e in args.effects.split(",") if e.strip()]
    specs = list(args.scene or []) + [int(s) for s in (args.random or [])]
    if getattr(args, "all", False):
        specs += list(SCENES)
    if not specs:
        raise ValueError("scene: give --scene NAME|FILE.json, --random SEED or --all")
    return [resolve(s, effects) for s in specs]


def _check_out(path, force, ext):
    check_out_file(path, force, kind=f"a {ext} file")
    if not path.endswith(ext):
        raise ValueError(f"--out: expected a path ending in {ext}, got {path}")


MAX_SIZE = 16384  # HR frame side: past this a single frame alone needs gigabytes


def _render(args):
    scenes = _scenes_from(args)
    names = [s.name for s in scenes]
    if len(set(names)) != len(names):
        raise ValueError(f"scene: names repeat ({names}); every scene needs its own name")
    _check_out(args.out, args.force, ".h5")
    if args.size < 4 or args.size % 4 or args.size > MAX_SIZE:
        raise ValueError(f"--size: expected a multiple of 4 in [4, {MAX_SIZE}], got {args.size}")
    for f in args.factors:
        if f not in (2, 4):
            raise ValueError(f"--factors: expected 2 and/or 4, got {f}")
    if args.frames < 1 or args.videos < 1 or (args.spp or 1) < 1 or args.workers < 1:
        raise ValueError("--frames, --videos, --spp and --workers: expected positive integers")
    if args.targets == "adaptive" and args.spp is not None:
        raise ValueError("--spp: adaptive targets choose 4, 16 or 64 samples per pixel "
                         "themselves; give --spp only with --targets uniform")
    check_budget(*render_budget(args.size, args.factors, args.frames,
                                len(names) * args.videos, args.workers), args.out,
                 args.force, what="sim render")
    jitters = VARIETY if args.jitter == "variety" else (args.jitter,)
    for j in jitters:
        for f in args.factors:
            jitter_sequence(j, f)  # refuses unknown names before anything renders
    p = Preset((args.size, args.size), tuple(args.factors), args.spp or 16, 1,
               {sp: ((tuple(names) if sp == args.split else ()), args.videos, args.frames)
                for sp in SPLITS}, jitters, targets=args.targets)
    t0 = time.perf_counter()
    generate(p, args.out, progress=not args.quiet, custom={s.name: s for s in scenes},
             workers=args.workers)
    print(f"wrote {args.out}: {len(names)} scene(s) x {args.videos} video(s) x {args.frames} "
          f"frames in split {args.split!r} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    return 0


def _render_args(r):
    """``render``'s options beside the scene ones."""
    r.add_argument("--out", required=True)
    r.add_argument("--force", action="store_true",
                   help="replace an existing --out, and render past the memory and disk check")
    r.add_argument("--frames", type=int, default=24)
    r.add_argument("--videos", type=int, default=1, help="videos per scene (own camera seeds)")
    r.add_argument("--size", type=int, default=256, help="HR frame size (square)")
    r.add_argument("--factors", type=int, nargs="+", default=[2, 4])
    r.add_argument("--spp", type=int, help="target samples per pixel (uniform targets; "
                   "default 16)")
    r.add_argument("--targets", choices=TARGETS, default="uniform",
                   help="uniform: --spp samples in every pixel; adaptive: 4, 16 or 64 "
                        "where the samples disagree (docs/simulator.md)")
    r.add_argument("--workers", type=int, default=default_workers(),
                   help="rendering processes, one per core (default: every core)")
    r.add_argument("--split", default="test", choices=("train", "val", "test"))
    r.add_argument("--jitter", default="thesis",
                   help=f"one of {VARIETY}, halton<N>, or 'variety' (drawn per video)")
    r.add_argument("--quiet", action="store_true")


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m jtus.sim", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("list", help="the built-in scenes and their effects")
    sub.add_parser("levels", help="the installed game levels (data/fetch_game_assets.sh) "
                   "and the effects each declares")

    def scene_args(q, many=True):
        q.add_argument("--scene", nargs="+" if many else 1,
                       help="built-in name, random_<seed> or a .json spec")
        q.add_argument("--random", nargs="+" if many else 1, type=int, metavar="SEED",
                       help="scenes of the randomized family")
        q.add_argument("--effects", help="comma-separated effects replacing the scene's own")

    v = sub.add_parser("preview", help="input | target | motion | depth strip")
    scene_args(v)
    v.add_argument("--all", action="store_true", help="every built-in scene")
    v.add_argument("--out", required=True)
    v.add_argument("--size", type=int, default=128)
    v.add_argument("--factor", type=int, default=4, choices=(2, 4))
    v.add_argument("--frame", type=int, default=12)
    v.add_argument("--spp", type=int, default=16)
    s = sub.add_parser("show", help="print a scene's JSON spec")
    scene_args(s, many=False)
    r = sub.add_parser("render", help="render scenes into an HDF5 dataset")
    scene_args(r)
    _render_args(r)
    f = sub.add_parser("fps", help="rendering speed of a dataset preset on this machine")
    f.add_argument("--preset", default="default")
    f.add_argument("--frames", type=int, default=6)
    f.add_argument("--targets", choices=TARGETS, help="override the preset's targets")
    c = sub.add_parser("cost", help="rendering time per frame with each effect alone")
    c.add_argument("--seed", type=int, default=3, help="random scene to measure")
    c.add_argument("--size", type=int, default=192)
    c.add_argument("--frames", type=int, default=4)
    c.add_argument("--out", help="write the table as JSON here")
    c.add_argument("--level", metavar="MAP",
                   help="measure a game level's mesh effects instead (oa_dm4, ...): no "
                        "FLOP count, the mesh path is not XLA")
    args = p.parse_args(argv)
    cli.sigterm_as_exit()
    try:
        return _dispatch(args)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def _dispatch(args):
    if args.cmd == "list":
        for name in SCENES:
            print(f"{name:14s} {', '.join(get_scene(name).effects)}")
        print("random_<seed> (the randomized family: python -m jtus.sim show --random SEED)")
        return 0
    if args.cmd == "levels":
        for m in game.levels():
            split = ("val" if m in game.VAL_LEVELS else "test" if m in game.TEST_LEVELS
                     else "train")
            effects = game.scene_of(game.PREFIX + m).effects
            print(f"{game.PREFIX + m:20s} {split:5s} {', '.join(effects)}")
        return 0
    if args.cmd == "show":
        print(to_json(_scenes_from(args)[0]))
        return 0
    if args.cmd == "preview":

        scenes = _scenes_from(args)
        if os.path.isdir(args.out):
            raise ValueError(f"--out: {args.out} is a folder; expected an image path")
        rows = [strip(sc, args.size, args.factor, args.frame, args.spp) for sc in scenes]
        Image.fromarray(_to_u8(np.concatenate(rows, 0))).save(args.out)
        print(f"wrote {args.out}")
        return 0
    if args.cmd == "render":
        return _render(args)
    if args.cmd == "cost":
        return _cost(args)
    return _fps(args.preset, args.frames, args.targets)


def effect_costs(seed=3, size=192, frames=4, factors=(2, 4), spp=16):
    """Per row (no effect, each effect alone, all of them) of random scene ``seed``:
    ``(label, effects, FLOPs per screen point, seconds per frame)``, the FLOPs XLA's
    count for the compiled renderer (``render.flops_per_point``), the seconds warm
    (compiling excluded) for the inputs at every factor and the target."""

    base = random_scene(seed, effects=EFFECTS)
    return _timed_rows(EFFECTS, lambda fx: dataclasses.replace(base, effects=fx), size,
                       frames, factors, spp, render.flops_per_point)


def mesh_effect_costs(level, size=128, frames=3, factors=(2, 4), spp=16):
    """``effect_costs`` for game level ``level`` over ``MESH_EFFECTS`` (FLOPs None:
    the mesh path is numpy and Embree)."""
    return _timed_rows(MESH_EFFECTS, lambda fx: game.scene_of(game.PREFIX + level, fx), size,
                       frames, factors, spp, lambda scene: None)


def _timed_rows(effects, scene_with, size, frames, factors, spp, flops):
    """``(label, effects, flops(scene), seconds per frame)`` for no effect, each of
    ``effects`` alone and all of them; the first frame of each row is not timed."""
    rows = [("none", ())] + [(e, (e,)) for e in effects] + [("all", effects)]
    out = []
    for label, fx in tqdm(rows, desc="effects", leave=False):
        scene = scene_with(fx)
        r = VideoRenderer(scene, (size, size), factors, spp)
        r.video("train", 0, 1)  # compile (analytic scenes), warm caches
        t0 = time.perf_counter()
        r.video("train", 0, frames)
        seconds = (time.perf_counter() - t0) / frames
        out.append((label, fx, flops(scene), seconds))
    return out


def cost_table(rows):
    """The Markdown table of ``effect_costs`` rows, with a header row."""
    flops0, sec0 = rows[0][2], rows[0][3]
    lines = ["| effects | FLOP per point (XLA) | x no effect | ms per frame | x no effect |",
             "| --- | --- | --- | --- | --- |"]
    lines += [f"| {label} | {'-' if fl is None else f'{fl:,.0f}'} | "
              f"{'-' if fl is None else f'{fl / flops0:.2f}'} | {sec * 1e3:.0f} | "
              f"{sec / sec0:.2f} |" for label, _, fl, sec in rows]
    return "\n".join(lines)


def _cost(args):
    machine = timing.hardware_line()
    if args.level:
        rows = mesh_effect_costs(args.level, args.size, args.frames)
        what = f"{game.PREFIX}{args.level}"
    else:
        rows = effect_costs(args.seed, args.size, args.frames)
        what = f"random_{args.seed}"
    print(f"{what}, {args.size}x{args.size}, inputs at 2x and 4x + 16-spp target, "
          f"{args.frames} frames ({machine})")
    print(cost_table(rows))
    if args.out:
        with atomic_path(args.out) as tmp, open(tmp, "w") as fh:
            json.dump({"scene": what, "seed": None if args.level else args.seed,
                       "size": args.size, "frames": args.frames,
                       "machine": machine,
                       "rows": [{"effects": label, "flops_per_point": fl,
                                 "ms_per_frame": sec * 1e3}
                                for label, _, fl, sec in rows]}, fh, indent=1)
        print(f"wrote {args.out}")
    return 0


def _fps(preset_name, frames, targets=None):
    """Frames per second of rendering a preset's videos (every factor and the
    target), warm, averaged over the built-in scenes; ``targets`` overrides the
    preset's."""
    p = preset(preset_name)
    p = dataclasses.replace(p, targets=targets or p.targets)
    total, n = 0.0, 0
    for name in SCENES:
        r = VideoRenderer(get_scene(name), p.size, p.factors, p.spp, p.spp_match,
                          targets=p.targets)
        r.video("train", 0, 1)  # compile
        t0 = time.perf_counter()
        r.video("train", 1, frames)
        total += time.perf_counter() - t0
        n += frames
    spp = "adaptive targets" if p.targets == "adaptive" else f"{p.spp} spp"
    print(f"preset {preset_name}: {p.size[0]}x{p.size[1]}, factors {p.factors}, {spp}: "
          f"{n / total:.2f} frames/s over {len(SCENES)} scenes x {frames} frames "
          f"({platform.processor() or platform.machine()})")
    return 0


if __name__ == "__main__":
    cli.run(main)
