"""``python -m jtus.bench``: time per frame and per training step, against the machine's
peak and against the PyTorch reference, all measured in one run.

    python -m jtus.bench                                   # DLCTUS, 720p and 1080p, 2x and 4x
    python -m jtus.bench --models dlctus jau tus --sizes 720p --factors 4 --json
    python -m jtus.bench --what train --train-crop 128 --train-seq 8 --train-batch 4

Every timing is jitted, warm (the first call compiles and is not counted), blocked
until ready, and the median of ``--repeats`` runs. The peak is a large float32 matmul
and two convolutions (DLCTUS's own 3x3 32->32 layer at the 1080p network size, and a
3x3 64->64 one), timed in the same run, so ratios are taken side by side on a noisy
machine. The PyTorch reference (``tests/torch_dlctus.py``, loaded by path: needs
``torch`` and a source checkout) runs the same workloads, each repeat alternating with jtus's
(``timeit_pair``), so both medians come from the same minutes of a noisy machine;
ratios are torch time / jtus time.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jtus import files, sampling

SIZES = {"720p": (720, 1280), "1080p": (1080, 1920), "256": (256, 256), "64": (64, 64)}


def hardware():
    name = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    name = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    dev = jax.devices()[0]
    return {"cpu": name, "cores": os.cpu_count(), "jax": jax.__version__,
            "backend": dev.platform, "device": getattr(dev, "device_kind", str(dev))}


def timeit(fn, repeats=5):
    """Median seconds of ``fn()`` (which must block) after one warm-up call."""
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts))


def timeit_round_robin(fns, repeats=5):
    """``{name: median seconds}`` of each blocking ``fns[name]()``, timed in turn (a, b,
    c, a, b, c, ...) after one warm-up call each, so that all see the same machine: on
    a shared, noisy machine their ratios are then steadier than separate medians'."""
    for fn in fns.values():
        fn()
    times = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            times[k].append(time.perf_counter() - t0)
    return {k: float(np.median(v)) for k, v in times.items()}


def timeit_pair(fa, fb, repeats=5):
    """Median seconds of ``fa()`` and of ``fb()``, timed alternately
    (``timeit_round_robin`` of the two)."""
    t = timeit_round_robin({"a": fa, "b": fb}, repeats)
    return t["a"], t["b"]


def peaks(repeats):
    out = {}
    n = 2048
    a = jnp.asarray(np.random.default_rng(0).normal(size=(n, n)), jnp.float32)
    mm = jax.jit(lambda x: x @ x)
    out["matmul_gflops"] = 2 * n ** 3 / timeit(lambda: mm(a).block_until_ready(), repeats) / 1e9
    from jtus.models import layers
    for name, (h, w, c) in {"conv_dlctus_gflops": (270, 480, 32),
                            "conv_64_gflops": (256, 256, 64)}.items():
        x = jnp.asarray(np.random.default_rng(1).normal(size=(1, h, w, c)), jnp.float32)
        k = jnp.asarray(np.random.default_rng(2).normal(size=(3, 3, c, c)), jnp.float32) * 0.05
        cv = jax.jit(lambda x, k: layers.conv(x, k))
        flops = h * w * c * c * 9 * 2
        out[name] = flops / timeit(lambda: cv(x, k).block_until_ready(), repeats) / 1e9
    return out


def random_frame(h, w, b=1, seed=0):
    """A random LR ``Frame`` (``b`` x ``h`` x ``w``) for timings: colour and jitter
    uniform, depth in [0.5, 1), motion normal with 0.5 LR pixels' spread."""
    from jtus.frame import Frame
    r = np.random.default_rng(seed)
    return Frame(jnp.asarray(r.uniform(size=(b, h, w, 3)), jnp.float32),
                 jnp.asarray(r.uniform(0.5, 1.0, size=(b, h, w, 1)), jnp.float32),
                 jnp.asarray(r.normal(scale=0.5, size=(b, h, w, 2)), jnp.float32),
                 jnp.asarray(r.uniform(size=(b, 2)), jnp.float32))


def is_dlctus(name):
    """A registry name built by DLCTUS's module: it has the network-only timing, the
    dtype and formulation variants and the PyTorch reference."""
    from jtus import models
    from jtus.models import dlctus

    return models.spec(name).make is dlctus.make


