"""The θ sweep (thesis Table 10): DLCTUS trained with L1 and with L_st-linear θ on the
same data and seeds, scored by L_st-linear at θ=0 (spatial) and θ=1 (temporal), PSNR
and SSIM over the test videos.

    python experiments/sweep_theta.py                       # θ in 0.1 0.5 0.9, 4x
    python experiments/sweep_theta.py --thetas 0.2 0.8 --factor 2 --epochs 8
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

from common import ROOT, l1_recipe, write

from jtus import evaluate, recipe, train


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--thetas", type=float, nargs="+", default=[0.1, 0.5, 0.9])
    p.add_argument("--factor", type=int, default=4)
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--steps-per-epoch", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dataset", default=os.path.join(ROOT, "data", "default.h5"))
    p.add_argument("--max-videos", type=int)
    args = p.parse_args(argv)
    base, _ = l1_recipe(args.factor, args.epochs, args.dataset, args.steps_per_epoch, args.seed)
    runs = [("L1", base)] + [(f"L_st-linear θ={t}", dataclasses.replace(base, loss="st-linear",
                                                                       theta=t))
                             for t in args.thetas]
    rows = {}
    for label, config in runs:
        work = os.path.join(ROOT, "runs", "sweep_theta", label.replace(" ", "_").replace("=", ""))
        params, _ = train.train_and_evaluate(config, work, resume=True,
                                              progress=sys.stderr.isatty())
        rows[label] = evaluate.video_means(recipe.model_for(config), params, args.dataset,
                                           args.factor, max_videos=args.max_videos)
    table = ["| loss | L_st-linear θ=0 (spatial) | L_st-linear θ=1 (temporal) | PSNR (dB) | SSIM |",
             "| --- | --- | --- | --- | --- |"]
    for label, r in rows.items():
        table.append(f"| {label} | {r['spatial']:.5f} | {r['temporal']:.5f} | {r['psnr']:.2f} | "
                     f"{r['ssim']:.4f} |")
    d = write("theta", "\n".join(table), rows,
              f"DLCTUS {args.factor}x, {args.epochs} epochs x {args.steps_per_epoch} steps per "
              f"run, seed {args.seed}; test split of `{os.path.relpath(args.dataset, ROOT)}`.")
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 4))
    for label, r in rows.items():
        ax.scatter(r["spatial"], r["temporal"], label=label)
    ax.set_xlabel("spatial error (L_st-linear, θ=0)")
    ax.set_ylabel("temporal error (L_st-linear, θ=1)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(os.path.join(d, "theta.png"), dpi=100)


if __name__ == "__main__":
    main()
