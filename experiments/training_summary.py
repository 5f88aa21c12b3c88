"""Where each comparison run stands, from its per-epoch log: epochs and Adam steps done,
training seconds (the sum of the per-epoch times), validation PSNR after the first
epoch, at its best and at the end, and its change over the last fifth of the epochs
(the training issue's rule: a run has flattened when that moves less than 0.1 dB).

Reads the finished runs' exported logs (``experiments/weights/<model>-x<f>-training.csv``)
and the unfinished runs' committed checkpoints (``experiments/checkpoints/<model>-
diverse-x<f>/metrics.csv``, when it is the longer log) and writes a markdown table:

    python experiments/training_summary.py --out docs/results/comparison-training.md
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import sys

SYSTEMS = ("mlp", "kpn", "nsrr-fast", "nsrr")
FACTORS = (4, 2)


def summarize(rows, epochs_planned):
    """One run's figures from its ``metrics.csv`` rows."""
    psnr = [float(r["val_psnr"]) for r in rows]
    n = len(rows)
    first_of_last_fifth = max(n - max(n // 5, 1) - 1, 0)
    delta = psnr[-1] - psnr[first_of_last_fifth]
    return {"epochs": n, "planned": epochs_planned, "steps": int(rows[-1]["step"]),
            "seconds": sum(float(r["seconds"]) for r in rows), "first": psnr[0],
            "best": max(psnr), "last": psnr[-1], "last_fifth": delta,
            "flat": n == epochs_planned and abs(delta) < 0.1}


def find(model, factor, root="."):
    """``(rows, planned epochs, source)`` of the newest log of a run, or None."""
    cands = []
    for csv_path, cfg_path in (
            (f"experiments/checkpoints/{model}-diverse-x{factor}/metrics.csv",
             f"experiments/checkpoints/{model}-diverse-x{factor}/config.json"),
            (f"experiments/weights/{model}-x{factor}-training.csv",
             f"experiments/weights/{model}-x{factor}.json")):
        p, c = os.path.join(root, csv_path), os.path.join(root, cfg_path)
        if os.path.exists(p) and os.path.exists(c):
            with open(p) as fh:
                rows = list(csv.DictReader(fh))
            with open(c) as fh:
                cfg = json.load(fh)
            cfg = cfg.get("config", cfg)
            if rows and cfg.get("dataset", "").endswith("diverse.h5"):
                # the longer log is the newer (a run only grows; file times mean nothing
                # in a fresh clone), the exported one on a tie (it is the finished run)
                cands.append(((len(rows), "weights/" in csv_path), rows, cfg["epochs"],
                              csv_path))
    if not cands:
        return None
    _, rows, planned, src = max(cands, key=lambda c: c[0])
    return rows, planned, src


def finished(model, factor, epochs, root="."):
    """True if the run's exported log (``experiments/weights/``) is of the ``diverse``
    data and reaches ``epochs``: a finished run, on any machine, with nothing to resume
    or retrain."""
    got = find(model, factor, root)
    return (got is not None and got[2].startswith("experiments/weights/")
            and int(got[0][-1]["epoch"]) >= epochs)


def table(root="."):
    lines = ["| system | factor | epochs (of) | Adam steps | training s | val PSNR first / best / "
             "last (dB) | last fifth (dB) | flat | log |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for m in SYSTEMS:
        for f in FACTORS:
            got = find(m, f, root)
            if got is None:
                lines.append(f"| {m} | {f}x | no diverse-data log committed | | | | | | |")
                continue
            rows, planned, src = got
            s = summarize(rows, planned)
            lines.append(f"| {m} | {f}x | {s['epochs']} ({s['planned']}) | {s['steps']:,} | "
                         f"{s['seconds']:,.0f} | {s['first']:.2f} / {s['best']:.2f} / "
                         f"{s['last']:.2f} | {s['last_fifth']:+.2f} | "
                         f"{'yes' if s['flat'] else 'no'} | `{src}` |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", help="write the table (markdown) here as well")
    p.add_argument("--finished", nargs=3, metavar=("MODEL", "FACTOR", "EPOCHS"),
                   help="print nothing; exit 0 if that run's exported log reaches EPOCHS, "
                        "1 if not (train_comparison.sh skips finished runs)")
    args = p.parse_args(argv)
    if args.finished:
        m, f, e = args.finished
        return 0 if finished(m, int(f), int(e)) else 1
    text = table()
    print(text)
    if args.out:
        os.makedirs(os.path.dirname(args.out) or ".", exist_ok=True)
        with open(args.out, "w") as fh:
            fh.write("# Comparison runs on the diverse data\n\n" + text + "\n\nMade by `python "
                     "experiments/training_summary.py --out " + args.out + "`. Training "
                     "seconds are wall time on one core of the machine named in "
                     "docs/comparison.md, often shared with other work.\n")


if __name__ == "__main__":
    sys.exit(main())
