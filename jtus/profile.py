"""``python -m jtus.profile``: where a model's step spends its time, per XLA op.

    python -m jtus.profile                                  # the bench's DLCTUS training step
    python -m jtus.profile --what infer --size 1080p --factor 4
    python -m jtus.profile --model nsrr --factor 2          # any trainable model's step
    python -m jtus.profile --out docs/results/profile-cpu/profile-train-cpu  # .json and .md

The step is the bench's workload (``jtus.bench.train_workload`` / ``infer_workload``),
jitted and warm. A few steps are traced; every XLA op the trace shows (a *thunk* on
XLA:CPU) is matched by name to its instruction in the compiled module, whose metadata
says which JAX code made it. Ops are then summed by

- **stage**: the named scope of the model's step they come from (its ``Spec.stages``:
  DLCTUS's ``input_upsampling``, ``reprojection``, ``network``, ``output``; NSRR's
  ``feature_extraction``, ``reprojection``, ``reweighting``, ``reconstruction``; ...),
  the loss and the optimizer (``TRAINING_STAGES``, scopes in ``jtus.rollout`` and
  ``jtus.train``), or ``other`` (the scan's own bookkeeping: stacking residuals,
  copies, loop control);
- **pass**: ``forward`` or ``backward`` (ops made by transposition);
- **kind**: convolution, matmul, gather, scatter, concatenate, copy/slice, elementwise
  fusion, reduction, collective (a split step's gradient exchange: its span includes the
  wait for the slowest device), other, and two kinds of a scan's bookkeeping: *fill*
  (materializing a broadcast, and copies of one: JAX lowers a scan's stacked outputs on
  the CPU as buffers filled with zeros, which XLA:CPU makes by copying one broadcast
  into each) and *stacking* (a dynamic-update-slice in a loop body writing one frame's
  slice of a stacked buffer: the residuals the backward pass reads, or the scan's
  outputs).

A fusion carries the metadata of its root operation, so work XLA fused into it from
an earlier stage is filed under the root's stage (TUS's history read, fused into its
output blend, shows under ``output``); the largest single ops the report lists show
which fusions those are.

``--host-devices N`` profiles the training step split over ``N`` XLA CPU devices, as
``python -m jtus.train`` runs it from crop 128 on (``sharding.use_host_devices``; each
device runs the whole program on its part of the batch). The spans of all devices are
summed and divided by ``N``: the report's times are one device's.

Each op's time is its span on the thread that ran it: the op's wall time, during which
its own worker threads (YNNPACK, Eigen) may help it. XLA:CPU mostly runs one op at a
time here, so the spans add up to about the step's wall time (printed beside them,
measured untraced); where independent ops overlap the sum is larger. Ops that XLA
launches asynchronously can show less than they take; read shares, not single ops.
"""

from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import re
import sys
import tempfile

import jax

from jtus import bench, cli, files, models, sampling, sharding, timing

TRAINING_STAGES = ("loss", "optimizer")
TOP_OPS = 25  # the single ops a report lists (the largest), 10 of them in its markdown


def stages_of(name):
    """The stages a profile of model ``name`` files its ops under, in order: the named
    scopes its step labels (``Spec.stages``), then the loss and the optimizer."""
    return tuple(models.spec(name).stages) + TRAINING_STAGES


DEFAULT_STAGES = stages_of("dlctus")  # the bench's model, profiled without --model
_INSTR = re.compile(r"\s*(?:ROOT )?%?([\w.\-]+) = .*? ([a-z][\w\-]*)\(")
_OPNAME = re.compile(r'op_name="([^"]+)"')
_OPERAND = re.compile(r"%?([\w.\-]+)")
_CONTAINERS = {"while", "call", "conditional"}


def hlo_ops(text):
    """``{instruction name: (opcode, op_name metadata, first operand's name)}`` from a
    compiled module's text."""
    out = {}
    for line in text.splitlines():
        m = _INSTR.match(line)
        if m:
            on = _OPNAME.search(line)
            operand = _OPERAND.match(line, m.end())
            out[m.group(1)] = (m.group(2), on.group(1) if on else "",
                               operand.group(1) if operand else "")
    return out


