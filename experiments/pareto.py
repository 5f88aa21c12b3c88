"""What accuracy costs in time: every model, reprojection warp and compute dtype, timed
per frame at two resolutions (jitted, warm, median, same run) against PSNR/SSIM on the
test videos, with FLOPs and bytes per frame; a Pareto plot; and the ablations of thesis
Tables 13 (warp), 14 (motion-vector dilation) and 16 (accumulation buffer).

    python experiments/pareto.py                            # shipped DLCTUS, baselines
    python experiments/pareto.py --checkpoint nsrr=experiments/weights/nsrr-x4.msgpack \\
        --checkpoint kpn=experiments/weights/kpn-x4.msgpack --train-ablations

DLCTUS variants reuse the shipped weights (trained with the 16-tap a=-0.75 warp), as
the thesis evaluated its warps with one trained network (Table 13); dilation is also
switched at inference (Table 14). The accumulation-buffer ablation (Table 16) needs
networks trained alike with and without it: ``--train-ablations`` trains both with the
θ sweep's L1 recipe (reusing that sweep's run when it exists).
Learned comparison systems without a ``--checkpoint`` are timed but not scored.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

import numpy as np
from common import ROOT, WARPS, evaluate_videos, l1_recipe, write  # noqa: E402

from jtus import bench, models, recipe, train

DTYPES = ("float32", "bfloat16", "float16")


def _variants(include_dtypes=True):
    out = [("jau", {}), ("jau-bicubic", {}), ("tus", {}), ("tus-clip", {})]
    for dt in (DTYPES if include_dtypes else DTYPES[:1]):
        for w, a in WARPS:
            out.append(("dlctus", {"warp": w, "warp_a": a, "dtype": dt}))
    out.append(("dlctus", {"dilation": True}))
    for name in ("nsrr", "nsrr-fast", "kpn", "mlp"):
        out.append((name, {}))
    return out


def _label(name, over):
    return name + "".join(f" {k}={v}" for k, v in over.items() if k != "warp_a")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--factor", type=int, default=4)
    p.add_argument("--sizes", nargs="+", default=["720p", "1080p"])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--dataset", default=os.path.join(ROOT, "data", "default.h5"))
    p.add_argument("--max-videos", type=int)
    p.add_argument("--checkpoint", action="append", default=[], help="NAME=PATH")
    p.add_argument("--train-ablations", action="store_true")
    p.add_argument("--ablation-epochs", type=int, default=10,
                   help="epochs of 100 steps for each accumulation-ablation network")
    args = p.parse_args(argv)
    ckpts = dict(c.split("=", 1) for c in args.checkpoint)
    shipped = models.load("shipped", args.factor)
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
            params = models.load(f"{name}={ckpts[name]}", args.factor).params
        elif name in ("jau", "jau-bicubic", "tus", "tus-clip"):
            params = {}
        if params is not None:
            rec.update(evaluate_videos(model, params, args.dataset, args.factor,
                                       max_videos=args.max_videos))
        rows.append(rec)
        print(rec)
    if args.train_ablations:
        # Table 16 needs two networks trained alike, with and without the accumulation
        # buffer: the θ sweep's L1 recipe (its run is reused when it exists)
        base, l1_work = l1_recipe(args.factor, args.ablation_epochs, args.dataset)
        for acc, work in ((True, l1_work),
                          (False, os.path.join(ROOT, "runs", "ablation_no_accumulation"))):
            cfg = base if acc else dataclasses.replace(
                base, model_overrides=(("accumulation", False),))
            params, hist = train.train_and_evaluate(cfg, work, resume=True,
                                                    progress=sys.stderr.isatty())
            # a network whose clamped outputs saturate stops learning (docs/weights.md):
            # its validation loss then repeats exactly from epoch to epoch
            collapsed = len(hist) > 2 and len({h["val_loss"] for h in hist[1:]}) == 1
            why = "; collapsed: validation constant from epoch 2" if collapsed else ""
            rec = {"label": f"dlctus accumulation={acc} ({args.ablation_epochs}x100 steps{why})",
                   "model": "dlctus", "collapsed": collapsed}
            rec.update(evaluate_videos(recipe.model_for(cfg), params, args.dataset, args.factor,
                                       max_videos=args.max_videos))
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
              f"on the test split of `{os.path.relpath(args.dataset, ROOT)}`.")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    pts = [(r[f"ms_{big}"], r["psnr"], r["label"]) for r in rows
           if "psnr" in r and f"ms_{big}" in r]
    fig, ax = plt.subplots(figsize=(8, 5))
    for ms, ps, lab in pts:
        ax.scatter(ms, ps)
        ax.annotate(lab, (ms, ps), fontsize=6)
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
    fig.savefig(os.path.join(d, "pareto.png"), dpi=110)


if __name__ == "__main__":
    main()
