"""The shipped recipe's training step on one XLA CPU device against the same step with
its batch split over several (``jax_num_cpu_devices``, ``sharding.batch_parallel``; what
``python -m jtus.train`` does by default), and PyTorch's step, all in one process,
round-robin, so every variant sees the same machine (docs/performance.md, "Training on
several cores").

XLA fixes its devices when JAX starts, so the one-device step runs on the first of the
process's devices (inference there measured the same as in a one-device process);
each round is ``timing.timeit_round_robin`` of the three steps.

    python experiments/host_devices.py --out docs/results/train-host-devices
    python experiments/host_devices.py --what inference   # the trunk of one frame, rows split
    python experiments/host_devices.py --what allreduce   # the gradients' exchange alone

Writes ``result.json`` and ``result.md`` under ``--out``; also how busy the cores are
(process CPU seconds per wall second) while each variant runs.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys

import jax
import jax.numpy as jnp
import numpy as np
import torch
from jax.sharding import Mesh
from jax.sharding import PartitionSpec as P

from common import cpu_per_wall
from jtus import config as run_config
from jtus import models, recipe, sharding, timing
from jtus.bench import workloads
from jtus.models import dlctus, kernels, layers


def op_threads(repeats=300):
    """``{op: (ms, CPU/wall)}`` of one of the trunk's 3x3 32->32 convolutions at the
    training shape (batch 4, 32x32 at H/4, edge-padded as DLCTUS's), a matmul of the
    same FLOPs (the convolution's im2col product ``[4096, 288] @ [288, 32]``), and
    PyTorch's convolution of the same shape: which of them XLA:CPU spreads over cores."""
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.uniform(size=(4, 32, 32, 32)), jnp.float32)
    k = jnp.asarray(rng.uniform(-0.1, 0.1, size=(3, 3, 32, 32)), jnp.float32)
    b = jnp.zeros((32,), jnp.float32)
    a = jnp.asarray(rng.uniform(size=(4096, 288)), jnp.float32)
    conv, dot = jax.jit(layers.conv_edge), jax.jit(jnp.matmul)
    tx = torch.from_numpy(np.array(x)).permute(0, 3, 1, 2).contiguous()
    tk = torch.from_numpy(np.array(k)).permute(3, 2, 0, 1).contiguous()

    def torch_conv():
        with torch.no_grad():
            torch.nn.functional.conv2d(torch.nn.functional.pad(tx, (1, 1, 1, 1), "replicate"),
                                       tk)

    k2 = k.reshape(288, 32)
    ops = {"XLA convolution": lambda: conv(x, k, b).block_until_ready(),
           "XLA matmul, same FLOPs": lambda: dot(a, k2).block_until_ready(),
           "PyTorch convolution": torch_conv}
    out = {}
    for name, fn in ops.items():
        seconds, busy = cpu_per_wall(fn, repeats)
        out[name] = (seconds * 1e3, busy)
    return out


HALO = 8  # the trunk's eight 3x3 convolutions reach 8 rows across a cut


def trunk_rows_split(size, repeats=5, rounds=3):
    """DLCTUS's trunk (the network's 95% of FLOPs) at the H/4 x W/4 of an HR ``size``,
    batch 1, on one device against the same with its rows cut between the devices, each
    computing its rows plus ``HALO`` on either side (edge-padded at the image's own
    edges, so the values are equal): ``(max |difference|, [(one ms, split ms)] per
    round)``. What splitting an inference frame over the devices could gain."""
    config = dlctus.Config(factor=2)
    params = dlctus.init(jax.random.PRNGKey(0), config)
    rows, cols = size[0] // 4, size[1] // 4
    h = jnp.asarray(np.random.default_rng(0).uniform(size=(1, rows, cols, 32)), jnp.float32)
    n = len(jax.devices())
    per = -(-rows // n)
    size_with_halo = min(per + 2 * HALO, rows)

    def local(p, x):
        start = jax.lax.axis_index("rows") * per
        lo = jnp.clip(start - HALO, 0, rows - size_with_halo)
        part = jax.lax.dynamic_slice_in_dim(x, lo, size_with_halo, axis=1)
        out = kernels.trunk(p, part, config.blocks, "xla")
        return jax.lax.dynamic_slice_in_dim(out, start - lo, per, axis=1)

    mesh = Mesh(np.array(jax.devices()), ("rows",))
    one = jax.jit(lambda p, x: kernels.trunk(p, x, config.blocks, "xla"))
    split = jax.jit(jax.shard_map(local, mesh=mesh, in_specs=(P(), P()),
                                  out_specs=P(None, "rows"), check_vma=False))
    diff = float(jnp.max(jnp.abs(one(params, h) - np.asarray(split(params, h))[:, :rows])))
    times = []
    for _ in range(rounds):
        t = timing.timeit_round_robin({"one": lambda: one(params, h).block_until_ready(),
                                       "split": lambda: split(params, h).block_until_ready()},
                                      repeats)
        times.append((t["one"] * 1e3, t["split"] * 1e3))
    return diff, times


def _report(argv, **fields):
    """The report's hardware and command, then ``fields``."""
    return {"hardware": timing.hardware(), "command": "python experiments/host_devices.py "
            + shlex.join(argv if argv is not None else sys.argv[1:]), **fields}


def _write(out, report, lines):
    """``result.json`` and ``result.md`` (the command and hardware, then ``lines``) under
    ``out``; the Markdown printed."""
    os.makedirs(out, exist_ok=True)
    with open(os.path.join(out, "result.json"), "w") as f:
        json.dump(report, f, indent=1)
    md = [f"Command: `{report['command']}`", "",
          f"Hardware: {timing.hardware_line(report['hardware'])}.", ""] + lines
    with open(os.path.join(out, "result.md"), "w") as f:
        f.write("\n".join(md) + "\n")
    print("\n".join(md))


def inference_report(args, argv):
    """``--what inference``: ``trunk_rows_split`` at 720p and 1080p, to ``--out``."""
    sizes = {"720p": (720, 1280), "1080p": (1080, 1920)}
    res = {name: trunk_rows_split(size, args.repeats, args.rounds) for name, size in sizes.items()}
    report = _report(argv, devices=len(jax.devices()), trunk={
        k: {"max_abs_diff": d, "ms_one_split": t} for k, (d, t) in res.items()})
    md = [f"DLCTUS's trunk (four residual blocks, eight 3x3 32->32 convolutions at H/4 x W/4) "
          f"on one frame, on one XLA CPU device against its rows cut between "
          f"{report['devices']} devices (each with {HALO} rows of halo; the same values); ms, "
          f"medians of {args.repeats} round-robin repeats per round.", "",
          "| size | round | one device | split | one / split | max abs difference |",
          "| --- | --- | --- | --- | --- | --- |"]
    for name, (d, times) in res.items():
        md += [f"| {name} | {i + 1} | {a:.1f} | {b:.1f} | {a / b:.2f} | {d:.1e} |"
               for i, (a, b) in enumerate(times)]
    _write(args.out, report, md)


def allreduce_report(args, argv, repeats=200):
    """``--what allreduce``: the split step's exchange alone, a ``psum`` over the devices
    of a float32 vector the size of DLCTUS's parameters (each device holding its own),
    ms per call with dispatch, the median of ``repeats`` after a warm-up call."""
    n_params = models.param_count(dlctus.init(jax.random.PRNGKey(0)))
    devices = jax.devices()
    if len(devices) < 2:
        raise SystemExit("--what allreduce: needs several devices (--devices)")
    mesh = Mesh(np.array(devices), ("data",))
    x = jax.device_put(jnp.ones((len(devices), n_params), jnp.float32),
                       jax.sharding.NamedSharding(mesh, P("data")))
    f = jax.jit(jax.shard_map(lambda v: jax.lax.psum(v, "data"), mesh=mesh,
                              in_specs=P("data"), out_specs=P("data")))
    ms = 1e3 * timing.timeit(lambda: f(x).block_until_ready(), repeats)
    report = _report(argv, devices=len(devices), params=n_params, ms_median=ms)
    _write(args.out, report, [
        f"A `psum` over {len(devices)} XLA CPU devices of {n_params:,} float32 values each "
        f"(DLCTUS's parameters: the split training step's gradient exchange), alone: "
        f"{ms:.3f} ms per call, median of {repeats}, dispatch included."])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--devices", type=int, default=None,
                   help="XLA CPU devices (default: one per core this process may use)")
    p.add_argument("--preset", default="diverse", help="the jtus.train preset whose step is timed")
    p.add_argument("--rounds", type=int, default=4)
    p.add_argument("--repeats", type=int, default=9, help="steps per variant in each round")
    p.add_argument("--what", choices=("train", "inference", "allreduce"), default="train",
                   help="inference: DLCTUS's trunk on one frame, its rows split over the "
                        "devices (trunk_rows_split), instead of the training step; "
                        "allreduce: the split step's gradient exchange alone")
    p.add_argument("--out", default=None, help="default: docs/results/train-host-devices, "
                                               "or inference-host-devices with --what inference")
    args = p.parse_args(argv)
    args.out = args.out or f"docs/results/{args.what}-host-devices"
    n = sharding.use_host_devices(args.devices)  # before JAX's first computation
    if args.what == "inference":
        return inference_report(args, argv)
    if args.what == "allreduce":
        return allreduce_report(args, argv)

    cfg = run_config.PRESETS[args.preset]
    plan = recipe.plan(cfg)
    w = (cfg.factor, cfg.crop, cfg.batch, plan.window, plan.loss_frames)
    one = workloads.train_workload(*w, split=False)[0]
    split = workloads.train_workload(*w)[0]
    if split.devices < 2:
        p.error(f"--devices: the step ran on one device ({n} asked, batch {cfg.batch})")
    steps = {"one device": one, f"split over {split.devices}": split,
             "torch": workloads.torch_reference("dlctus").train_workload(*w)}
    rounds = []
    for r in range(args.rounds):
        t = timing.timeit_round_robin(steps, args.repeats)
        rounds.append(t)
        print(f"  round {r + 1}: " + ", ".join(f"{k} {v:.3f} s" for k, v in t.items()),
              file=sys.stderr)
    busy = {k: cpu_per_wall(f, 3)[1] for k, f in steps.items()}
    ops = op_threads()
    names = list(steps)
    med = {k: float(np.median([t[k] for t in rounds])) for k in names}
    report = _report(argv, devices=split.devices, workload=dict(zip(
        ("factor", "crop", "batch", "seq", "loss_frames"), w)), rounds=rounds, median=med,
        cpu_per_wall=busy, ops=ops)
    md = [f"DLCTUS {w[0]}x training step of the `{args.preset}` preset (crop {w[1]}, batch "
          f"{w[2]}, {w[3]} frames, loss on the last {w[4]}, the model's loss, Adam), "
          f"random data; seconds per step, medians of {args.repeats} round-robin repeats "
          f"per round; CPU/wall: process CPU seconds per wall second while the step ran.",
          "", "| round | " + " | ".join(names) + " | one / split | torch / one | torch / split |",
          "| --- " * (len(names) + 4) + "|"]
    for i, t in enumerate(rounds + [med]):
        label = str(i + 1) if i < len(rounds) else "median"
        vals = [t[k] for k in names]
        md.append(f"| {label} | " + " | ".join(f"{v:.3f}" for v in vals)
                  + f" | {vals[0] / vals[1]:.2f} | {vals[2] / vals[0]:.2f} | "
                  f"{vals[2] / vals[1]:.2f} |")
    md.append("| CPU/wall | " + " | ".join(f"{busy[k]:.2f}" for k in names) + " | | | |")
    md += ["", "One operation of the step at a time (the first of the process's devices; "
           "ms per call after a warm-up call, dispatch included):", "",
           "| operation | ms | CPU/wall |", "| --- | --- | --- |"]
    md += [f"| {name} | {ms:.3f} | {busy_:.2f} |" for name, (ms, busy_) in ops.items()]
    _write(args.out, report, md)


if __name__ == "__main__":
    main()