def classify(name, opcode, op_name, operand="", stages=DEFAULT_STAGES):
    """(stage, pass, kind) of one op; ``operand``: the name of its first operand;
    ``stages``: the scope names to file it under (the first found in ``op_name``)."""
    stage = next((s for s in stages if f"/{s}/" in op_name or op_name.endswith("/" + s)),
                 "other")
    pass_ = "backward" if "transpose(" in op_name else "forward"
    if "conv_general_dilated" in op_name and opcode in ("fusion", "convolution", "custom-call"):
        kind = "convolution"
    elif opcode == "dot" or op_name.endswith("/dot_general"):
        kind = "matmul"
    elif name.startswith("wrapped_broadcast") or (
            opcode == "copy" and operand.startswith(("wrapped_broadcast", "broadcast"))):
        kind = "fill"
    elif "/while/body/" in op_name and op_name.endswith("/dynamic_update_slice"):
        kind = "stacking"
    elif opcode in ("all-reduce", "all-gather", "reduce-scatter", "all-to-all",
                    "collective-permute"):
        kind = "collective"  # a split step's exchange, and its wait for the other devices
    elif opcode in ("gather", "scatter", "concatenate"):
        kind = opcode
    elif op_name.endswith("/gather") or "gather" in name:
        kind = "gather"
    elif op_name.endswith(("/scatter-add", "/scatter_add")) or "scatter" in name:
        kind = "scatter"
    elif opcode in ("copy", "dynamic-update-slice", "dynamic-slice", "slice", "bitcast",
                    "transpose") or name.startswith(("copy", "wrapped_slice",
                                                     "dynamic-update-slice", "wrapped_transpose")):
        kind = "copy/slice"
    elif name.startswith("ynn_fusion"):
        kind = "reduction"  # YNNPACK runs reductions too
    elif opcode == "fusion":
        kind = "elementwise fusion"
    else:
        kind = "other"
    return stage, pass_, kind


def trace_ops(run, hlo_text, steps, logdir):
    """Trace ``steps`` calls of ``run``; returns ``{op name: total ns}`` of the leaf ops
    found in ``hlo_text`` and the number of op events that matched nothing."""
    jax.profiler.start_trace(logdir)
    for _ in range(steps):
        run()
    jax.profiler.stop_trace()
    files = sorted(glob.glob(os.path.join(logdir, "**", "*.xplane.pb"), recursive=True),
                   key=os.path.getmtime)
    if not files:
        raise RuntimeError(f"{logdir}: the profiler wrote no .xplane.pb")
    ops = hlo_ops(hlo_text)
    data = jax.profiler.ProfileData.from_file(files[-1])
    totals, unmatched = collections.Counter(), 0
    for plane in data.planes:
        for line in plane.lines:
            if line.name == "python":
                continue
            for ev in line.events:
                info = ops.get(ev.name)
                if info is None:
                    unmatched += not ev.name.startswith("ThunkExecutor")
                    continue
                if info[0] in _CONTAINERS:
                    continue  # a loop's span contains its body's ops
                totals[ev.name] += ev.duration_ns
    return totals, ops, unmatched


def summarize(totals, ops, steps, stages=DEFAULT_STAGES):
    by = {k: collections.Counter() for k in ("stage", "pass", "kind", "stage_pass", "stage_kind")}
    top = []
    for name, ns in totals.items():
        stage, pass_, kind = classify(name, *ops[name], stages=stages)
        op_name = ops[name][1]
        ms = ns / 1e6 / steps
        by["stage"][stage] += ms
        by["pass"][pass_] += ms
        by["kind"][kind] += ms
        by["stage_pass"][f"{stage}/{pass_}"] += ms
        by["stage_kind"][f"{stage}/{pass_}/{kind}"] += ms
        top.append((ms, name, stage, pass_, kind, op_name))
    top.sort(reverse=True)
    return {"op_ms_per_step": sum(by["stage"].values()),
            **{k: dict(v.most_common()) for k, v in by.items()},
            "top_ops": [dict(ms=m, op=n, stage=s, pass_=p, kind=k, op_name=o)
                        for m, n, s, p, k, o in top[:TOP_OPS]]}


