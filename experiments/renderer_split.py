"""What casting the targets without depth and motion saves: per scene, XLA's FLOP and
byte counts per point and the compile times of the whole renderer
(``jtus.sim.render.make_renderer``) against the split one
(``make_split_renderer``: ``shade`` for every point, ``geometry`` for the inputs only).

    taskset -c 1 python experiments/renderer_split.py     # docs/results/renderer-split/

Counts do not move with the machine's load; compile times do (one core, one run each).
Both renderers are built ``intersect="unrolled"``, the form XLA's counts describe.
The frames per second side by side with the previous commit are in
``docs/results/target-colour-only/result.md``.
"""

from __future__ import annotations

import argparse
import time

import jax.numpy as jnp
from common import write

from jtus.sim import get_scene, paths, render


def _counts(fn, *args):
    """``(FLOP, bytes, compile seconds)`` of ``fn`` compiled for these arguments."""
    t0 = time.perf_counter()
    cost = render.compiled_cost(fn, *args)
    seconds = time.perf_counter() - t0
    return float(cost["flops"]), float(cost.get("bytes accessed", 0.0)), seconds


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+",
                   default=["camera_orbit", "objects", "everything", "random_3", "random_7"])
    p.add_argument("--points", type=int, default=16384, help="points per call (video.CHUNK)")
    args = p.parse_args(argv)
    n = args.points
    xy = jnp.zeros((n, 2), jnp.float32)
    rows, data = [], {}
    for name in args.scenes:
        scene = get_scene(name)
        state = render.state_arrays(paths.timeline(scene, "train", 0, 1, 1.0)[0])
        # unrolled: every object tested in one expression, the form whose FLOPs XLA
        # counts (the culled renderer's loop body would be counted once)
        whole = _counts(render.make_renderer(scene, intersect="unrolled"), state, xy, 0.01)
        shade, geometry = render.make_split_renderer(scene, intersect="unrolled")
        colour = _counts(shade, state, xy, 0.01)
        geo = _counts(geometry, state, xy, jnp.zeros((n,), jnp.float32),
                      jnp.zeros((n,), jnp.int32))
        rows.append(f"| {name} | {whole[0] / n:,.0f} / {whole[1] / n:,.0f} | "
                    f"{colour[0] / n:,.0f} / {colour[1] / n:,.0f} | {colour[0] / whole[0]:.2f} | "
                    f"{whole[2]:.2f} | {colour[2]:.2f} + {geo[2]:.2f} |")
        data[name] = {"whole": whole, "shade": colour, "geometry": geo}
        print(rows[-1], flush=True)
    table = "\n".join([
        "| scene | whole: FLOP / bytes per point | colour alone: FLOP / bytes per point | "
        "colour / whole FLOP | whole: compile s | shade + geometry: compile s |",
        "| --- | --- | --- | --- | --- | --- |"] + rows)
    write("renderer-split", table, data,
          note=f"XLA's `cost_analysis` of each function compiled for {n} points. The "
               "targets pay the colour column per sample; the inputs pay the whole.")


if __name__ == "__main__":
    main()
