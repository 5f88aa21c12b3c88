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
import os
import sys

from common import FACTORS, SYSTEMS, find, finished, summarize

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
