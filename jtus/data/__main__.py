"""``python -m jtus.data``: generate datasets, import EXR sequences, export videos.

    python -m jtus.data generate --preset default --out data/default.h5
    python -m jtus.data generate --preset game --targets adaptive --out data/game-a.h5
    python -m jtus.data import-exr --input renders/lr --target renders/hr --factor 4 \\
        --sidecar renders/spec.json --out data/mine.h5
    python -m jtus.data import-nss --root captures/nss --factor 2 --out data/nss-x2.h5
    python -m jtus.data export --dataset data/default.h5 --split test --video objects_00 \\
        --what target --format png --out out/objects
    python -m jtus.data info data/default.h5
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import sys

from jtus import cli
from jtus.data import dataset, exr, nss
from jtus.files import check_budget, check_out_file
from jtus.sim import generate
from jtus.sim.video import TARGETS


def _generate_args(g):
    """``generate``'s options."""
    g.add_argument("--preset", choices=generate.PRESET_NAMES, default="default")
    g.add_argument("--out", required=True)
    g.add_argument("--quiet", action="store_true")
    g.add_argument("--targets", choices=TARGETS,
                   help="target supersampling (default: the preset's, uniform for every "
                        "built-in one; adaptive: docs/simulator.md)")
    g.add_argument("--workers", type=int, default=generate.default_workers(),
                   help="rendering processes, one per core (default: every core this "
                        "process may use)")
    g.add_argument("--force", action="store_true",
                   help="go on past the memory or disk budget (an existing --out is "
                        "always replaced, once the new file is complete)")


def _parser():
    p = argparse.ArgumentParser(prog="python -m jtus.data", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="render a preset into an HDF5 file (atomically)")
    _generate_args(g)
    i = sub.add_parser("import-exr", help="an EXR sequence into the HDF5 layout")
    i.add_argument("--input", required=True, help="folder of LR per-frame EXRs")
    i.add_argument("--target", required=True, help="folder of HR per-frame EXRs")
    i.add_argument("--factor", type=int, required=True)
    i.add_argument("--out", required=True)
    i.add_argument("--sidecar", help="JSON with ImportSpec keys (flags below override it)")
    i.add_argument("--split", default="test", choices=dataset.SPLITS)
    i.add_argument("--name", default="video_00")
    i.add_argument("--force", action="store_true",
                   help="replace an existing --out; go on past the memory or disk budget")
    i.add_argument("--color", help="comma-separated channel names, e.g. R,G,B")
    i.add_argument("--depth", help="depth channel name")
    i.add_argument("--motion", help="comma-separated motion channel names (x,y)")
    i.add_argument("--motion-units", choices=("pixels", "uv", "ndc"))
    i.add_argument("--motion-y-up", action="store_true", default=None)
    i.add_argument("--motion-negate", action="store_true", default=None)
    i.add_argument("--depth-kind", choices=("device", "reversed", "linear", "view"))
    i.add_argument("--near", type=float)
    i.add_argument("--far", type=float)
    s = sub.add_parser("import-nss", help="Arm's NSS dataset layout into the HDF5 layout")
    s.add_argument("--root", required=True, help="the NSS dataset folder (0000.json, ...)")
    s.add_argument("--factor", type=int, required=True, help="the x<ratio> folder to read")
    s.add_argument("--out", required=True)
    s.add_argument("--split", default="test", choices=dataset.SPLITS)
    s.add_argument("--sequences", help="comma-separated sequence names (default: all)")
    s.add_argument("--linear-truth", action="store_true",
                   help="the ground truth EXRs are linear (Arm's --linear_truth); by "
                        "default they are Karis tone-mapped and brought back to linear")
    s.add_argument("--force", action="store_true",
                   help="replace an existing --out; go on past the memory or disk budget")
    s.add_argument("--quiet", action="store_true")
    e = sub.add_parser("export", help="write a dataset video as EXR or PNG frames")
    e.add_argument("--dataset", required=True)
    e.add_argument("--split", default="test")
    e.add_argument("--video", required=True)
    e.add_argument("--what", default="target", help="target, or color@FACTOR")
    e.add_argument("--format", choices=exr.IMAGE_FORMATS, default="png")
    e.add_argument("--out", required=True)
    e.add_argument("--force", action="store_true",
                   help="replace the frames of an earlier export in --out")
    n = sub.add_parser("info", help="summarize a dataset")
    n.add_argument("path", nargs="?", help="the dataset (or give --dataset)")
    n.add_argument("--dataset")
    return p