def infer_workload(name, factor, size, dtype="float32", **overrides):
    """One jitted inference step of ``name`` at HR ``size``, its state donated.
    Returns ``(run, hlo, model, params, state, frame)``: ``run()`` steps once and
    blocks; ``hlo()`` is the compiled module's text (for profiles)."""
    from jtus import models

    H, W = size
    has_dtype = "dtype" in {f.name for f in dataclasses.fields(models.spec(name).config(factor))}
    over = dict({"dtype": dtype} if has_dtype else {}, **overrides)
    model = models.build(name, factor, **over)
    params = model.init(jax.random.PRNGKey(0))
    frame = random_frame(H // factor, W // factor)
    state = [model.init_state(frame)]
    step = jax.jit(model.step, donate_argnums=(1,))

    def run():
        out, state[0] = step(params, state[0], frame)
        out.block_until_ready()

    def hlo():
        return step.lower(params, state[0], frame).compile().as_text()

    return run, hlo, model, params, state, frame


def bench_infer(name, factor, size, repeats, dtype="float32", against=None, **overrides):
    """One model's inference timing record. ``against``: a blocking callable (the
    PyTorch reference's step) timed alternately with jtus's (``timeit_pair``)."""
    from jtus import cost
    from jtus.models import dlctus

    H, W = size
    run, _, model, params, state, frame = infer_workload(name, factor, size, dtype, **overrides)
    c = cost.cost(name, model.config, H, W)
    if against is None:
        seconds = timeit(run, repeats)
    else:
        seconds, other = timeit_pair(run, against, repeats)
    rec = {"model": name, "factor": factor, "size": f"{H}x{W}", "dtype": dtype, **overrides,
           "ms": seconds * 1e3, "gflop": c.flops / 1e9, "gflops": c.flops / seconds / 1e9,
           "mbytes": c.bytes / 1e6}
    if against is not None:
        rec.update(torch_ms=other * 1e3, torch_over_jtus=other / seconds)
    if is_dlctus(name):
        net_in, _, _ = dlctus.prepare(state[0], frame, model.config)
        net = jax.jit(lambda p, x: dlctus.network(p, x, model.config))
        ns = timeit(lambda: net(params, net_in).block_until_ready(), repeats)
        rec.update(network_ms=ns * 1e3, network_gflops=c.network_flops / ns / 1e9)
    return rec


def train_workload(factor, crop, batch, seq, loss_frames, remat=False, unroll=1,
                   conv_backward="custom", warp="bicubic", hoist=False):
    """One DLCTUS BPTT training step (L1 loss, Adam) on random data.
    Returns ``(run, hlo, model)``: ``run()`` takes one step and blocks; ``hlo()`` is
    the compiled module's text (for profiles)."""
    import optax

    from jtus import losses, rollout, train
    from jtus.models import dlctus

    model = dlctus.make(dlctus.Config(factor=factor, conv_backward=conv_backward, warp=warp))
    opt = optax.adam(1e-4)
    ts = [train.create_train_state(model.init(jax.random.PRNGKey(0)), opt)]
    step = train.make_train_step(model, losses.make("l1", factor), opt, loss_frames=loss_frames,
                                 remat=remat, unroll=unroll, hoist=hoist)
    h = crop // factor
    frames = [random_frame(h, h, batch, seed=t) for t in range(seq)]
    frames = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *frames)
    frames = frames._replace(reset=jnp.zeros((seq, batch), bool).at[0].set(True))
    targets = jnp.asarray(np.random.default_rng(9).uniform(size=(seq, batch, crop, crop, 3)),
                          jnp.float32)

    def carry():
        return rollout.start(rollout.first_state(model, frames), targets[0])

    def run():
        ts[0], _, stats = step(ts[0], carry(), frames, targets)
        stats["loss"].block_until_ready()

    def compiled():
        return step.lower(ts[0], carry(), frames, targets).compile()

    def hlo():
        return compiled().as_text()

    run.compiled = compiled  # for the memory the compiled step needs (bench_train)
    return run, hlo, model


