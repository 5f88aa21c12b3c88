"""What accuracy costs in time: every model, reprojection warp and compute dtype, timed
per frame at two resolutions (jitted, warm, median, same run) against PSNR/SSIM on the
test videos, with FLOPs and bytes per frame; a Pareto plot; and thesis Tables 13 (warp)
and 14 (motion-vector dilation) at inference.

    python experiments/pareto.py          # shipped DLCTUS, baselines, trained comparison

DLCTUS variants reuse the shipped weights (trained with the 16-tap a=-0.75 warp), as
the thesis evaluated its warps with one trained network (Table 13); dilation is also
switched at inference (Table 14). The learned comparison systems are scored with their
trained parameters in ``experiments/weights/<name>-x<F>.msgpack`` (``--checkpoint
NAME=PATH`` for others); one without parameters is timed but not scored. Quality is on
the randomized scenes' unseen test seeds of ``data/diverse.h5`` (``--videos``), the
first column of the README's table. Networks trained with and without the warp or the
accumulation buffer (Tables 13 and 16 with retraining) are ``experiments/ablations.py``.
"""

from __future__ import annotations

import argparse
import os

import numpy as np
from common import ROOT, WARPS, weights_path, write

from jtus import bench, evaluate, loading, models

DTYPES = ("float32", "bfloat16", "float16")
LEARNED = ("nsrr", "nsrr-fast", "kpn", "mlp")  # scored with experiments/weights/


def _variants(include_dtypes=True):
    out = [("jau", {}), ("jau-bicubic", {}), ("tus", {}), ("tus-clip", {})]
    for dt in (DTYPES if include_dtypes else DTYPES[:1]):
        for w, a in WARPS:
            out.append(("dlctus", {"warp": w, "warp_a": a, "dtype": dt}))
    out.append(("dlctus", {"dilation": True}))
    for name in LEARNED:
        out.append((name, {}))
    return out


def default_checkpoints(factor):
    """``{name: path}`` of the trained comparison systems in ``experiments/weights/``."""
    out = {}
    for name in LEARNED:
        path = os.path.join(ROOT, weights_path(name, factor))
        if os.path.exists(path):
            out[name] = path
    return out


