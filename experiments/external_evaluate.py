"""Every system on the independent-renderer clips (``render_mitsuba.py``), per clip and
pooled over all frames, per factor.

    python experiments/external_evaluate.py --models jau tus shipped
    python experiments/external_evaluate.py --models jau tus shipped \
        mine=runs/diverse-x{f}/checkpoint.msgpack --name external-mine

Reads ``data/external/{clip}-x{f}.h5``; writes ``docs/results/<name>/`` (default
``external``). Held-out data: evaluate on it, never train or tune on it.
"""

from __future__ import annotations

import argparse

from common import evaluate_clips, write

from jtus import loading


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=["jau", "tus", "shipped"])
    p.add_argument("--data", default="data/external")
    p.add_argument("--name", default="external")
    p.add_argument("--factors", type=int, nargs="+", default=[4, 2], choices=(2, 4))
    args = p.parse_args()
    rows, data = [], {}
    for f in args.factors:
        entries = loading.load_all(args.models, f)
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