def _import(args):
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", args.name) or set(args.name) == {"."}:
        raise ValueError(f"--name: expected letters, digits, '_', '-' or '.', got "
                         f"{args.name!r}")
    check_out_file(args.out, args.force, kind="an .h5 file")
    spec = exr.ImportSpec.from_json(args.sidecar) if args.sidecar else exr.ImportSpec()
    over = {"color": tuple(args.color.split(",")) if args.color else None,
            "depth": args.depth, "motion": tuple(args.motion.split(",")) if args.motion else None,
            "motion_units": args.motion_units, "motion_y_up": args.motion_y_up,
            "motion_negate": args.motion_negate, "depth_kind": args.depth_kind,
            "near": args.near, "far": args.far}
    spec = dataclasses.replace(spec, **{k: v for k, v in over.items() if v is not None})
    check_budget(*exr.sequence_budget(args.input, args.target, args.factor), args.out,
                 args.force, what="import-exr")
    exr.import_exr(args.input, args.target, args.factor, args.out, spec, args.split, args.name)
    print(f"wrote {args.out}")


def _export(args):
    exr.check_sequence_folder(args.out, args.force)
    m = re.fullmatch(r"target|color@(\d+)", args.what)
    if not m:
        raise ValueError(f"--what: expected target or color@FACTOR, got {args.what!r}")
    with dataset.Dataset(args.dataset) as ds:
        g = ds.group(args.split, args.video)
        if args.what == "target":
            frames = g["target"][:]
        else:
            factor = int(m.group(1))
            if factor not in ds.factors:
                raise ValueError(f"--what: {args.dataset} holds factors {ds.factors}, got "
                                 f"{args.what!r}")
            frames = g[f"x{factor}/color"][:]
    paths = exr.write_sequence(frames.astype("float32"), args.out, args.format)
    print(f"wrote {len(paths)} frames to {args.out}")


def _info(args):
    if bool(args.path) == bool(args.dataset):
        raise ValueError("info: give the dataset once, as a path or as --dataset")
    args.dataset = args.dataset or args.path
    with dataset.Dataset(args.dataset) as ds:
        a = ds.file.attrs
        spp = ("adaptive targets (4, 16 or 64 spp)" if a.get("targets") == "adaptive"
               else f"spp {a['spp']}")
        print(f"{args.dataset}: {a['size'][0]}x{a['size'][1]}, factors {list(ds.factors)}, "
              f"{spp}, mip_bias {a['mip_bias']}")
        for split in dataset.SPLITS:
            vids = ds.videos(split)
            frames = sum(ds.file[f"{split}/{v}/target"].shape[0] for v in vids)
            print(f"  {split}: {len(vids)} videos, {frames} frames")


def main(argv=None):
    args = _parser().parse_args(argv)
    cli.sigterm_as_exit()
    try:
        if args.cmd == "generate":
            check_out_file(args.out, kind="an .h5 file")
            if args.workers < 1:
                raise ValueError(f"--workers: expected a positive integer, got {args.workers}")
            p = generate.preset(args.preset)
            if args.targets:
                p = dataclasses.replace(p, targets=args.targets)
            check_budget(*p.budget(args.workers), args.out,
                         args.force, what=f"generate --preset {args.preset}")
            generate.generate(p, args.out, progress=not args.quiet, workers=args.workers)
            print(f"wrote {args.out}")
        elif args.cmd == "import-exr":
            _import(args)
        elif args.cmd == "import-nss":
            if args.factor < 1:
                raise ValueError(f"--factor: expected a positive integer, got {args.factor}")
            check_out_file(args.out, args.force, kind="an .h5 file")
            names = args.sequences.split(",") if args.sequences else None
            check_budget(*nss.budget(args.root, args.factor, names), args.out, args.force,
                         what="import-nss")
            nss.import_nss(args.root, args.factor, args.out, args.split, names,
                           progress=not args.quiet,
                           truth="linear" if args.linear_truth else "karis")
            print(f"wrote {args.out}")
        elif args.cmd == "export":
            _export(args)
        else:
            _info(args)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    cli.run(main)
