"""Which learning rate keeps the ablations' DLCTUS from collapsing: the first epochs of
the ablation recipe (``experiments/ablations.py``: the ``diverse`` preset, 10 x 200
steps, 4x) per variant, learning rate and seed, each stopped after ``--epochs`` epochs
(or at a collapse), with the verdict of ``jtus.train.collapsed`` on its epoch log.

    python experiments/collapse_probe.py --variants "without buffer" --lrs 3e-4 \\
        --seeds 0 1 2

A collapse (the clamped blend outputs saturate on every sub-pixel, so no gradient
reaches the network again; ``docs/weights.md``) showed within the first epoch in every
collapsed run so far, so two epochs tell. The schedule is the full run's (warm-up and
cosine over 10 x 200 steps), so a probe is the start of the run it stands for.
Writes ``docs/results/collapse-probe/result.{md,json}``, adding to the rows there (a
probe already in the file is not run again); runs go to
``runs/collapse-probe/<variant>-lr<lr>-s<seed>/``. The table also reads the first
``--epochs`` epochs of the ablation runs committed under ``--runs`` (the accumulation
study's runs at the preset's learning rate, 1e-3, which showed the collapses): the
same recipe, so their start is a probe too.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

from common import ROOT, out_dir, slug, variants, write

from jtus import loading, train
from jtus.config import PRESETS


def probe_dir(label, lr, seed):
    return os.path.join(ROOT, "runs", "collapse-probe", f"{slug(label)}-lr{lr:g}-s{seed}")


def is_probe(row):
    """Whether a table row is a probe's (its run under ``runs/collapse-probe/``) rather
    than a committed ablation run's."""
    return row["workdir"].startswith(os.path.join("runs", "collapse-probe"))


def probe(label, changes, lr, seed, epochs, base):
    cfg = dataclasses.replace(base, seed=seed, lr=lr, **changes)
    work = probe_dir(label, lr, seed)
    _, hist = train.train_and_evaluate(cfg, work, resume=True, progress=sys.stderr.isatty(),
                                       stop_after=epochs, stop_when=train.collapsed)
    why = train.collapsed(hist)
    return {"variant": label, "lr": lr, "seed": seed, "epochs": len(hist),
            "val_psnr": [h["val_psnr"] for h in hist],
            "grad_norm_max": [h["grad_norm_max"] for h in hist],
            "collapsed": why, "workdir": os.path.relpath(work, ROOT)}