def _label(name, over):
    return name + "".join(f" {k}={v}" for k, v in over.items() if k != "warp_a")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--factor", type=int, default=4)
    p.add_argument("--sizes", nargs="+", default=["720p", "1080p"])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--dataset", default=os.path.join(ROOT, "data", "diverse.h5"))
    p.add_argument("--videos", default="random_*",
                   help="test videos scored (a glob on their names)")
    p.add_argument("--max-videos", type=int)
    p.add_argument("--checkpoint", action="append", default=[],
                   help="NAME=PATH (default: experiments/weights/NAME-x<F>.msgpack)")
    p.add_argument("--plot-only", action="store_true",
                   help="redraw pareto.png from the committed result.json and exit")
    args = p.parse_args(argv)
    if args.plot_only:
        plot_only()
        return
    ckpts = default_checkpoints(args.factor)
    for c in args.checkpoint:
        if "=" not in c:
            p.error(f"--checkpoint: expected NAME=PATH, got {c!r}")
        ckpts.update([c.split("=", 1)])
    shipped = loading.load("shipped", args.factor)
    rows = []
    for name, over in _variants():
        rec = {"label": _label(name, over), "model": name}
        for size in args.sizes:
            t = bench.bench_infer(name, args.factor, bench.SIZES[size], args.repeats,
                                  **({"dtype": over["dtype"]} if "dtype" in over else {}),
                                  **{k: v for k, v in over.items() if k != "dtype"})
            rec[f"ms_{size}"] = t["ms"]
            rec[f"gflop_{size}"] = t["gflop"]
            rec[f"mbytes_{size}"] = t["mbytes"]
        model = models.build(name, args.factor, **over)
        params = None
        if name == "dlctus" and shipped is not None:
            params = shipped.params
        elif name in ckpts:
            params = loading.load(f"{name}={ckpts[name]}", args.factor).params
        elif name in ("jau", "jau-bicubic", "tus", "tus-clip"):
            params = {}
        if params is not None:
            rec.update(evaluate.video_means(model, params, args.dataset, args.factor,
                                       max_videos=args.max_videos, videos=args.videos))
        rows.append(rec)
        print(rec)
    big = args.sizes[-1]
    table = [f"| system | ms/frame {' | ms/frame '.join(args.sizes)} | GFLOP/frame ({big}) | "
             f"MB/frame ({big}) | PSNR (dB) | SSIM | temporal |",
             "| --- |" + " --- |" * (len(args.sizes) + 5)]
    for r in rows:
        times = " | ".join(f"{r[f'ms_{s}']:.1f}" if f"ms_{s}" in r else "" for s in args.sizes)
        q = (f"{r['psnr']:.2f} | {r['ssim']:.4f} | {r['temporal']:.5f}" if "psnr" in r
             else "not trained | | ")
        table.append(f"| {r['label']} | {times} | {r.get(f'gflop_{big}', float('nan')):.2f} | "
                     f"{r.get(f'mbytes_{big}', float('nan')):.1f} | {q} |")
    d = write("pareto", "\n".join(table), rows,
              f"{args.factor}x; times at the listed HR sizes, median of {args.repeats}; quality "
              f"on the test videos `{args.videos}` of `{os.path.relpath(args.dataset, ROOT)}`"
              f"; parameters: " + ", ".join(f"{k} `{os.path.relpath(v, ROOT)}`"
                                            for k, v in sorted(ckpts.items())) + ".")
    plot(rows, big, os.path.join(d, "pareto.png"))


def plot(rows, big, path):
    """PSNR against ms per frame at size ``big`` (log), with the Pareto front. The DLCTUS
    variants (warps, dtypes, dilation: within 0.1 dB of each other) are drawn in one
    colour and labelled once, by their fastest; the others each by name."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    pts = [(r[f"ms_{big}"], r["psnr"], r["label"]) for r in rows
           if "psnr" in r and f"ms_{big}" in r]
    fig, ax = plt.subplots(figsize=(8, 5))
    ours = sorted(p for p in pts if p[2].startswith("dlctus"))
    for ms, ps, lab in pts:
        if lab.startswith("dlctus"):
            ax.scatter(ms, ps, color="tab:red", s=14)
        else:
            ax.scatter(ms, ps, color="tab:blue")
            ax.annotate(lab, (ms, ps), fontsize=7, xytext=(4, -3), textcoords="offset points")
    if ours:
        ax.annotate(f"dlctus ({len(ours)} variants: warp, dtype, dilation;\n"
                    f"fastest: {ours[0][2].removeprefix('dlctus ')})",
                    (ours[0][0], ours[0][1]), fontsize=7, xytext=(-10, -24),
                    textcoords="offset points", color="tab:red")
    front, best = [], -np.inf
    for ms, ps, _ in sorted(pts):
        if ps > best:
            front.append((ms, ps))
            best = ps
    if front:
        ax.plot(*zip(*front), "k--", lw=1, label="Pareto front")
    ax.set_xscale("log")
    ax.set_xlabel(f"ms per frame at {big} (log)")
    ax.set_ylabel("test PSNR (dB)")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_only(result_dir=None):
    """Redraw ``pareto.png`` from the ``result.json`` beside it (no timing, no scoring)."""
    import json
    d = result_dir or os.path.join(ROOT, "docs", "results", "pareto")
    with open(os.path.join(d, "result.json")) as fh:
        rows = json.load(fh)
    sizes = [k.removeprefix("ms_") for k in rows[0] if k.startswith("ms_")]
    plot(rows, sizes[-1], os.path.join(d, "pareto.png"))


if __name__ == "__main__":
    main()
