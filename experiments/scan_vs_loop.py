"""A whole video through each model two ways: ``rollout.outputs`` (one ``lax.scan``
over the frames, what ``rollout.video`` runs for figures and ``jtus.upsample``) against
the same jitted step called from a Python loop, on a rendered static hold of the
``textures`` scene. Both give the same outputs up to float32 rounding (their largest
difference is reported; programs fused differently may round differently); the times
per frame show where XLA:CPU compiles a model's step worse inside the scan than alone.

    python experiments/scan_vs_loop.py --name scan-vs-loop

Writes ``docs/results/<name>/result.md`` and ``result.json``.
"""

from __future__ import annotations

import argparse
import functools

import jax
import jax.numpy as jnp
import numpy as np

from common import write
from jtus import models, rollout, sim, timing
from jtus.sim.video import VideoRenderer, static_hold


def per_frame(name, frames, repeats):
    """``(scan s, loop s, largest |difference|)`` per frame of model ``name`` (initialized
    parameters) over ``frames``; raises if the two differ by more than float32
    rounding (1e-6)."""
    model = models.build(name, 4)
    params = model.init(jax.random.PRNGKey(0)) if name in models.TRAINABLE else {}
    scan = functools.partial(rollout.video, model, check=False)  # compiled once per model
    step = jax.jit(model.step)

    def loop(p, f):
        s, outs = rollout.first_state(model, f), []
        for t in range(f.color.shape[0]):
            out, s = step(p, s, jax.tree_util.tree_map(lambda x: x[t], f))
            outs.append(out)
        return jnp.stack(outs)

    a, b = np.asarray(scan(params, frames)), np.asarray(loop(params, frames))
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)
    t = timing.timeit_round_robin({"scan": lambda: scan(params, frames).block_until_ready(),
                                   "loop": lambda: loop(params, frames).block_until_ready()},
                                  repeats)
    n = frames.color.shape[0]
    return t["scan"] / n, t["loop"] / n, float(np.abs(a - b).max())


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--models", nargs="+", default=["jau", "tus", "tus-mean", "kpn", "dlctus"])
    p.add_argument("--sizes", nargs="+", type=int, default=[128, 256])
    p.add_argument("--frames", type=int, default=48)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--name", default="scan-vs-loop")
    args = p.parse_args(argv)
    scene = sim.get_scene("textures")
    rows, data = [], []
    for size in args.sizes:
        r = VideoRenderer(scene, (size, size), (4,), 16)
        frames, _ = static_hold(scene, size, 4, "halton8", args.frames, renderer=r)
        frames = jax.tree_util.tree_map(jnp.asarray, frames)
        for name in args.models:
            scan, loop, diff = per_frame(name, frames, args.repeats)
            rows.append(f"| {name} | {size}x{size} | {1e3 * scan:.2f} | {1e3 * loop:.2f} | "
                        f"{scan / loop:.2f} | {diff:.1e} |")
            data.append({"model": name, "size": size, "scan_s": scan, "loop_s": loop,
                         "max_abs_diff": diff})
            print(rows[-1], flush=True)
    table = ("| model | HR size | scan ms/frame | loop ms/frame | scan / loop | largest "
             "difference |\n| --- | --- | --- | --- | --- | --- |\n" + "\n".join(rows))
    write(args.name, table, data, note=(
        f"{args.frames} frames of a static hold (4x, Halton(2,3) x8), one video (B=1), "
        f"medians of {args.repeats} alternating runs."))


if __name__ == "__main__":
    main()
