"""Candidate weights side by side: the validation splits that choose between them, then
the test families that report them (never the other way round).

    python experiments/candidate_scores.py --factor 4 --name mlp-game-mix-x4 \\
        --models jau mlp=experiments/weights/mlp-x4.msgpack \\
        mlp-mix=experiments/checkpoints/mlp-mix-x4/checkpoint.msgpack

Columns, PSNR (dB), every video from a fresh state:
- validation: the ``diverse`` data's validation scenes and the ``game`` data's
  validation levels (``data/diverse.h5``, ``data/game.h5``, split ``val``);
- test: the four families of ``comparison_table.py`` (randomized scenes, hand-made
  scenes, the Mitsuba clips, the held-out game levels).

Writes ``docs/results/<name>/result.{md,json}``.
"""

from __future__ import annotations

import argparse
import os

from comparison_table import FAMILIES, score
from common import ROOT, write

from jtus import evaluate, loading

VAL = {"diverse val": "data/diverse.h5", "game val": "data/game.h5"}


def scores(entries, factor, data_root=ROOT):
    """``{column: {label: psnr}}`` over the validation splits, then the test families."""
    out = {}
    for col, path in VAL.items():
        per_frame, _ = evaluate.evaluate(entries, os.path.join(data_root, path), factor,
                                         split="val", progress=False)
        out[col] = {lab: s["psnr"] for lab, s in evaluate.summarize(per_frame).items()}
    for fam in FAMILIES:
        out[fam] = {lab: s["psnr"] for lab, s in score(entries, fam, factor,
                                                      data_root).items()}
    return out


def table(result):
    cols = list(result)
    labels = list(result[cols[0]])
    lines = ["| model | " + " | ".join(f"{c} (validation)" if c in VAL else f"{c} (test)"
                                      for c in cols) + " |",
             "| --- " * (len(cols) + 1) + "|"]
    for lab in labels:
        lines.append(f"| {lab} | " + " | ".join(f"{result[c][lab]:.2f}" for c in cols) + " |")
    return "\n".join(lines)


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--factor", type=int, required=True, choices=(2, 4))
    p.add_argument("--models", nargs="+", required=True,
                   help="built-in names, shipped, or LABEL=PATH")
    p.add_argument("--data-root", default=ROOT)
    p.add_argument("--name", required=True)
    args = p.parse_args()
    entries = loading.load_all(args.models, args.factor)
    result = scores(entries, args.factor, args.data_root)
    write(args.name, table(result), result,
          note=f"{args.factor}x; PSNR (dB), every video from a fresh state. The validation "
               "columns choose between candidates; the test columns only report.")


if __name__ == "__main__":
    main()