def profile(run, hlo_text, steps=3, stages=DEFAULT_STAGES, devices=1):
    """Time ``run`` ``steps`` times (``timing.timeit``), then trace it as many times; returns
    ``{"steps", "wall_ms" (median, untraced), "unmatched_events", "stages", "devices",
    "summary"}``, the ops filed under ``stages`` (``stages_of``). ``run`` runs one
    program on each of ``devices`` devices: the summary's times are the spans of all
    of them divided by ``devices``, one device's."""
    wall = timing.timeit(run, steps)
    with tempfile.TemporaryDirectory() as logdir:
        totals, ops, unmatched = trace_ops(run, hlo_text, steps, logdir)
    if not totals:
        raise RuntimeError("the trace held no XLA ops that match the compiled module")
    return {"steps": steps, "wall_ms": 1e3 * wall, "unmatched_events": unmatched,
            "stages": list(stages), "devices": devices,
            "summary": summarize(totals, ops, steps * devices, stages)}


def markdown(report):
    s = report["summary"]
    total = s["op_ms_per_step"]
    n = report.get("devices", 1)
    per = (f" on each of {n} devices (every device's spans summed, divided by {n}; all "
           f"times below are per device)") if n > 1 else ""
    lines = [f"Profile of {report['workload']} ({report['hardware']['cpu']}, "
             f"{report['hardware']['cores']} cores, JAX {report['hardware']['jax']}).",
             f"Command: `{report['command']}`", "",
             f"Wall time {report['wall_ms']:.1f} ms per step (untraced, median of "
             f"{report['steps']}); op spans summed {total:.1f} ms per step{per}.", "",
             "| stage | forward ms | backward ms | share |",
             "| --- | --- | --- | --- |"]
    for stage in tuple(report.get("stages", DEFAULT_STAGES)) + ("other",):
        f = s["stage_pass"].get(f"{stage}/forward", 0.0)
        b = s["stage_pass"].get(f"{stage}/backward", 0.0)
        if f or b:
            lines.append(f"| {stage} | {f:.1f} | {b:.1f} | {100 * (f + b) / total:.0f}% |")
    lines += ["", "| kind of op | ms | share |", "| --- | --- | --- |"]
    lines += [f"| {k} | {v:.1f} | {100 * v / total:.0f}% |" for k, v in s["kind"].items()]
    lines += ["", "Largest stage/pass/kind groups:", "",
              "| stage / pass / kind | ms | share |", "| --- | --- | --- |"]
    lines += [f"| {k} | {v:.1f} | {100 * v / total:.0f}% |"
              for k, v in list(s["stage_kind"].items())[:12]]
    lines += ["", "Largest single ops (summed over a step's loop iterations; the JAX "
              "operation that made each, from the compiled module's metadata):", "",
              "| op | stage / pass / kind | ms | share | made by |",
              "| --- | --- | --- | --- | --- |"]
    lines += [f"| {o['op']} | {o['stage']}/{o['pass_']}/{o['kind']} | {o['ms']:.1f} | "
              f"{100 * o['ms'] / total:.0f}% | `{_short(o['op_name'])}` |"
              for o in s["top_ops"][:10]]
    return "\n".join(lines)


def _short(op_name, parts=3):
    """The last ``parts`` components of an op's JAX name (``.../network/conv_general_dilated``)."""
    return "/".join(op_name.split("/")[-parts:]) if op_name else "-"