def bench_train(factor, crop, batch, seq, loss_frames, repeats, remat=False, unroll=1,
                conv_backward="custom", warp="bicubic", against=None, hoist=False):
    """The training-step timing record; ``against`` as in ``bench_infer``."""
    from jtus import cost

    run, _, model = train_workload(factor, crop, batch, seq, loss_frames, remat, unroll,
                                   conv_backward, warp, hoist)
    # a training step runs the network forward and, for the frames that reach the loss,
    # its two backward products (input and kernel gradients), each as costly as the
    # forward: at least 3x the forward FLOPs of every frame (BPTT reaches all of them)
    fwd = cost.cost("dlctus", model.config, crop, crop).flops * batch * seq
    rec = {"factor": factor, "crop": crop, "batch": batch, "seq": seq, "loss_frames": loss_frames,
           "gflop_per_step": 3 * fwd / 1e9,
           "remat": remat, "unroll": bool(unroll is True), "conv_backward": conv_backward,
           "warp": warp, "hoist": hoist}
    try:  # what XLA plans for the step: temporaries plus arguments and outputs
        mem = run.compiled().memory_analysis()
        rec["peak_mib"] = (mem.temp_size_in_bytes + mem.argument_size_in_bytes
                           + mem.output_size_in_bytes) / 2 ** 20
    except Exception:  # not every backend reports it
        pass
    frames = batch * seq
    if against is None:
        seconds = timeit(run, repeats)
        return dict(rec, s_per_step=seconds, frames_per_s=frames / seconds)
    seconds, other = timeit_pair(run, against, repeats)
    return dict(rec, s_per_step=seconds, torch_s_per_step=other, torch_over_jtus=other / seconds,
                frames_per_s=frames / seconds, torch_frames_per_s=frames / other)


# the PyTorch DLCTUS of the test suite, loaded by path (a test file, not part of the
# package): the bench compares against it only from a source checkout
TORCH_REFERENCE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                               "tests", "torch_dlctus.py")


def _torch():
    import importlib.util

    try:
        import torch
    except ImportError:
        return None, None
    if not os.path.exists(TORCH_REFERENCE):
        print(f"warning: no PyTorch reference at {TORCH_REFERENCE} (a source checkout has "
              f"it); timing jtus alone", file=sys.stderr)
        return None, None
    spec = importlib.util.spec_from_file_location("jtus_bench_torch_dlctus", TORCH_REFERENCE)
    ref = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(ref)
    # as many threads as cores this process may run on (taskset), as XLA:CPU does
    torch.set_num_threads(len(os.sched_getaffinity(0)))
    return torch, ref


def torch_infer(factor, size):
    """The PyTorch reference's inference step as a blocking callable (None without
    torch)."""
    torch, ref = _torch()
    if torch is None:
        return None
    H, W = size
    h, w = H // factor, W // factor
    r = np.random.default_rng(0)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
    color = t(r.uniform(size=(1, 3, h, w)))
    depth = t(r.uniform(0.5, 1.0, size=(1, 1, h, w)))
    motion = t(r.normal(scale=0.5, size=(1, 2, h, w)))
    jitter = t(r.uniform(size=(1, 2)))
    net = ref.Net().to(memory_format=torch.channels_last)
    hist = [ref.init_history(color, jitter, factor)]

    def run():
        with torch.no_grad():
            _, hist[0] = ref.step(net, hist[0], color, depth, motion, jitter, factor)

    return run


def torch_train(factor, crop, batch, seq, loss_frames):
    """The PyTorch reference's training step as a callable (None without torch)."""
    torch, ref = _torch()
    if torch is None:
        return None
    h = crop // factor
    r = np.random.default_rng(0)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
    xs = [(t(r.uniform(size=(batch, 3, h, h))), t(r.uniform(0.5, 1, size=(batch, 1, h, h))),
           t(r.normal(scale=0.5, size=(batch, 2, h, h))), t(r.uniform(size=(batch, 2))))
          for _ in range(seq)]
    targets = [t(r.uniform(size=(batch, 3, crop, crop))) for _ in range(seq)]
    net = ref.Net()
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)

    def run():
        opt.zero_grad()
        hist = ref.init_history(xs[0][0], xs[0][3], factor)
        loss = 0
        for i, (c, d, m, j) in enumerate(xs):
            out, hist = ref.step(net, hist, c, d, m, j, factor)
            if i >= seq - loss_frames:
                loss = loss + (out - targets[i]).abs().mean()
        (loss / loss_frames).backward()
        opt.step()

    return run


