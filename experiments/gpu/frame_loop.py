"""DLCTUS's whole step as an engine runs it: frame after frame, each frame's history the
last one's output, dispatched without waiting in between (a frame loop), against the
same step waited for after every call (what ``python -m jtus.bench`` times: each
frame's latency, launch included).

    python experiments/gpu/frame_loop.py --out out/gpu/frame-loop.json   # on a GPU

Per size, factor and trunk form (``Config.kernels``): ``latency_ms``, the median of
``--repeats`` single blocked calls, and ``loop_ms``, the median over ``--repeats`` of a
``--frames``-frame loop's time divided by its frames.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import jax

from jtus.bench.workloads import SIZES, infer_workload
from jtus import files
from jtus.timing import hardware_line


def _loop(step, params, state, frame, frames):
    t0 = time.perf_counter()
    for _ in range(frames):
        out, state = step(params, state, frame)
    out.block_until_ready()
    return (time.perf_counter() - t0) / frames, state


def measure(size, factor, dtype, kernels, frames, repeats):
    run, _, model, params, state, frame = infer_workload("dlctus", factor, SIZES[size],
                                                        dtype, kernels=kernels)
    run()
    lat = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        lat.append(time.perf_counter() - t0)
    step = jax.jit(model.step, donate_argnums=(1,))
    s = model.init_state(frame)
    _, s = _loop(step, params, s, frame, 2)  # compile and warm
    loops = []
    for _ in range(repeats):
        t, s = _loop(step, params, s, frame, frames)
        loops.append(t)
    return {"size": size, "factor": factor, "dtype": dtype, "kernels": kernels,
            "latency_ms": 1e3 * statistics.median(lat), "loop_ms": 1e3 * statistics.median(loops)}


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="+", default=["720p", "1080p", "4k"], choices=tuple(SIZES))
    p.add_argument("--factors", nargs="+", type=int, default=[4, 2])
    p.add_argument("--dtypes", nargs="+", default=["bfloat16"])
    p.add_argument("--kernels", nargs="+", default=["xla", "pallas"])
    p.add_argument("--frames", type=int, default=50)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out")
    args = p.parse_args()
    report = {"hardware": hardware_line(), "command": "python experiments/gpu/frame_loop.py "
              + " ".join(sys.argv[1:]), "rows": []}
    for size in args.sizes:
        for f in args.factors:
            for dt in args.dtypes:
                for k in args.kernels:
                    rec = measure(size, f, dt, k, args.frames, args.repeats)
                    print(json.dumps(rec), flush=True)
                    report["rows"].append(rec)
                    if args.out:  # row by row: a run stopped by its time limit keeps its rows
                        with files.atomic_path(args.out) as tmp, open(tmp, "w") as fh:
                            json.dump(report, fh, indent=1)


if __name__ == "__main__":
    main()
