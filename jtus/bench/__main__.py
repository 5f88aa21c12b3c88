"""``python -m jtus.bench``: ms per frame and training frames per second of every
model, beside its PyTorch reference where it has one and against the machine's peak,
all measured in one run.

    python -m jtus.bench                                   # every model, 720p and 1080p
    python -m jtus.bench --models dlctus jau tus --sizes 720p --factors 4 --json
    python -m jtus.bench --what train --train-models dlctus --train-preset diverse
    python -m jtus.bench --out docs/results/bench-2core/bench.json   # and bench.md

Inference times each model at each size and factor (DLCTUS also in each of
``--dtypes`` and ``--formulations``, and its network alone); training times one BPTT
step of each of ``--train-models`` (its own loss, Adam) on random crops. The
references (``jtus.reference``, needing ``torch``) run the same workloads alternately
with jtus's; ratios are torch time / jtus time.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from jtus import cli, files, hostmem, models, recipe, sampling, sharding, train
from jtus import config as run_config
from jtus.bench.report import markdown
from jtus.bench.workloads import SIZES, bench_infer, bench_train, peaks
from jtus.models import dlctus, layers
from jtus.timing import hardware


def _infer_rows(args, rows, saved):
    for name in args.models:
        spec = models.spec(name)
        dtypes = [d for d in args.dtypes if d in spec.dtypes] or ["float32"]
        forms = [f for f in args.formulations if f in spec.formulations] or [None]
        kerns = [k for k in args.kernels if k in spec.kernels] or [None]
        variants = [(dt, fm, k) for dt in dtypes for fm in forms for k in kerns]
        for size in args.sizes:
            for f in args.factors:
                for dt, fm, k in variants:
                    over = dict({"formulation": fm} if fm else {}, **({"kernels": k} if k else {}))
                    # the reference alongside once per model, size and factor
                    ref = args.torch and (dt, fm, k) == variants[0]
                    rec = bench_infer(name, f, SIZES[size], args.repeats, dt, reference=ref,
                                      **over)
                    rows.append(rec)
                    saved()
                    _progress(rec)


def _train_rows(args, peak, rows, saved):
    for name in args.train_models:
        fields = models.spec(name).config(4).__dataclass_fields__
        warps = args.train_warps if "warp" in fields else args.train_warps[:1]
        kerns = [k for k in args.train_kernels if k in models.spec(name).kernels] or ["auto"]
        convs = args.train_conv_backward if "conv_backward" in fields \
            else args.train_conv_backward[:1]
        for warp, k, cb in [(w, k, c) for w in warps for k in kerns for c in convs]:
            rec = bench_train(args.factors[0], args.train_crop, args.train_batch,
                              args.train_seq, args.train_loss_frames, args.repeats,
                              remat=run_config.REMAT_CHOICES[args.train_remat],
                              unroll=True if args.train_unroll else 1,
                              conv_backward=cb, warp=warp,
                              reference=args.torch and k == kerns[0], hoist=args.train_hoist,
                              name=name, kernels=k)
            if peak:
                rec["bound_s_at_conv_peak"] = rec["gflop_per_step"] / peak
            _progress(rec)
            rows.append(rec)
            saved()


def run(args, save=lambda report: None):
    """The report; ``save(report)`` is called after each measurement with what has been
    measured so far (an interrupted run keeps its rows)."""
    report = {"hardware": hardware(), "command": "python -m jtus.bench " + " ".join(args.argv),
              "host_memory": hostmem.state()}
    saved = lambda: save(report)  # noqa: E731
    if "peak" in args.what:
        report["peak"] = peaks(args.repeats)
        saved()
    if "infer" in args.what:
        _infer_rows(args, report.setdefault("infer", []), saved)
    if "train" in args.what:
        _train_rows(args, report.get("peak", {}).get("conv_dlctus_gflops"),
                    report.setdefault("train", []), saved)
    return report


def _write(report, out):
    """The JSON report at ``out``, and its table beside it as Markdown, each atomically."""
    with files.atomic_path(out) as tmp, open(tmp, "w") as fh:
        json.dump(report, fh, indent=1)
    with files.atomic_path(os.path.splitext(out)[0] + ".md") as tmp, open(tmp, "w") as fh:
        fh.write(markdown(report) + "\n")


def _progress(rec):
    print("  " + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}"
                           for k, v in rec.items()), file=sys.stderr)


def _parser():
    p = argparse.ArgumentParser(prog="python -m jtus.bench", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--what", nargs="+", choices=("peak", "infer", "train"),
                   default=["peak", "infer", "train"])
    p.add_argument("--models", nargs="+", choices=models.NAMES, default=list(models.NAMES))
    p.add_argument("--sizes", nargs="+", choices=tuple(SIZES), default=["720p", "1080p"])
    p.add_argument("--factors", nargs="+", type=int, default=[2, 4], choices=(2, 4))
    p.add_argument("--dtypes", nargs="+", default=["float32"],
                   choices=("float32", "bfloat16", "float16"),
                   help="compute dtypes, for the models that take them")
    p.add_argument("--formulations", nargs="+", default=["opt2"],
                   choices=("standard", "opt1", "opt2"),
                   help="equivalent formulations, for the models that have them")
    p.add_argument("--kernels", nargs="+", default=["auto"], choices=dlctus.KERNELS,
                   help="trunk implementations, for the models that have them (im2col: "
                        "matmuls; pallas: Triton kernels, interpret mode on a CPU, so time "
                        "them on a GPU)")
    p.add_argument("--repeats", type=int, default=5)
    t = p.add_argument_group("training step (the first --factors)")
    t.add_argument("--train-models", nargs="+", choices=models.TRAINABLE,
                   default=list(models.TRAINABLE))
    t.add_argument("--train-crop", type=int, default=128)
    t.add_argument("--train-batch", type=int, default=4)
    t.add_argument("--train-seq", type=int, default=8)
    t.add_argument("--train-loss-frames", type=int, default=5)
    t.add_argument("--train-unroll", action="store_true", help="unroll the scan fully")
    t.add_argument("--train-warps", nargs="+", default=["bicubic"], choices=sampling.METHODS,
                   help="reprojection warps to time the training step with, for models that "
                        "take one (PyTorch's DLCTUS reference uses bicubic)")
    t.add_argument("--train-remat", choices=tuple(run_config.REMAT_CHOICES), default="none")
    t.add_argument("--train-hoist", action="store_true",
                   help="compute the carry-independent part of each frame before the scan "
                        "(Config.hoist)")
    t.add_argument("--train-kernels", nargs="+", default=["auto"], choices=dlctus.KERNELS,
                   help="trunk implementations to time the training step with")
    t.add_argument("--train-conv-backward", nargs="+", choices=layers.CONV_BACKWARDS,
                   default=["auto"],
                   help="how the convolutions of the models that take it are differentiated "
                        "(Config.conv_backward); each is timed beside PyTorch")
    t.add_argument("--train-preset", metavar="NAME", choices=tuple(run_config.PRESETS),
                   help="time the training step of a jtus.train preset (e.g. diverse, the "
                        "shipped weights' recipe): its crop, batch, window and loss frames "
                        "replace the --train-* values")
    t.add_argument("--host-devices", type=int, default=None, metavar="N",
                   help="XLA CPU devices the training step splits its batch over, as "
                        "python -m jtus.train does (default: from crop 128 on, one per "
                        "core, as many as divide the batch; 1: one device). Inference "
                        "runs on one")
    p.add_argument("--torch", action=argparse.BooleanOptionalAction, default=True,
                   help="also time the PyTorch references")
    p.add_argument("--json", action="store_true")
    p.add_argument("--out", help="write the JSON report here (and its tables beside it, "
                                 "as a .md of the same name)")
    return p


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    p = _parser()
    args = p.parse_args(argv)
    args.argv = argv
    if args.out:
        try:
            files.check_out_file(args.out)
        except ValueError as e:
            p.error(str(e))
    for name in ("repeats", "train_crop", "train_batch", "train_seq", "train_loss_frames"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')}: expected a positive integer, "
                    f"got {getattr(args, name)}")
    if args.train_crop % 4 or any(args.train_crop % f for f in args.factors[:1]):
        p.error(f"--train-crop: expected a multiple of 4 and of the factor, got {args.train_crop}")
    if args.train_loss_frames > args.train_seq:
        p.error(f"--train-loss-frames: {args.train_loss_frames} exceeds --train-seq "
                f"{args.train_seq}")
    if args.train_preset:
        cfg = run_config.PRESETS[args.train_preset]
        plan = recipe.plan(cfg)
        args.train_crop, args.train_batch = cfg.crop, cfg.batch
        args.train_seq, args.train_loss_frames = plan.window, plan.loss_frames
    if args.host_devices is not None and args.host_devices < 1:
        p.error(f"--host-devices: expected a positive count, got {args.host_devices}")
    if "train" in args.what:
        sharding.use_host_devices(train.host_devices_for(args.train_crop, args.host_devices),
                                  args.train_batch)
    report = run(args, (lambda r: _write(r, args.out)) if args.out else (lambda r: None))
    print(json.dumps(report, indent=1) if args.json else markdown(report))
    return 0


if __name__ == "__main__":
    cli.run(main)