def run(args):
    report = {"hardware": hardware(), "command": "python -m jtus.bench " + " ".join(args.argv)}
    if "peak" in args.what:
        report["peak"] = peaks(args.repeats)
    if "infer" in args.what:
        rows = []
        for name in args.models:
            for size in args.sizes:
                for f in args.factors:
                    variants = ([(dt, fm) for dt in args.dtypes for fm in args.formulations]
                                if is_dlctus(name) else [("float32", None)])
                    for dt, fm in variants:
                        over = {"formulation": fm} if fm else {}
                        against = None
                        if (is_dlctus(name) and dt == "float32" and fm == args.formulations[0]
                                and args.torch):
                            against = torch_infer(f, SIZES[size])
                        rec = bench_infer(name, f, SIZES[size], args.repeats, dt, against=against,
                                          **over)
                        rows.append(rec)
                        _progress(rec)
        report["infer"] = rows
    if "train" in args.what:
        rows = []
        against = (torch_train(args.factors[0], args.train_crop, args.train_batch,
                               args.train_seq, args.train_loss_frames) if args.torch else None)
        for warp in args.train_warps:
            rec = bench_train(args.factors[0], args.train_crop, args.train_batch, args.train_seq,
                              args.train_loss_frames, args.repeats, remat=args.train_remat,
                              unroll=True if args.train_unroll else 1,
                              conv_backward=args.train_conv_backward, warp=warp,
                              against=against, hoist=args.train_hoist)
            _progress(rec)
            rows.append(rec)
        rec = rows[0]
        peak = report.get("peak", {}).get("conv_dlctus_gflops")
        if peak:
            for r in rows:
                r["bound_s_at_conv_peak"] = r["gflop_per_step"] / peak
        report["train"] = rec
        if len(rows) > 1:
            report["train_warps"] = rows
    return report


def _progress(rec):
    print("  " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                           for k, v in rec.items()), file=sys.stderr)


