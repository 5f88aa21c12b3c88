"""XLA:CPU's library fusions (XNNPACK graph fusion, YNN and oneDNN fusion types) and two
of its scheduling options (copy insertion's region analysis, the concurrency-optimized
scheduler) on DLCTUS training and inference, each against PyTorch timed alongside.

XLA flags are read once per process, so each variant is one ``python -m jtus.bench``
run with its own ``XLA_FLAGS``; inside that run PyTorch's step alternates with jtus's
(``timeit_pair``), so the torch/jtus ratio of each variant is taken side by side and
ratios can be compared across variants on a noisy machine, where raw times cannot.

    taskset -c 1 python experiments/xla_flags.py                 # every variant
    python experiments/xla_flags.py --variants baseline xnn-greedy --repeats 3

Writes one bench report per variant and a summary table under
``docs/results/xla-flags/`` (``result.md``, ``result.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

from common import ROOT, out_dir, write

VARIANTS = {
    "baseline": "",
    "xnn-greedy": "--xla_cpu_experimental_xnn_graph_fusion_mode=XNN_GRAPH_FUSION_MODE_GREEDY",
    "xnn-greedy-slinky":
        "--xla_cpu_experimental_xnn_graph_fusion_mode=XNN_GRAPH_FUSION_MODE_GREEDY_SLINKY",
    "xnn-fusion-dot": "--xla_cpu_experimental_xnn_fusion_type=dot",
    "xnn-fusion-eltwise": "--xla_cpu_experimental_xnn_fusion_type=eltwise",
    "xnn-fusion-dot,eltwise": "--xla_cpu_experimental_xnn_fusion_type=dot,eltwise",
    "xnn-fusion-dot,eltwise,reduce": "--xla_cpu_experimental_xnn_fusion_type=dot,eltwise,reduce",
    "ynn-fusion-dot,eltwise,reduce": "--xla_cpu_experimental_ynn_fusion_type=dot,eltwise,reduce",
    "onednn": "--xla_cpu_use_onednn=true",
    "onednn-fusion-dot,eltwise,reduce":
        "--xla_cpu_use_onednn=true --xla_cpu_experimental_onednn_fusion_type=dot,eltwise,reduce",
    # copy insertion with region analysis (off by default on the CPU): fewer copies of a
    # while loop's carried buffers, where the scan's bookkeeping goes
    "copy-region-analysis": "--xla_cpu_copy_insertion_use_region_analysis=true",
    # the scheduler that orders independent operations for concurrency (on by default)
    "no-concurrency-scheduler": "--xla_cpu_enable_concurrency_optimized_scheduler=false",
    # the legacy elemental emitter for fusions instead of the MLIR fusion emitters
    # (compiles small programs about a third faster)
    "no-fusion-emitters": "--xla_cpu_use_fusion_emitters=false",
}


def bench(name, flags, repeats, d, tag=""):
    out = os.path.join(d, f"{name}{tag}.json")
    env = dict(os.environ, XLA_FLAGS=flags)
    cmd = [sys.executable, "-m", "jtus.bench", "--what", "infer", "train", "--models", "dlctus",
           "--train-models", "dlctus", "--sizes", "720p", "1080p", "--factors", "4", "2",
           "--train-preset", "diverse", "--repeats", str(repeats), "--out", out]
    r = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
    if r.returncode:
        return {"variant": name, "flags": flags, "error": r.stderr.strip().splitlines()[-1:]}
    with open(out) as fh:
        rep = json.load(fh)
    train = rep["train"][0] if isinstance(rep["train"], list) else rep["train"]
    row = {"variant": name + tag, "flags": flags,
           "train_torch_over_jtus": train["torch_over_jtus"],
           "train_frames_per_s": train["frames_per_s"]}
    for rec in rep["infer"]:
        row[f"infer {rec['size']} {rec['factor']}x torch/jtus"] = rec["torch_over_jtus"]
    return row


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--variants", nargs="+", choices=tuple(VARIANTS), default=list(VARIANTS))
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--rounds", type=int, default=1,
                   help="run the whole list this many times, in turn (a, b, a, b)")
    p.add_argument("--name", default="xla-flags", help="the folder under docs/results/")
    args = p.parse_args()
    d = out_dir(args.name)
    rows = []
    for r in range(args.rounds):
        for name in args.variants:
            tag = f"-r{r + 1}" if args.rounds > 1 else ""
            rows.append(bench(name, VARIANTS[name], args.repeats, d, tag))
            print(rows[-1], flush=True)
    ok = [r for r in rows if "error" not in r]
    keys = [k for k in ok[0] if k not in ("variant", "flags")] if ok else []
    lines = ["| variant | " + " | ".join(keys) + " |", "| --- " * (len(keys) + 1) + "|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['variant']} | failed: {r['error']} |")
        else:
            lines.append(f"| {r['variant']} | " + " | ".join(f"{r[k]:.2f}" for k in keys) + " |")
    write(args.name, "\n".join(lines), rows,
          note="Each cell is PyTorch's time over jtus's (above 1: jtus faster), both timed "
               "alternately in the same process, except the training frames per second. "
               "Flags per variant are in result.json.")


if __name__ == "__main__":
    main()
