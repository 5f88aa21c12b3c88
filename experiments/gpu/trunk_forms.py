"""DLCTUS's trunk in its three forms (``jtus.models.kernels``: XLA convolutions, im2col
matmuls, Pallas/Triton kernels with several tiles and warp counts), timed alone at the
network's resolution of 720p, 1080p and 4K outputs (H/4 x W/4), in bfloat16 and
float32, with a check that each form's values match the XLA trunk's.

    python experiments/gpu/trunk_forms.py --out out/gpu/trunk-forms.json   # on a GPU
    python experiments/gpu/trunk_forms.py --sizes 16x24 --tiles 8x16 --repeats 1  # CPU smoke

Each timing is the median over ``--repeats`` of ``--calls`` calls dispatched back to
back and then waited for (the throughput a frame loop sees). On a CPU the Pallas form
runs in interpret mode (a check, not a speed).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jtus import files
from jtus.models import dlctus, kernels
from jtus.timing import hardware_line


def _pair(text):
    a, b = text.lower().split("x")
    return int(a), int(b)


def _time(fn, x, calls, repeats):
    fn(x).block_until_ready()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(calls):
            y = fn(x)
        y.block_until_ready()
        times.append((time.perf_counter() - t0) / calls)
    return statistics.median(times)


def forms(args, dtype):
    """``{name: trunk function of (weights..., h)}`` to time: every tile and warp count
    in the dtypes of ``--sweep-dtypes``, the default ones in the others."""
    out = {"xla": kernels.trunk_xla, "im2col": kernels.trunk_im2col}
    cpu = jax.default_backend() == "cpu"
    sweep = dtype in args.sweep_dtypes
    for tile in args.tiles if sweep else [kernels.TILE]:
        for warps in args.warps if sweep else [kernels.NUM_WARPS]:
            out[f"pallas-{tile[0]}x{tile[1]}-w{warps}"] = (
                lambda *a, t=tile, w=warps: kernels.trunk_pallas(*a, tile=t, num_warps=w,
                                                                 interpret=cpu))
    return out


def run(args, save):
    params = dlctus.init(jax.random.PRNGKey(0))
    report = {"hardware": hardware_line(), "command": "python experiments/gpu/trunk_forms.py "
              + " ".join(sys.argv[1:]), "rows": []}
    for size in args.sizes:
        for dtype in args.dtypes:
            dt = jnp.dtype(dtype)
            w = [a.astype(dt) for a in kernels.stack_blocks(params, 4)]
            h = jnp.asarray(np.random.default_rng(0).normal(size=(1, *size, 32)), dt)
            ref = None
            for name, trunk in forms(args, dtype).items():
                fn = jax.jit(lambda x, trunk=trunk: trunk(*w, x))
                rec = {"size": f"{size[0]}x{size[1]}", "dtype": dtype, "form": name}
                try:
                    y = np.asarray(fn(h).astype(jnp.float32))
                    ref = y if ref is None else ref
                    rec["max_abs_diff_vs_xla"] = float(np.abs(y - ref).max())
                    rec["ms"] = 1e3 * _time(fn, h, args.calls, args.repeats)
                    flop = 8 * size[0] * size[1] * 32 * 32 * 9 * 2
                    rec["tflops"] = flop / (rec["ms"] / 1e3) / 1e12
                except Exception as e:  # a form that does not compile here: say why
                    rec["error"] = f"{type(e).__name__}: {str(e)[:300]}"
                print(json.dumps(rec), flush=True)
                report["rows"].append(rec)
                save(report)  # row by row: a run stopped by its time limit keeps its rows
    return report


def _save(report, out):
    with files.atomic_path(out) as tmp, open(tmp, "w") as f:
        json.dump(report, f, indent=1)


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sizes", nargs="+", type=_pair, default=[(180, 320), (270, 480), (540, 960)])
    p.add_argument("--dtypes", nargs="+", default=["bfloat16", "float32"])
    p.add_argument("--tiles", nargs="+", type=_pair,
                   default=[(8, 32), (16, 32), (32, 32), (16, 64)])
    p.add_argument("--warps", nargs="+", type=int, default=[4, 8])
    p.add_argument("--sweep-dtypes", nargs="*", default=["bfloat16"],
                   help="dtypes timed with every tile and warp count (others: the defaults)")
    p.add_argument("--calls", type=int, default=20)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out")
    args = p.parse_args()
    run(args, (lambda r: _save(r, args.out)) if args.out else (lambda r: None))


if __name__ == "__main__":
    main()
