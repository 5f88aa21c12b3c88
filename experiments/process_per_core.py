"""The shipped recipe's training step run three ways on one machine, in turn, each
round: one process with its batch split over a device per core (what ``python -m
jtus.train`` does), one process per core each pinned to its core
(``jax.distributed``, gloo between the processes: ``python -m jtus.train
--distributed``, docs/distributed.md), and PyTorch's step in one process; and, as a
bound, the pinned processes each running its part of the batch alone, side by side,
with no exchange.

In one process XLA:CPU's devices share one pool of threads: where one device runs an
element-wise fusion over both cores the other device's next operation waits
(docs/performance.md, "Training on several cores"). A process pinned to one core has a
pool of one thread, and the processes exchange only the gradients, once per step.

    python experiments/process_per_core.py --rounds 3 --name process-per-core
    python experiments/process_per_core.py --exchange --name process-exchange

``--exchange`` times instead the gradients' exchange alone between the pinned processes:
DLCTUS's parameter arrays averaged over the processes one ``pmean`` per array, and as
one vector (``sharding.mean_over_devices``, what the training step does).

Each jtus variant runs in fresh processes (JAX fixes its devices when it starts); the
workers time ``--repeats`` steps after a warm-up step and process 0 reports the median.
Writes ``docs/results/<name>/result.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys

import jax
import numpy as np
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

from common import write
from jtus import config as run_config
from jtus import recipe, sharding, timing
from jtus.bench import workloads
from jtus.models import dlctus

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _workload(args):
    """``(factor, crop, batch, window, loss_frames)`` of ``--preset``'s training step."""
    cfg = run_config.PRESETS[args.preset]
    plan = recipe.plan(cfg)
    return cfg.factor, cfg.crop, cfg.batch, plan.window, plan.loss_frames


def worker(args):
    """One process of a variant: time the step, print ``{"s_per_step": ...}`` (process 0)."""
    factor, crop, batch, window, loss_frames = _workload(args)
    if args.alone:  # this process's part of the batch, on its own
        batch //= args.processes
    elif args.processes > 1:
        sharding.initialize(f"localhost:{args.port}", args.processes, args.rank)
        batch //= args.processes  # this process's part of the global batch
    else:
        sharding.use_host_devices(args.devices, batch)
    run = workloads.train_workload(factor, crop, batch, window, loss_frames)[0]
    seconds = timing.timeit(run, args.repeats)
    if args.rank == 0:
        print(json.dumps({"s_per_step": seconds, "devices": run.devices}))


def exchange_worker(args):
    """One pinned process of ``--exchange``: ms per exchange, per array and as one vector
    (median of ``--repeats`` after a warm-up call; process 0 prints them)."""
    sharding.initialize(f"localhost:{args.port}", args.processes, args.rank)
    mesh = Mesh(np.array(jax.devices()), ("data",))
    leaves = [np.asarray(x)[None] for x in
              jax.tree_util.tree_leaves(dlctus.init(jax.random.PRNGKey(0)))]
    x = sharding.shard(leaves, mesh, 0)

    def timed(mean):
        f = jax.jit(jax.shard_map(mean, mesh=mesh, in_specs=P("data"), out_specs=P("data")))
        return 1e3 * timing.timeit(lambda: jax.block_until_ready(f(x)), args.repeats)

    res = {"arrays": len(leaves), "values": int(sum(v.size for v in leaves)),
           "ms_per_array": timed(lambda v: jax.lax.pmean(v, "data")),
           "ms_one_vector": timed(lambda v: next(sharding.mean_over_devices([v])))}
    if args.rank == 0:
        print(json.dumps(res))


def _free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _start(args, extra, core=None):
    cmd = [sys.executable, os.path.abspath(__file__), "--preset", args.preset,
           "--repeats", str(args.repeats)] + extra
    pin = (lambda: os.sched_setaffinity(0, {core})) if core is not None else None
    return subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True, preexec_fn=pin)


def _result(proc):
    out, _ = proc.communicate(timeout=1800)
    if proc.returncode:
        raise SystemExit(f"a worker failed (exit {proc.returncode})")
    return json.loads(out.strip().splitlines()[-1])


def one_process(args):
    """Seconds per step of one process splitting its batch over a device per core."""
    return _result(_start(args, ["--worker", "--devices", str(args.cores)]))["s_per_step"]


