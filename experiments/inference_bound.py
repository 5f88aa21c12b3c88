"""What the CPU inference target asks of this machine, from one bench report.

For each DLCTUS row of a ``python -m jtus.bench`` report (``--what peak infer``), the
target time is PyTorch's time over the aimed ratio (1.5x), the network's floor is its
FLOPs at the convolution peak measured in the same run, and "the rest" is jtus's frame
time minus its network time (warps, blends, layout work; memory-bound). The last column
is the frame time jtus would reach with its network at the peak and the rest as it is:
where it exceeds the target, the target also needs the rest cut by the difference.

    python experiments/inference_bound.py docs/results/bench-2core/bench.json

Writes ``docs/results/inference-bound/result.{md,json}``.
"""

from __future__ import annotations

import argparse
import json

from common import write


def bounds(report, ratio):
    """One dict per DLCTUS inference row of ``report`` (a bench JSON)."""
    peak = report["peak"]["conv_dlctus_gflops"]
    out = []
    for r in report["infer"]:
        if r["model"] != "dlctus" or r.get("torch_ms") is None:
            continue
        floor = 1e3 * r["gflop"] / peak
        rest = r["ms"] - r["network_ms"]
        out.append({"size": r["size"], "factor": r["factor"], "torch_ms": r["torch_ms"],
                    "target_ms": r["torch_ms"] / ratio, "jtus_ms": r["ms"],
                    "network_ms": r["network_ms"], "network_floor_ms": floor,
                    "rest_ms": rest, "at_peak_ms": floor + rest})
    return out


def table(rows, ratio, peak):
    head = (f"| size | factor | PyTorch ms | target ms ({ratio}x) | jtus ms | network ms | "
            f"network at peak ms | rest ms | network at peak + rest ms |\n"
            + "| --- " * 9 + "|\n")
    body = "".join(
        f"| {r['size']} | {r['factor']}x | {r['torch_ms']:.1f} | {r['target_ms']:.1f} | "
        f"{r['jtus_ms']:.1f} | {r['network_ms']:.1f} | {r['network_floor_ms']:.1f} | "
        f"{r['rest_ms']:.1f} | {r['at_peak_ms']:.1f} |\n" for r in rows)
    return head + body + f"\nConvolution peak (3x3 32->32, same run): {peak:.1f} GFLOP/s."


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("report", help="a bench JSON with peak and infer sections")
    p.add_argument("--ratio", type=float, default=1.5, help="the aimed torch/jtus ratio")
    p.add_argument("--name", default="inference-bound")
    args = p.parse_args()
    with open(args.report) as fh:
        report = json.load(fh)
    for key in ("peak", "infer"):
        if key not in report:
            raise SystemExit(f"{args.report}: no '{key}' section (run the bench with "
                             "--what peak infer)")
    rows = bounds(report, args.ratio)
    if not rows:
        raise SystemExit(f"{args.report}: no DLCTUS inference row with a PyTorch time")
    peak = report["peak"]["conv_dlctus_gflops"]
    write(args.name, table(rows, args.ratio, peak),
          {"report": args.report, "ratio": args.ratio, "hardware": report["hardware"],
           "rows": rows}, note=f"From `{args.report}` ({report['hardware']['cpu']}, "
          f"{report['hardware']['cores']} cores); nothing is timed by this script.")


if __name__ == "__main__":
    main()
