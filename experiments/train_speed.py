"""Training-step variants of DLCTUS timed against each other and against PyTorch, in
one process, round-robin (a, b, c, ..., a, b, c, ...) so every variant sees the same
machine; the ratios are what to read (docs/results/cpu-speed/result.md, "Training speed").

Variants: the plain scan of ``step`` (the default), the same with the trunk's
convolutions differentiated by direct convolutions or by Winograd's F(4x4), whatever
the map size (``dlctus.Config.conv_backward="custom"`` and ``"winograd"``; the default
``"auto"`` picks by size), the same keeping the residuals of
the network's down-sampling and output construction per frame instead of recomputing
them (``dlctus.Config.remat_edges=False``), the carry-independent
preparation hoisted out of the scan (``Model.prepare``), the hoisted step under
``jax.checkpoint`` policies (``rollout.REMAT_POLICIES``, full remat), and the
hand-written reverse-time backward (``remat="reverse"``: the forward keeps each frame's
carry, the backward recomputes one step at a time under ``jax.vjp``). Then, for the
default variant, training frames per second over batch sizes and crops, and the
comparison systems' steps with and without the custom SAME-convolution backward.

    python experiments/train_speed.py                     # the bench's workload
    python experiments/train_speed.py --variants "plain scan" \
        "plain scan, direct convolutions" --shapes --comparison --repeats 15
    taskset -c 1 python experiments/train_speed.py --out docs/results/train-speed-1core

The step splits its batch over XLA CPU devices as ``python -m jtus.train`` does for the
crop (``--host-devices``); results recorded before that option existed ran on one device,
and ``--host-devices 1`` repeats them.

Writes ``result.json`` and ``result.md`` under ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys

import jax
import numpy as np

from jtus import bench, sharding, timing, train

VARIANTS = {  # name -> train_workload overrides
    "plain scan": {"hoist": False},
    "plain scan, direct convolutions": {"hoist": False, "conv_backward": "custom"},
    "plain scan, Winograd convolutions": {"hoist": False, "conv_backward": "winograd"},
    "plain scan, edges kept": {"hoist": False, "remat_edges": False},  # dlctus.Config
    "hoisted preparation": {"hoist": True},
    "hoisted + remat dots": {"hoist": True, "remat": "dots"},
    "hoisted + remat dots_no_batch": {"hoist": True, "remat": "dots_no_batch"},
    "hoisted + full remat": {"hoist": True, "remat": True},
    "full remat": {"hoist": False, "remat": True},
    "reverse-time backward": {"hoist": False, "remat": "reverse"},  # rollout._segment_reverse
}


def comparison_step(name, factor, crop, batch, seq, loss_frames, fast=True):
    """A blocking training step (its own paper's loss, Adam) of comparison system
    ``name`` on random data; ``fast=False`` builds it with the SAME convolutions'
    plain autodiff backward (``layers.conv`` in place of ``layers.conv_same_fast``:
    the same values, tested in float64) to show what the custom backward is worth."""
    import contextlib

    import jax
    import jax.numpy as jnp
    import optax

    from jtus import losses, models, rollout, train
    from jtus.models import layers

    patch = contextlib.nullcontext()
    if not fast:
        from unittest import mock
        patch = mock.patch.object(layers, "conv_same_fast", layers.conv)
    with patch:
        model = models.build(name, factor)
        opt = optax.adam(1e-4)
        ts = [train.create_train_state(model.init(jax.random.PRNGKey(0)), opt)]
        step = train.make_train_step(model, losses.make(models.spec(name).loss, factor), opt,
                                     loss_frames=loss_frames)
        h = crop // factor
        frames = [bench.random_frame(h, h, batch, seed=t) for t in range(seq)]
        frames = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *frames)
        frames = frames._replace(reset=jnp.zeros((seq, batch), bool).at[0].set(True))
        targets = jnp.asarray(np.random.default_rng(9).uniform(size=(seq, batch, crop, crop, 3)),
                              jnp.float32)
        carry = lambda: rollout.start(rollout.first_state(model, frames), targets[0])  # noqa

        def run():
            ts[0], _, stats = step(ts[0], carry(), frames, targets)
            stats["loss"].block_until_ready()

        run()  # compile inside the patch
    return run


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--factor", type=int, default=2)
    p.add_argument("--crop", type=int, default=128)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--seq", type=int, default=8)
    p.add_argument("--loss-frames", type=int, default=5)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    p.add_argument("--shapes", nargs="*", default=["2x64", "4x64", "8x64", "2x128", "4x128",
                                                   "8x128", "2x192", "4x192"],
                   help="BATCHxCROP for the throughput table (empty: none)")
    p.add_argument("--no-torch", action="store_true")
    p.add_argument("--comparison", nargs="*", default=["nsrr-fast", "kpn"],
                   help="comparison systems timed with and without the custom SAME-conv "
                        "backward (crop 64, batch 4, 8 frames, loss on all 8)")
    p.add_argument("--host-devices", type=int, default=None, metavar="N",
                   help="XLA CPU devices the step splits its batch over (default: as "
                        "python -m jtus.train chooses for --crop; 1: one device)")
    p.add_argument("--out", default="docs/results/train-speed")
    args = p.parse_args(argv)
    if args.host_devices is not None and args.host_devices < 1:
        p.error(f"--host-devices: expected a positive count, got {args.host_devices}")
    sharding.use_host_devices(train.host_devices_for(args.crop, args.host_devices), args.batch)
    w = (args.factor, args.crop, args.batch, args.seq, args.loss_frames)
    fns, mem = {}, {}
    for name in args.variants:
        run, _, _ = bench.train_workload(*w, **VARIANTS[name])
        fns[name] = run
        m = run.compiled().memory_analysis()
        mem[name] = (m.temp_size_in_bytes + m.argument_size_in_bytes
                     + m.output_size_in_bytes) / 2 ** 20
    if not args.no_torch:
        fns["PyTorch"] = bench.torch_reference("dlctus").train_workload(*w)
    print(f"timing {len(fns)} variants x {args.repeats}", file=sys.stderr)
    sec = timing.timeit_round_robin(fns, args.repeats)
    frames = args.batch * args.seq
    base = sec["plain scan"] if "plain scan" in sec else None
    rows = [{"variant": k, "s_per_step": v, "frames_per_s": frames / v,
             "peak_mib": mem.get(k), "plain_over_this": base / v if base else None,
             "torch_over_this": sec["PyTorch"] / v if "PyTorch" in sec else None}
            for k, v in sec.items()]
    shapes = []
    for spec in args.shapes:
        b, c = (int(x) for x in spec.split("x"))
        run, _, _ = bench.train_workload(args.factor, c, b, args.seq, args.loss_frames)
        s = timing.timeit(run, max(3, args.repeats // 2))
        shapes.append({"batch": b, "crop": c, "s_per_step": s, "frames_per_s": b * args.seq / s,
                       "mpix_per_s": b * args.seq * c * c / s / 1e6})
        print(f"  {spec}: {s:.3f} s/step", file=sys.stderr)
    comp = []
    for name in args.comparison:
        pair = {"custom": comparison_step(name, args.factor, 64, 4, 8, 8),
                "autodiff": comparison_step(name, args.factor, 64, 4, 8, 8, fast=False)}
        t = timing.timeit_round_robin(pair, max(3, args.repeats // 2))
        comp.append({"model": name, "custom_s": t["custom"], "autodiff_s": t["autodiff"]})
        print(f"  {name}: custom {t['custom']:.3f} s, autodiff {t['autodiff']:.3f} s",
              file=sys.stderr)
    report = {"hardware": timing.hardware(), "command": "python experiments/train_speed.py "
              + shlex.join(argv if argv is not None else sys.argv[1:]),
              "workload": dict(zip(("factor", "crop", "batch", "seq", "loss_frames"), w)),
              "rows": rows, "shapes": shapes, "comparison": comp}
    os.makedirs(args.out, exist_ok=True)
    with open(os.path.join(args.out, "result.json"), "w") as f:
        json.dump(report, f, indent=1)
    hw = report["hardware"]
    md = [f"Command: `{report['command']}`", "",
          f"Hardware: {hw.get('cpu', '?')}, {hw.get('cores', '?')} cores visible, "
          f"JAX {hw.get('jax', '?')} (affinity: {len(os.sched_getaffinity(0))} core(s)).", "",
          f"DLCTUS {args.factor}x training step, crop {args.crop}, batch {args.batch}, "
          f"{args.seq} frames, loss on the last {args.loss_frames}, L1, Adam; medians of "
          f"{args.repeats} round-robin repeats; {len(jax.devices())} XLA device(s).", "",
          "| variant | s/step | frames/s | compiled memory MiB | plain/this | torch/this |",
          "| --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        md.append(f"| {r['variant']} | {r['s_per_step']:.3f} | {r['frames_per_s']:.1f} | "
                  + (f"{r['peak_mib']:.0f}" if r["peak_mib"] else "-") + " | "
                  + (f"{r['plain_over_this']:.2f}" if r["plain_over_this"] else "-") + " | "
                  + (f"{r['torch_over_this']:.2f}" if r["torch_over_this"] else "-") + " |")
    if shapes:
        md += ["", "Default variant over batch and crop (same sequence; frames/s = batch x "
               "sequence per second, Mpix/s = HR pixels trained on per second):", "",
               "| batch | crop | s/step | frames/s | HR Mpix/s |",
               "| --- | --- | --- | --- | --- |"]
        md += [f"| {s['batch']} | {s['crop']} | {s['s_per_step']:.3f} | {s['frames_per_s']:.1f} "
               f"| {s['mpix_per_s']:.2f} |" for s in shapes]
    if comp:
        md += ["", f"Comparison systems' training steps ({args.factor}x, crop 64, batch 4, 8 "
               "frames, loss on all 8, their own losses, Adam), SAME convolutions with the "
               "custom backward (`layers.conv_same_fast`) against plain autodiff:", "",
               "| model | custom s/step | autodiff s/step | speed-up |",
               "| --- | --- | --- | --- |"]
        md += [f"| {c['model']} | {c['custom_s']:.3f} | {c['autodiff_s']:.3f} | "
               f"{c['autodiff_s'] / c['custom_s']:.2f}x |" for c in comp]
    with open(os.path.join(args.out, "result.md"), "w") as f:
        f.write("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