def markdown(report):
    hw = report["hardware"]
    lines = [f"Hardware: {hw['cpu']}, {hw['cores']} cores, JAX {hw['jax']} on {hw['backend']}.",
             f"Command: `{report['command']}`", ""]
    if "peak" in report:
        p = report["peak"]
        lines += [f"Peak (same run): matmul 2048^3 {p['matmul_gflops']:.1f} GFLOP/s; "
                  f"3x3 conv 32->32 at 270x480 {p['conv_dlctus_gflops']:.1f} GFLOP/s; "
                  f"3x3 conv 64->64 at 256x256 {p['conv_64_gflops']:.1f} GFLOP/s.", ""]
    if "infer" in report:
        lines += ["| model | size | factor | dtype | formulation | ms/frame | GFLOP/frame | "
                  "GFLOP/s | network ms | network GFLOP/s | % of conv peak | torch ms | "
                  "torch/jtus |",
                  "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
        conv_peak = report.get("peak", {}).get("conv_dlctus_gflops")
        for r in report["infer"]:
            pct = (f"{100 * r['network_gflops'] / conv_peak:.0f}%"
                   if conv_peak and "network_gflops" in r else "")
            lines.append(
                f"| {r['model']} | {r['size']} | {r['factor']}x | {r['dtype']} | "
                f"{r.get('formulation', '')} | {r['ms']:.1f} | "
                f"{r['gflop']:.2f} | {r['gflops']:.1f} | {r.get('network_ms', float('nan')):.1f} | "
                f"{r.get('network_gflops', float('nan')):.1f} | {pct} | "
                f"{r.get('torch_ms', float('nan')):.1f} | "
                f"{r.get('torch_over_jtus', float('nan')):.2f} |")
        lines.append("")
    if "train" in report:
        r = report["train"]
        scan = "unrolled" if r["unroll"] else "rolled"
        lines += [f"Training step (DLCTUS {r['factor']}x, crop {r['crop']}, batch {r['batch']}, "
                  f"sequence {r['seq']}, loss on the last {r['loss_frames']}, Adam; {scan} scan, "
                  f"{r['conv_backward']} conv backward{', remat' if r['remat'] else ''}"
                  f"{', preparation hoisted' if r.get('hoist') else ''}): "
                  f"jtus {r['s_per_step']:.3f} s, "
                  f"PyTorch {r.get('torch_s_per_step', float('nan')):.3f} s, "
                  f"torch/jtus {r.get('torch_over_jtus', float('nan')):.2f}.",
                  "", f"Training throughput: jtus {r['frames_per_s']:.1f} frames/s, PyTorch "
                  f"{r.get('torch_frames_per_s', float('nan')):.1f} frames/s (batch x sequence "
                  f"per step); compiled step memory {r.get('peak_mib', float('nan')):.0f} MiB "
                  f"(XLA's plan: temporaries, arguments, outputs)."]
        if "bound_s_at_conv_peak" in r:
            torch_over_bound = r.get("torch_s_per_step", float("nan")) / r["bound_s_at_conv_peak"]
            lines += ["", f"At least {r['gflop_per_step']:.1f} GFLOP per step (3x the forward "
                          f"FLOPs of {r['batch']} x {r['seq']} frames): "
                          f"{r['bound_s_at_conv_peak']:.3f} s at the measured convolution peak, "
                          f"so no implementation on this machine's convolutions beats that; "
                          f"PyTorch's step is "
                          f"{torch_over_bound:.2f}x "
                          f"that bound and jtus's "
                          f"{r['s_per_step'] / r['bound_s_at_conv_peak']:.2f}x."]
    if "train_warps" in report:
        lines += ["", "| reprojection warp | jtus s/step | PyTorch s/step (timed alongside) | "
                      "torch/jtus |", "| --- | --- | --- | --- |"]
        lines += [f"| {r['warp']} | {r['s_per_step']:.3f} | "
                  f"{r.get('torch_s_per_step', float('nan')):.3f} | "
                  f"{r.get('torch_over_jtus', float('nan')):.2f} |" for r in report["train_warps"]]
    return "\n".join(lines)


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(prog="python -m jtus.bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--what", nargs="+", choices=("peak", "infer", "train"),
                   default=["peak", "infer", "train"])
    p.add_argument("--models", nargs="+", default=["dlctus"])
    p.add_argument("--sizes", nargs="+", choices=tuple(SIZES), default=["720p", "1080p"])
    p.add_argument("--factors", nargs="+", type=int, default=[2, 4])
    p.add_argument("--dtypes", nargs="+", default=["float32"],
                   choices=("float32", "bfloat16", "float16"))
    p.add_argument("--formulations", nargs="+", default=["opt2"],
                   choices=("standard", "opt1", "opt2"), help="DLCTUS formulations to time")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--train-crop", type=int, default=128)
    p.add_argument("--train-batch", type=int, default=4)
    p.add_argument("--train-seq", type=int, default=8)
    p.add_argument("--train-loss-frames", type=int, default=5)
    p.add_argument("--train-unroll", action="store_true", help="unroll the scan fully")
    p.add_argument("--train-warps", nargs="+", default=["bicubic"], choices=sampling.METHODS,
                   help="DLCTUS reprojection warps to time the training step with (the "
                        "first is the headline figure; PyTorch's reference uses bicubic)")
    p.add_argument("--train-remat", action="store_true")
    p.add_argument("--train-hoist", action="store_true",
                   help="compute the carry-independent part of each frame before the scan "
                        "(Model.prepare; measured no faster on XLA:CPU)")
    p.add_argument("--train-conv-backward", choices=("custom", "autodiff"), default="custom")
    p.add_argument("--torch", action=argparse.BooleanOptionalAction, default=True,
                   help="also time the PyTorch reference")
    p.add_argument("--json", action="store_true")
    p.add_argument("--out", help="write the JSON report here (and its tables beside it, "
                                 "as a .md of the same name)")
    p.add_argument("--train-preset", metavar="NAME",
                   help="time the training step of a jtus.train preset (e.g. diverse, the "
                        "shipped weights' recipe): its crop, batch, window and loss frames "
                        "replace the --train-* values")
    args = p.parse_args(argv)
    args.argv = argv
    if args.out:
        try:
            files.check_out_file(args.out)
        except ValueError as e:
            p.error(str(e))
    if args.train_preset:
        from jtus import config as run_config, recipe
        if args.train_preset not in run_config.PRESETS:
            p.error(f"--train-preset: expected one of {sorted(run_config.PRESETS)}, "
                    f"got {args.train_preset!r}")
        cfg = run_config.PRESETS[args.train_preset]
        plan = recipe.plan(cfg)
        args.train_crop, args.train_batch = cfg.crop, cfg.batch
        args.train_seq, args.train_loss_frames = plan.window, plan.loss_frames
    report = run(args)
    text = markdown(report)
    if args.out:  # the JSON report, and its table beside it as Markdown
        with files.atomic_path(args.out) as tmp, open(tmp, "w") as fh:
            json.dump(report, fh, indent=1)
        with files.atomic_path(os.path.splitext(args.out)[0] + ".md") as tmp, \
                open(tmp, "w") as fh:
            fh.write(text + "\n")
    print(json.dumps(report, indent=1) if args.json else text)
    return 0


if __name__ == "__main__":
    from jtus import cli  # not ``from jtus.cli import run``: a module may have its own run
    cli.run(main)
