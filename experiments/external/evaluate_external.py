"""Every system on the independent-renderer clips (``render_mitsuba.py``), per clip and
pooled over all frames, per factor.

    python experiments/external/evaluate_external.py --models jau tus shipped
    python experiments/external/evaluate_external.py --models jau tus shipped \
        mine=runs/diverse-x{f}/checkpoint.msgpack --name external-mine

Reads ``data/external/{clip}-x{f}.h5``; writes ``docs/results/<name>/`` (default
``external``). Held-out data: evaluate on it, never train or tune on it.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from common import write  # noqa: E402
from external.render_mitsuba import CLIPS  # noqa: E402  (the renderer's clip list)

from jtus import evaluate, models  # noqa: E402


def evaluate_clips(entries, factor, data_root="data/external"):
    """Score ``entries`` (``models.load_all``) on every clip at ``factor``.

    Returns ``(per_clip, pooled)``: ``{clip: {label: summary}}`` and ``{label:
    summary}`` over every frame of every clip (``evaluate.summarize``'s PSNR, SSIM,
    temporal error)."""
    per_clip, pooled = {}, {e.label: {"psnr": [], "ssim": [], "temporal": []} for e in entries}
    for clip in CLIPS:
        path = os.path.join(data_root, f"{clip}-x{factor}.h5")
        if not os.path.exists(path):
            raise SystemExit(f"{path} is missing: python experiments/external/render_mitsuba.py")
        per_frame, _ = evaluate.evaluate(entries, path, factor, progress=False)
        per_clip[clip] = evaluate.summarize(per_frame)
        for lab, d in per_frame.items():
            for k in pooled[lab]:
                pooled[lab][k].append(d[k])
    return per_clip, evaluate.summarize({lab: {k: np.concatenate(v) for k, v in d.items()}
                                         for lab, d in pooled.items()})


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=["jau", "tus", "shipped"])
    p.add_argument("--data", default="data/external")
    p.add_argument("--name", default="external")
    args = p.parse_args()
    rows, data = [], {}
    for f in (4, 2):
        entries = models.load_all(args.models, f)
        per_clip, pooled = evaluate_clips(entries, f, args.data)
        for clip, summaries in [*per_clip.items(), ("all", pooled)]:
            name = "**all**" if clip == "all" else clip
            for lab, s in summaries.items():
                data.setdefault(str(f), {}).setdefault(clip, {})[lab] = s
                rows.append(f"| {f}x | {name} | {lab} | {s['psnr']:.2f} | {s['ssim']:.4f} | "
                            f"{s['temporal']:.5f} |")
    table = ("| factor | clip | method | PSNR (dB) | SSIM | temporal error |\n"
             "| --- | --- | --- | --- | --- | --- |\n" + "\n".join(rows))
    write(args.name, table, data, note="Clips rendered by Mitsuba 3 "
          "(`python experiments/external/render_mitsuba.py`), 32 frames each, 256x256; "
          "**all** pools every frame of the three clips.")


if __name__ == "__main__":
    main()
