"""Where a DLCTUS step's GPU time goes: the kernels the device ran, summed by name, for
the inference step in a frame loop (1080p 4x bfloat16, the default trunk form) and
the training step at the thesis's scale (crop 256, 30 frames, batch 4).

    python experiments/gpu/profile_step.py --out out/gpu/profile-step.json   # on a GPU

Each workload is warmed, then ``--steps`` calls are traced with ``jax.profiler``; the
trace's device planes (``/device:GPU:*``) give every kernel's span (their CUDA
streams' lines) and every XLA op's (the "XLA Ops" line). Reported per workload and
line kind: the time per step (spans summed), the count per step, and the largest by
time per step.
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import sys
import tempfile

import jax

from jtus.bench.workloads import SIZES, infer_workload, train_workload
from jtus import files
from jtus.timing import hardware_line


def _kind(line_name):
    """A device plane's lines: the XLA ops (HLO names), the CUDA streams' kernels, and
    the rest (modules, memcpy summaries), kept apart so that no span is counted twice."""
    if line_name == "XLA Ops":
        return "ops"
    return "kernels" if line_name.startswith("Stream") else "other"


def device_kernels(run, steps, prefix):
    """``{(line kind, event name): total ns}`` and the counts, over ``steps`` traced
    calls of ``run``, from the planes whose name starts with ``prefix``."""
    with tempfile.TemporaryDirectory() as logdir:
        jax.profiler.start_trace(logdir)
        for _ in range(steps):
            run()
        jax.profiler.stop_trace()
        files = glob.glob(os.path.join(logdir, "**", "*.xplane.pb"), recursive=True)
        data = jax.profiler.ProfileData.from_file(max(files, key=os.path.getmtime))
        ns, count = collections.Counter(), collections.Counter()
        for plane in data.planes:
            if not plane.name.startswith(prefix):
                continue
            for line in plane.lines:
                for ev in line.events:
                    ns[_kind(line.name), ev.name] += ev.duration_ns
                    count[_kind(line.name), ev.name] += 1
    return ns, count


def summary(name, run, steps, prefix, top):
    run()
    run()
    ns, count = device_kernels(run, steps, prefix)
    rec = {"workload": name, "steps": steps}
    for kind in ("kernels", "ops", "other"):
        sel = collections.Counter({k[1]: v for k, v in ns.items() if k[0] == kind})
        total = sum(sel.values())
        rec[f"{kind}_ms_per_step"] = total / 1e6 / steps
        rec[f"{kind}_per_step"] = sum(c for k, c in count.items() if k[0] == kind) / steps
        rec[f"top_{kind}"] = [{"name": k, "ms_per_step": v / 1e6 / steps,
                               "calls_per_step": count[kind, k] / steps,
                               "share": v / max(total, 1)} for k, v in sel.most_common(top)]
    return rec


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", default="1080p", choices=tuple(SIZES))
    p.add_argument("--factor", type=int, default=4, choices=(2, 4))
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--train-steps", type=int, default=3)
    p.add_argument("--train-crop", type=int, default=256)
    p.add_argument("--train-seq", type=int, default=30)
    p.add_argument("--top", type=int, default=25)
    p.add_argument("--prefix", default="/device:GPU", help="trace planes to read")
    p.add_argument("--out")
    args = p.parse_args()
    report = {"hardware": hardware_line(), "command": "python experiments/gpu/profile_step.py "
              + " ".join(sys.argv[1:]), "workloads": []}
    run = infer_workload("dlctus", args.factor, SIZES[args.size], "bfloat16")[0]
    jobs = [(f"inference {args.size} {args.factor}x bfloat16", run, args.steps)]
    run = train_workload(args.factor, args.train_crop, 4, args.train_seq,
                         min(5, args.train_seq))[0]
    jobs.append((f"training step, crop {args.train_crop}, {args.train_seq} frames, batch 4",
                 run, args.train_steps))
    for name, run, steps in jobs:
        rec = summary(name, run, steps, args.prefix, args.top)
        print(json.dumps({k: v for k, v in rec.items() if not k.startswith("top")}), flush=True)
        for kind in ("kernels", "ops"):
            for r in rec[f"top_{kind}"][:12]:
                print(f"  {kind} {r['ms_per_step']:.4f} ms x{r['calls_per_step']:.0f} "
                      f"{r['name'][:80]}")
        report["workloads"].append(rec)
        if args.out:
            with files.atomic_path(args.out) as tmp, open(tmp, "w") as fh:
                json.dump(report, fh, indent=1)


if __name__ == "__main__":
    main()
