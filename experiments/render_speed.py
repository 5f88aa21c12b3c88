"""The renderer's speed in this checkout against another one (an earlier commit in a
``git worktree``), side by side: per scene, seconds per frame of a preset's videos
(the 16-spp target and the inputs of every factor; compiles excluded), each checkout
in its own process, alternating, so that both see the same machine.

    git worktree add /tmp/base <commit>
    taskset -c 1 python experiments/render_speed.py --base /tmp/base --name NAME

Scenes: built-in names and ``random_<seed>``; the default set is the `default`
preset's 13 scenes and 6 scenes of the randomized family (the `diverse` preset's).
Writes ``docs/results/NAME/result.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

from common import ROOT, write

SCENES = ("random_3", "random_7", "random_11", "random_12", "random_13", "random_21")


def child(args):
    """Runs inside the checkout measured: prints ``{scene: seconds per frame}``."""
    import time

    from jtus import sim
    from jtus.sim.generate import preset
    from jtus.sim.video import VideoRenderer

    p = preset(args.preset)
    out = {}
    for name in args.scenes:
        scene = (sim.random_scene(int(name.split("_")[1])) if name.startswith("random_")
                 else sim.get_scene(name))
        r = VideoRenderer(scene, p.size, p.factors, p.spp, p.spp_match)
        r.video("train", 0, 1)  # compile
        t0 = time.perf_counter()
        r.video("train", 1, args.frames)
        out[name] = (time.perf_counter() - t0) / args.frames
    print(json.dumps(out))


def run(checkout, args):
    cmd = [sys.executable, os.path.abspath(__file__), "--child", "--preset", args.preset,
           "--frames", str(args.frames), "--scenes", *args.scenes]
    env = {**os.environ, "PYTHONPATH": checkout}
    res = subprocess.run(cmd, cwd=checkout, env=env, check=True, capture_output=True,
                         text=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--base", help="the checkout to compare with (a git worktree)")
    p.add_argument("--name", default="render-speed", help="docs/results/NAME/")
    p.add_argument("--preset", default="diverse", help="size, factors and spp to render")
    p.add_argument("--scenes", nargs="+", default=None)
    p.add_argument("--frames", type=int, default=2, help="frames per scene and round")
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.scenes is None:
        from jtus.sim import SCENES as BUILT_IN
        args.scenes = list(SCENES) + list(BUILT_IN)
    if args.child:
        return child(args)
    if not args.base or not os.path.isdir(os.path.join(args.base, "jtus")):
        p.error("--base: expected a checkout of jtus (a folder holding jtus/)")
    times = {"this": [], "base": []}
    for _ in range(args.rounds):
        for label, checkout in (("base", os.path.abspath(args.base)), ("this", ROOT)):
            times[label].append(run(checkout, args))
            print(label, times[label][-1], flush=True)
    med = {k: {s: statistics.median(r[s] for r in v) for s in args.scenes}
           for k, v in times.items()}
    rows = [f"| {s} | {med['base'][s]:.3f} | {med['this'][s]:.3f} | "
            f"{med['base'][s] / med['this'][s]:.2f} |" for s in args.scenes]
    group = {"randomized": [s for s in args.scenes if s.startswith("random_")],
             "hand-made": [s for s in args.scenes if not s.startswith("random_")]}
    for g, names in group.items():
        if names:
            b = sum(med["base"][s] for s in names)
            t = sum(med["this"][s] for s in names)
            rows.append(f"| **{g}, {len(names)} scenes (sum)** | {b:.3f} | {t:.3f} | "
                        f"**{b / t:.2f}** |")
    table = "\n".join(["| scene | base s/frame | this s/frame | base / this |",
                       "| --- | --- | --- | --- |"] + rows)
    write(args.name, table, {"median": med, "runs": times},
          note=f"Preset `{args.preset}` (sizes, factors, samples per pixel), {args.frames} "
               f"frames per scene after a compiling frame, medians of {args.rounds} rounds; "
               "each round runs the base checkout's process, then this one's.")


if __name__ == "__main__":
    main()