def saturation(checkpoint_path, dataset, videos=4):
    """The fraction of the blend output o1 (before its clamp) outside [0, 1], on the
    second frame of the first ``videos`` validation videos, for the network saved in
    ``checkpoint_path``: 1.0 means the clamp passes no gradient anywhere."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    from jtus import recipe, sampling
    from jtus.data.dataset import Dataset
    from jtus.models import dlctus

    params, cfg = loading.load_params(checkpoint_path)
    model = recipe.model_for(cfg)
    out = []
    with Dataset(dataset) as ds:
        for name in ds.videos("val")[:videos]:
            frames, _ = ds.video("val", name, cfg.factor)
            at = [jax.tree_util.tree_map(lambda x, t=t: jnp.asarray(x[t]), frames)
                  for t in (0, 1)]
            pre = dlctus.prepare_frame(at[1], model.config)
            net_in, _, _ = dlctus.reproject(model.init_state(at[0]), pre, model.config)
            o1 = sampling.pixel_shuffle(dlctus.network(params, net_in, model.config), 4)[..., 0]
            out.append(np.asarray((o1 < 0) | (o1 > 1)).ravel())
    return float(np.concatenate(out).mean())


def committed_runs(root, epochs):
    """Rows, like ``probe``'s, of the runs saved under ``root`` (``<variant>-s<seed>/``
    with ``config.json`` and ``metrics.json``), read over their first ``epochs``."""
    rows = []
    labels = {slug(lab): lab for lab, _ in variants("accumulation", ())}
    for run in sorted(os.listdir(root)) if os.path.isdir(root) else []:
        name, seed = run.rsplit("-s", 1)
        with open(os.path.join(root, run, "config.json")) as fh:
            lr = json.load(fh)["lr"]
        with open(os.path.join(root, run, "metrics.json")) as fh:
            hist = json.load(fh)[:epochs]
        rows.append({"variant": labels[name], "lr": lr, "seed": int(seed), "epochs": len(hist),
                     "val_psnr": [h["val_psnr"] for h in hist],
                     "grad_norm_max": [h["grad_norm_max"] for h in hist],
                     "collapsed": train.collapsed(hist),
                     "workdir": os.path.relpath(os.path.join(root, run), ROOT)})
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    names = [lab for lab, _ in variants("accumulation", ())]
    p.add_argument("--variants", nargs="+", default=names, choices=names)
    p.add_argument("--lrs", type=float, nargs="+", default=[3e-4])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--epochs", type=int, default=2)
    p.add_argument("--runs", default=os.path.join(ROOT, "experiments", "checkpoints",
                                                  "ablation-accumulation-lr0.001"),
                   help="committed ablation runs whose first epochs join the table")
    args = p.parse_args(argv)
    if args.epochs < 2:
        p.error(f"--epochs: expected >= 2 (a collapse is read from two epochs), got "
                f"{args.epochs}")
    base = dataclasses.replace(PRESETS["diverse"], factor=4, epochs=10, steps_per_epoch=200)
    path = os.path.join(out_dir("collapse-probe"), "result.json")
    # the probes of earlier invocations (committed runs are read afresh below)
    rows = [r for r in json.load(open(path)) if is_probe(r)] if os.path.exists(path) else []
    done = {(r["variant"], r["lr"], r["seed"]) for r in rows}
    changes = dict(variants("accumulation", ()))
    for label in args.variants:
        for lr in args.lrs:
            for seed in args.seeds:
                if (label, lr, seed) in done:
                    continue
                rows.append(probe(label, changes[label], lr, seed, args.epochs, base))
                print(rows[-1], file=sys.stderr, flush=True)
    rows += committed_runs(args.runs, args.epochs)
    for r in rows:  # measured while the run's checkpoint is here, then kept in the file
        ck = os.path.join(ROOT, r["workdir"], "checkpoint.msgpack")
        if "saturated" not in r and os.path.exists(ck):
            r["saturated"] = saturation(ck, base.dataset)
    rows.sort(key=lambda r: (r["variant"], -r["lr"], r["seed"]))
    table = ["| variant | lr | seed | run | epochs | validation PSNR per epoch (dB) | largest "
             "gradient norm per epoch | o1 outside [0, 1] at the end | collapsed |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        src = "probe" if is_probe(r) else f"`{r['workdir']}`"
        table.append(f"| {r['variant']} | {r['lr']:g} | {r['seed']} | {src} | {r['epochs']} | "
                     + ", ".join(f"{v:.2f}" for v in r["val_psnr"]) + " | "
                     + ", ".join(f"{v:.2g}" for v in r["grad_norm_max"]) + " | "
                     + (f"{100 * r['saturated']:.1f}%" if "saturated" in r else "-") + " | "
                     + (r["collapsed"] or "no") + " |")
    write("collapse-probe", "\n".join(table), rows,
          note="The ablation recipe (`diverse` preset, 4x, 10 x 200 steps: warm-up 300 "
               "steps, cosine decay) at the learning rate shown, over its first epochs: a "
               "probe stopped there, or the first epochs of a committed ablation run. Rows "
               "of earlier invocations are kept (each probe ran once). o1 outside [0, 1]: "
               "the share of the blend output, before its clamp, outside [0, 1] on the "
               "second frame of 4 validation videos, for the run's last checkpoint (a "
               "committed run's is its last epoch, not its second); 100% passes no "
               "gradient (`saturation`).")


if __name__ == "__main__":
    main()