def process_per_core(args, mode="--worker", alone=False):
    """Process 0's result of ``--cores`` processes, each pinned to its core: seconds
    per step (``mode`` ``--worker``, ``alone``: without joining each other) or the
    exchange's times (``--exchange-worker``)."""
    port = str(_free_port())
    procs = [_start(args, [mode, "--processes", str(args.cores), "--rank", str(r),
                           "--port", port] + (["--alone"] if alone else []), core=core)
             for r, core in enumerate(sorted(os.sched_getaffinity(0))[:args.cores])]
    res = [_result(p) if r == 0 else p.communicate(timeout=1800) for r, p in enumerate(procs)]
    if any(p.returncode for p in procs):
        raise SystemExit("a worker failed")
    return res[0]["s_per_step"] if mode == "--worker" else res[0]


def torch_step(args):
    """Seconds per step of PyTorch's reference step (this process, every core)."""
    fn = workloads.torch_reference("dlctus").train_workload(*_workload(args))
    return timing.timeit(fn, args.repeats)


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="diverse")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--repeats", type=int, default=9, help="steps each variant times a round")
    p.add_argument("--name", default="process-per-core")
    p.add_argument("--exchange", action="store_true",
                   help="time the gradients' exchange alone, per array and as one vector")
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--exchange-worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--alone", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--processes", type=int, default=1, help=argparse.SUPPRESS)
    p.add_argument("--rank", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--port", default="", help=argparse.SUPPRESS)
    p.add_argument("--devices", type=int, default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        return worker(args)
    if args.exchange_worker:
        return exchange_worker(args)
    args.cores = len(os.sched_getaffinity(0))
    if args.cores < 2:
        raise SystemExit("process_per_core.py: needs at least 2 cores")
    if args.rounds < 1 or args.repeats < 1:
        raise SystemExit("--rounds, --repeats: expected positive counts")
    if args.exchange:
        r = process_per_core(args, "--exchange-worker")
        write(args.name, f"DLCTUS's {r['arrays']} parameter arrays ({r['values']:,} float32 "
              f"values) averaged over {args.cores} processes on one machine, each pinned "
              f"to its core (gloo): {r['ms_per_array']:.2f} ms with one `pmean` per array, "
              f"{r['ms_one_vector']:.2f} ms as one vector (`sharding.mean_over_devices`); "
              f"medians of {args.repeats} calls after a warm-up call.", r)
        return
    factor, crop, batch, window, loss_frames = _workload(args)
    if batch % args.cores:
        raise SystemExit(f"--preset: its batch {batch} does not split over {args.cores} cores")
    names = ("one process, a device per core", "a process per core, pinned", "PyTorch",
             "pinned, each alone")
    rounds = []
    for r in range(args.rounds):
        t = dict(zip(names, (one_process(args), process_per_core(args), torch_step(args),
                             process_per_core(args, alone=True))))
        rounds.append(t)
        print(f"round {r + 1}: " + ", ".join(f"{k} {v:.3f} s" for k, v in t.items()),
              file=sys.stderr)
    med = {k: float(np.median([t[k] for t in rounds])) for k in names}
    lines = [f"DLCTUS {factor}x training step of the `{args.preset}` preset (crop {crop}, "
             f"batch {batch} in all, {window} frames, loss on the last {loss_frames}, the "
             f"model's loss, Adam), random data, {args.cores} cores; seconds per step, "
             f"median of {args.repeats} steps after a warm-up step, each variant in fresh "
             f"processes, the four in turn each round; the last: the pinned processes "
             f"side by side, each on its part of the batch, exchanging nothing.", "",
             "| round | " + " | ".join(names) + " | PyTorch / one process | "
             "PyTorch / a process per core |", "| --- " * (len(names) + 3) + "|"]
    for i, t in enumerate(rounds + [med]):
        label = str(i + 1) if i < len(rounds) else "median"
        v = [t[k] for k in names]
        lines.append(f"| {label} | " + " | ".join(f"{x:.3f}" for x in v)
                     + f" | {v[2] / v[0]:.2f} | {v[2] / v[1]:.2f} |")
    write(args.name, "\n".join(lines), {"rounds": rounds, "median": med,
                                        "cores": args.cores, "preset": args.preset})


if __name__ == "__main__":
    main()