def _parser():
    p = argparse.ArgumentParser(prog="python -m jtus.profile", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--what", choices=("train", "infer"), default="train")
    p.add_argument("--model", default="dlctus", choices=models.NAMES,
                   help="any model (training: any trainable one)")
    p.add_argument("--factor", type=int, default=2)
    p.add_argument("--size", choices=tuple(bench.SIZES), default="1080p", help="inference")
    p.add_argument("--crop", type=int, default=128)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--seq", type=int, default=8)
    p.add_argument("--loss-frames", type=int, default=5)
    p.add_argument("--warp", default="bicubic", choices=sampling.METHODS)
    p.add_argument("--steps", type=int, default=3, help="steps traced and timed")
    p.add_argument("--host-devices", type=int, default=1,
                   help="training: split the batch over this many XLA CPU devices, as "
                        "python -m jtus.train does from crop 128 on (default 1)")
    p.add_argument("--out", help="write OUT.json and OUT.md")
    return p


def _check(p, args):
    """Refuse bad arguments (``p.error``) before any work."""
    if args.steps < 1:
        p.error(f"--steps: expected a positive count, got {args.steps}")
    if args.host_devices < 1:
        p.error(f"--host-devices: expected a positive count, got {args.host_devices}")
    if args.host_devices > 1 and args.what != "train":
        p.error("--host-devices: only the training step splits over devices (--what train)")
    if args.host_devices > 1 and args.batch % args.host_devices:
        p.error(f"--host-devices: {args.host_devices} devices do not divide --batch "
                f"{args.batch}")
    if args.what == "train" and not models.spec(args.model).trainable:
        p.error(f"--model: {args.model} has no training step (expected one of "
                f"{[n for n in models.NAMES if models.spec(n).trainable]})")
    if args.out:
        for suffix in (".json", ".md"):
            try:
                files.check_out_file(args.out + suffix, field="--out", kind="a file stem")
            except ValueError as e:
                p.error(str(e))


def _training(p, args):
    """``(run, hlo, workload description)`` of the training step, split over
    ``--host-devices`` devices."""
    if args.host_devices > 1:
        sharding.use_host_devices(args.host_devices, args.batch)
    run, hlo, model = bench.train_workload(args.factor, args.crop, args.batch, args.seq,
                                           args.loss_frames, warp=args.warp,
                                           name=args.model, split=args.host_devices > 1)
    if run.devices != args.host_devices:
        p.error(f"--host-devices: asked for {args.host_devices}, but this process's JAX "
                f"already runs on {len(jax.devices())} device(s) (set before its first "
                f"computation)")
    warp = f", {args.warp} warp" if hasattr(model.config, "warp") else ""
    split = f"; the batch split over {run.devices} XLA CPU devices" if run.devices > 1 else ""
    return run, hlo, (f"the {args.model.upper()} {args.factor}x training step (crop "
                      f"{args.crop}, batch {args.batch}, {args.seq} frames, loss on the last "
                      f"{args.loss_frames}{warp}, its own loss, Adam{split})")


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    p = _parser()
    args = p.parse_args(argv)
    _check(p, args)
    if args.what == "train":
        run, hlo, workload = _training(p, args)
    else:
        over = {"warp": args.warp} if hasattr(models.spec(args.model).config(args.factor), "warp") \
            else {}
        run, hlo, *_ = bench.infer_workload(args.model, args.factor, bench.SIZES[args.size],
                                            **over)
        workload = (f"one {args.model.upper()} {args.factor}x inference step at {args.size}"
                    + (f" ({args.warp} warp)" if over else ""))
    run()  # compile
    report = {"hardware": timing.hardware(), "workload": workload,
              "command": "python -m jtus.profile " + " ".join(argv),
              **profile(run, hlo(), args.steps, stages_of(args.model),
                        getattr(run, "devices", 1))}
    md = markdown(report)
    if args.out:
        for suffix, text in ((".json", json.dumps(report, indent=1)), (".md", md + "\n")):
            with files.atomic_path(args.out + suffix) as tmp, open(tmp, "w") as fh:
                fh.write(text)
    print(md)
    return 0


if __name__ == "__main__":
    cli.run(main)
