"""The thesis's ablations at the `diverse` recipe, over several seeds, with collapsed
runs reported and replaced:

- ``accumulation``: DLCTUS with and without its accumulation buffer (thesis Table 16);
- ``warp``: the history reprojected bilinearly or with the 16-tap bicubic (a=-0.75),
  each network trained with its own warp (thesis Table 13);
- ``theta``: L1 against L_st-linear at several θ (thesis Table 10).

    python experiments/ablations.py --study accumulation            # 3 seeds each, 4x
    python experiments/ablations.py --study warp --seeds 0 1 2 --epochs 10
    python experiments/ablations.py --study theta --thetas 0.1 0.5 0.9 --seeds 0 1 2
    python experiments/ablations.py --study warp --variants bilinear   # one core's share

Every run is the ``diverse`` preset (randomized scenes, every jitter sequence, crop
128, TBPTT windows of 8 over 16 frames, warm-up and cosine decay, clipping) with
``--epochs`` x ``--steps-per-epoch`` steps (the schedule scales to it) at learning rate
``--lr`` (3e-4, not the preset's 1e-3: at 1e-3 every network without the buffer, 4 of
4, and 2 of 5 with it collapsed in their first epoch; at 3e-4, 1 of 5 probes, a seed
that collapsed at 1e-3 too; ``experiments/collapse_probe.py``,
``docs/results/collapse-probe/``), in
``runs/ablation-<study>/<variant>-s<seed>/`` (``ablation-<study>-lr<lr>`` at another
learning rate; resumed when it exists; a variant that
trains the same network as one of an earlier study, DLCTUS as the recipe has it, reuses
that run: ``run_of``). A run whose
network collapsed (``jtus.train.collapsed``: a gradient norm that stays at zero, or a
validation loss that stops changing) stops training at that epoch, is reported, not
averaged, and a run with the next unused seed takes its place, up to ``--max-extra``
extra seeds per variant.
Scores: PSNR, SSIM and the spatial / temporal errors over the first ``--max-videos``
videos of the test split (never trained or tuned on), mean and standard deviation
over the seeds that trained. Writes ``docs/results/ablation-<study>/result.{md,json}``.

A study spans sessions: ``--save-only`` copies every run's checkpoint, config and log
to ``experiments/checkpoints/ablation-<study>/<variant>-s<seed>/`` (about 1 MB each, to
commit) and exits; a run whose workdir holds no checkpoint starts from that copy.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys

import numpy as np
from common import (LR, ROOT, SAVED, copy_run, run_of, save_runs, saved_dir, slug, study_name,
                    variants, write)

from jtus import evaluate, recipe, train
from jtus.config import PRESETS

METRICS = ("psnr", "ssim", "spatial", "temporal")
# The thesis's PSNR (dB) for each study's variants, with the setting it measured them in:
# {study: (where and how, {variant label: psnr})}
THESIS = {
    "accumulation": ("Table 16: 4x on its dataset 1 (at 2x on its dataset 2: 35.89 with, "
                     "35.80 dB without)", {"with buffer": 35.49, "without buffer": 35.23}),
    "warp": ("Table 13: 4x on its dataset 1, every network trained with its 16-tap bicubic "
             "(Bicubic9) and the warp switched at inference, which the Pareto section does "
             "with the shipped weights", {"bicubic (16 taps, a=-0.75)": 35.49,
                                          "bilinear": 34.02}),
    "theta": ("Table 10: 2x on its dataset 2 (this study is at the factor shown above)",
              {"L1": 35.89, "L_st-linear θ=0.1": 35.90, "L_st-linear θ=0.5": 35.87,
               "L_st-linear θ=0.9": 35.36}),
}


def against_thesis(study, trained):
    """Markdown lines comparing each variant's mean PSNR gap to the study's first
    variant (the reference network) with the thesis's gap for the same pair. The gap's
    standard error is that of a difference of two means over independent seeds,
    ``sqrt(s1^2/n1 + s2^2/n2)``."""
    where, thesis = THESIS[study]
    by = {}
    for r in trained:
        by.setdefault(r["variant"], []).append(r["psnr"])
    if not by:
        return []
    ref = next(iter(by))  # the records come in the study's variant order
    lines = [f"Against the thesis ({where}): PSNR gap of each variant to \"{ref}\".", "",
             "| variant | gap here (dB) | standard error | thesis gap (dB) |",
             "| --- | --- | --- | --- |"]
    r = np.array(by[ref])
    for lab, v in by.items():
        if lab == ref:
            continue
        v = np.array(v)
        # one seed on either side: no spread to estimate it from
        se = (f"{np.sqrt(v.var(ddof=1) / len(v) + r.var(ddof=1) / len(r)):.2f}"
              if min(len(v), len(r)) > 1 else "-")
        th = f"{thesis[lab] - thesis[ref]:+.2f}" if lab in thesis and ref in thesis else "-"
        lines.append(f"| {lab} | {v.mean() - r.mean():+.2f} | {se} | {th} |")
    return lines


def run_variant(study, label, changes, base, seeds, max_extra, max_videos, progress,
                thetas=()):
    """Train ``len(seeds)`` networks that did not collapse (taking further seeds for
    collapsed ones). Returns ``(records of trained runs, records of collapsed runs)``."""
    trained, failed = [], []
    queue, next_seed = list(seeds), max(seeds) + 1
    while queue:
        seed = queue.pop(0)
        work, cfg = run_of(study, label, changes, base, seed, thetas)
        if not os.path.exists(os.path.join(work, SAVED[0])) and \
                copy_run(saved_dir(work), work):
            print(f"resuming {os.path.relpath(work, ROOT)} from its saved checkpoint",
                  file=sys.stderr)
        params, hist = train.train_and_evaluate(cfg, work, resume=True, progress=progress,
                                                stop_when=train.collapsed)
        rec = {"variant": label, "seed": seed, "workdir": os.path.relpath(work, ROOT),
               "val_psnr_last": hist[-1].get("val_psnr") if hist else None}
        why = train.collapsed(hist)
        if why:
            rec["collapsed"] = why
            failed.append(rec)
            if len(failed) <= max_extra:
                queue.append(next_seed)
                next_seed += 1
            print(f"{label} seed {seed}: collapsed ({why})", file=sys.stderr)
            continue
        rec.update(evaluate.video_means(recipe.model_for(cfg), params, cfg.dataset, cfg.factor,
                                   max_videos=max_videos))
        trained.append(rec)
        print(f"{label} seed {seed}: " + ", ".join(f"{k} {rec[k]:.4g}" for k in METRICS),
              file=sys.stderr)
    return trained, failed


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--study", required=True, choices=("accumulation", "warp", "theta"))
    p.add_argument("--factor", type=int, default=4, choices=(2, 4))
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--max-extra", type=int, default=3,
                   help="extra seeds per variant to replace collapsed runs")
    p.add_argument("--thetas", type=float, nargs="+", default=[0.1, 0.5, 0.9])
    p.add_argument("--epochs", type=int, default=10)
    p.add_argument("--steps-per-epoch", type=int, default=200)
    p.add_argument("--lr", type=float, default=LR, help="peak learning rate (default: %(default)g)")
    p.add_argument("--preset", default="diverse", choices=sorted(PRESETS))
    p.add_argument("--dataset", help="default: the preset's")
    p.add_argument("--max-videos", type=int, default=8)
    p.add_argument("--variants", nargs="+", metavar="VARIANT",
                   help="train only these variants (by slug: with_buffer, bilinear, "
                        "l_st_linear_θ_0_5, ...) and write no table; two processes on "
                        "disjoint variants share the machine, and a run without it "
                        "writes the table")
    p.add_argument("--save-only", action="store_true",
                   help="copy every run's checkpoint to experiments/checkpoints/ and exit")
    args = p.parse_args(argv)
    if args.save_only:
        save_runs(args.study, args.lr)
        return
    if len(set(args.seeds)) != len(args.seeds) or min(args.seeds) < 0:
        p.error(f"--seeds: expected distinct seeds >= 0, got {args.seeds}")
    base = dataclasses.replace(PRESETS[args.preset], factor=args.factor, epochs=args.epochs,
                               steps_per_epoch=args.steps_per_epoch, lr=args.lr,
                               **({"dataset": args.dataset} if args.dataset else {}))
    chosen = variants(args.study, args.thetas)
    if args.variants:
        slugs = [slug(lab) for lab, _ in chosen]
        bad = [v for v in args.variants if v not in slugs]
        if bad:
            p.error(f"--variants: {', '.join(bad)} not among the {args.study} study's "
                    f"{', '.join(slugs)}")
        chosen = [(lab, ch) for lab, ch in chosen if slug(lab) in args.variants]
    rows, data = [], {"trained": [], "collapsed": []}
    for label, changes in chosen:
        trained, failed = run_variant(args.study, label, changes, base, args.seeds,
                                      args.max_extra, args.max_videos, sys.stderr.isatty(),
                                      args.thetas)
        data["trained"] += trained
        data["collapsed"] += failed
        cells = []
        for k in METRICS:
            v = np.array([r[k] for r in trained])
            digits = 2 if k == "psnr" else 4 if k == "ssim" else 5
            spread = f" ± {v.std(ddof=1):.{digits}f}" if len(v) > 1 else ""  # one seed: none
            cells.append(f"{v.mean():.{digits}f}{spread}" if len(v) else "-")
        rows.append(f"| {label} | {', '.join(str(r['seed']) for r in trained) or '-'} | "
                    f"{', '.join(str(r['seed']) for r in failed) or 'none'} | "
                    + " | ".join(cells) + " |")
    if args.variants:
        print(f"trained {', '.join(args.variants)}; run without --variants for the table",
              file=sys.stderr)
        return
    table = "\n".join(["| variant | seeds trained | seeds collapsed (replaced) | PSNR (dB) | "
                       "SSIM | spatial error (θ=0) | temporal error (θ=1) |",
                       "| --- | --- | --- | --- | --- | --- | --- |"] + rows)
    steps = args.epochs * args.steps_per_epoch
    data_name = os.path.relpath(base.dataset, ROOT) if os.path.isabs(base.dataset) else \
        base.dataset
    write(study_name(args.study, args.lr), table, data,
          note=f"DLCTUS {args.factor}x, the `{args.preset}` recipe at learning rate "
               f"{args.lr:g} for {args.epochs} x "
               f"{args.steps_per_epoch} = {steps:,} steps per run; mean ± standard deviation "
               f"over the seeds that trained, on the first {args.max_videos} test videos of "
               f"`{data_name}`.\n\n" + "\n".join(against_thesis(args.study, data["trained"])))


if __name__ == "__main__":
    main()
