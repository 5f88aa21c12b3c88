"""The host allocator's cost: each workload with glibc's default allocator and with freed
memory kept in the process (``jtus.hostmem.keep_freed_memory``), in fresh processes
taken in turn, counting per call the wall time, the minor page faults and the kernel
time, and the PyTorch reference timed alternately in the same process (it shares the
process's allocator).

    python experiments/host_memory.py                        # every workload, 3 rounds
    python experiments/host_memory.py --what train --rounds 1 --calls 10
    python experiments/host_memory.py --what train infer-1080p --allocators kept one-arena \
        --name host-memory-one-arena                         # one glibc arena for all threads

Workloads: ``train``, the ``diverse`` preset's DLCTUS 2x step as ``python -m jtus.train``
runs it (the batch split over a CPU device per core); ``infer-720p`` and
``infer-1080p``, a DLCTUS 2x frame; ``render``, the ``default`` preset's renderer (a
video's frames at both factors and the target). Writes ``result.md`` and
``result.json`` under ``docs/results/host-memory/``.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

from common import ROOT, out_dir, write

from jtus import config, hostmem, recipe, sharding, train
from jtus.bench import workloads
from jtus.sim.generate import preset
from jtus.sim.suite import get as get_scene
from jtus.sim.video import VideoRenderer

WHATS = ("train", "infer-720p", "infer-1080p", "render")
SIZES = {"infer-720p": (720, 1280), "infer-1080p": (1080, 1920)}
M_ARENA_MAX = -8  # glibc's mallopt parameter (malloc.h)


def rss_mib():
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def timed_calls(fns, calls):
    """Per function, in turn after a warm-up call each: median wall seconds, mean minor
    faults and mean kernel seconds per call; and the resident memory (MiB) after each
    round."""
    for fn in fns.values():
        fn()
    rec = {k: {"wall": [], "faults": [], "sys": []} for k in fns}
    rss = []
    for _ in range(calls):
        for k, fn in fns.items():
            r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
            fn()
            t1, r1 = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
            rec[k]["wall"].append(t1 - t0)
            rec[k]["faults"].append(r1.ru_minflt - r0.ru_minflt)
            rec[k]["sys"].append(r1.ru_stime - r0.ru_stime)
        rss.append(rss_mib())
    return {k: {"s": float(np.median(v["wall"])), "faults": float(np.mean(v["faults"])),
                "sys_ms": 1e3 * float(np.mean(v["sys"]))} for k, v in rec.items()}, rss


def workload(what):
    """``{name: blocking call}`` of one workload (jtus's, and PyTorch's where it has a
    reference)."""
    if what == "train":
        cfg = config.PRESETS["diverse"]
        plan = recipe.plan(cfg)
        sharding.use_host_devices(train.host_devices_for(cfg.crop, None), cfg.batch)
        run, _, _ = workloads.train_workload(2, cfg.crop, cfg.batch, plan.window,
                                             plan.loss_frames)
        ref = workloads.torch_reference("dlctus")
        return {"jtus": run, "torch": ref.train_workload(2, cfg.crop, cfg.batch, plan.window,
                                                         plan.loss_frames)}
    if what in SIZES:
        run, _, model, *_ = workloads.infer_workload("dlctus", 2, SIZES[what])
        ref = workloads.torch_reference("dlctus")
        return {"jtus": run, "torch": ref.infer_workload(model.config, SIZES[what])}
    p = preset("default")
    r = VideoRenderer(get_scene("textures"), p.size, p.factors, p.spp, p.spp_match,
                      targets=p.targets)
    return {"jtus": lambda: r.video("train", 0, 4)}


ALLOCATORS = {
    "default": "glibc's default (large freed buffers unmapped)",
    "kept": "freed memory kept (jtus.hostmem)",
    "one-arena": "freed memory kept, one arena for every thread",
}


def child(what, allocator, calls):
    if allocator != "default":
        assert hostmem.keep_freed_memory() == "kept", "glibc's allocator set by the environment"
    if allocator == "one-arena":  # M_ARENA_MAX (malloc.h), before any thread allocates
        assert ctypes.CDLL(None).mallopt(M_ARENA_MAX, 1) == 1
    rec, rss = timed_calls(workload(what), calls)
    return {"what": what, "allocator": allocator,
            "rss_mib_half": rss[len(rss) // 2 - 1], "rss_mib_end": rss[-1],
            "maxrss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, **rec}


def run_child(what, allocator, calls):
    out = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", what,
                          "--allocators", allocator, "--calls", str(calls)],
                         cwd=ROOT, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def _row(what, allocator, rs):
    med = lambda k, f: float(np.median([r[k][f] for r in rs]))  # noqa: E731
    d = {"what": what, "allocator": allocator, "rounds": len(rs),
         "s": med("jtus", "s"), "faults": med("jtus", "faults"), "sys_ms": med("jtus", "sys_ms"),
         "rss_growth_mib": float(np.median([r["rss_mib_end"] - r["rss_mib_half"] for r in rs])),
         "maxrss_mib": float(np.median([r["maxrss_mib"] for r in rs]))}
    if "torch" in rs[0]:
        d.update(torch_s=med("torch", "s"), torch_faults=med("torch", "faults"),
                 torch_over_jtus=float(np.median([r["torch"]["s"] / r["jtus"]["s"]
                                                  for r in rs])))
    return d


def summarize(runs):
    data = [_row(what, a, rs) for what in dict.fromkeys(r["what"] for r in runs)
            for a in ALLOCATORS
            if (rs := [r for r in runs if r["what"] == what and r["allocator"] == a])]
    rows = []
    for d in data:
        t = f"{d['torch_s'] * 1e3:.1f} | {d['torch_faults']:.0f} | " \
            f"{d['torch_over_jtus']:.2f}" if "torch_s" in d else "– | – | –"
        rows.append(f"| {d['what']} | {ALLOCATORS[d['allocator']]} | {d['s'] * 1e3:.1f} | "
                    f"{d['faults']:.0f} | {d['sys_ms']:.1f} | {t} | {d['maxrss_mib']:.0f} | "
                    f"{d['rss_growth_mib']:+.0f} |")
    head = ("| workload | allocator | jtus ms/call | jtus faults/call | kernel ms/call | "
            "PyTorch ms/call | PyTorch faults/call | PyTorch / jtus | peak RSS MiB | "
            "RSS change over the second half of the calls MiB |\n" + "| --- " * 10 + "|")
    by = {(d["what"], d["allocator"]): d for d in data}
    cross = [f"| {w} | {by[w, 'default']['torch_s'] * 1e3:.1f} | {by[w, 'kept']['s'] * 1e3:.1f} "
             f"| {by[w, 'default']['torch_s'] / by[w, 'kept']['s']:.2f} |"
             for w, a in by if a == "default" and (w, "kept") in by and "torch_s" in by[w, a]]
    if cross:
        rows.append("\nPyTorch as it runs by default against jtus as its tools run (medians "
                    "from different processes, so noisier than the same-process ratios):\n\n"
                    "| workload | PyTorch ms, default allocator | jtus ms, freed memory kept | "
                    "PyTorch / jtus |\n| --- | --- | --- | --- |\n" + "\n".join(cross))
    return head + "\n" + "\n".join(rows), data


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--what", nargs="+", choices=WHATS, default=list(WHATS))
    p.add_argument("--allocators", nargs="+", choices=ALLOCATORS, default=["default", "kept"])
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--calls", type=int, default=8, help="timed calls per process")
    p.add_argument("--name", default="host-memory")
    p.add_argument("--child", choices=WHATS, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        print(json.dumps(child(args.child, args.allocators[0], args.calls)))
        return
    out_dir(args.name)
    runs = []
    for k in range(args.rounds):
        for what in args.what:
            for a in (args.allocators if k % 2 == 0 else args.allocators[::-1]):
                runs.append(run_child(what, a, args.calls))
                print(what, a, f"{runs[-1]['jtus']['s']:.4f} s", file=sys.stderr)
        table, data = summarize(runs)
        write(args.name, table, {"summary": data, "runs": runs},
              note=f"Each row: the median over {k + 1} fresh process(es) per allocator, "
                   f"taken in turn, of {args.calls} calls after one warm-up call; faults "
                   f"are minor page faults (a page the kernel maps and zeroes on first "
                   f"touch), kernel time is the process's system time. PyTorch's reference "
                   f"runs in the same process and shares its allocator.")


if __name__ == "__main__":
    main()
