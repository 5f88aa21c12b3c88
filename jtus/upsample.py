"""``python -m jtus.upsample``: run a model over an input sequence and write the frames.

    python -m jtus.upsample --input data/default.h5 --video objects_00 --factor 4 \\
        --model shipped --out out/objects --format png --mp4 out/objects.mp4
    python -m jtus.upsample --input renders/lr --exr-spec renders/spec.json --factor 4 \\
        --model tus --out out/mine --format exr

``--input`` is a jtus HDF5 dataset (with ``--split``/``--video``) or a folder of LR
EXR frames (read with an ``ImportSpec`` sidecar; no target needed). ``--model`` takes
the specs of ``python -m jtus.evaluate``. ``--mp4`` writes input (nearest-enlarged) |
output side by side, which needs the ``video`` extra (``pip install -e ".[video]"``).
"""

from __future__ import annotations

import argparse
import os
import sys
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from jtus import cli, loading, rollout
from jtus.files import atomic_path, check_out_file
from jtus.data import exr
from jtus.data.dataset import Dataset
from jtus.data.exr import linear_to_srgb
from jtus.frame import Frame, validate
from jtus.sampling import display


def _load_input(args):
    if os.path.isdir(args.input):

        spec = exr.ImportSpec.from_json(args.exr_spec) if args.exr_spec else exr.ImportSpec()
        video = exr.load_sequence(args.input, None, args.factor, spec)
        x = video[f"x{args.factor}"]
        e = video.get("exposure")
        return Frame(x["color"][:, None], x["depth"][:, None], x["motion"][:, None],
                     x["jitter"][:, None], video["reset"][:, None],
                     None if e is None else e[:, None])

    with Dataset(args.input) as ds:
        names = ds.videos(args.split)
        if not args.video and not names:
            raise ValueError(f"--split: no videos in split {args.split!r} of {args.input}")
        frames, _ = ds.video(args.split, args.video or names[0], args.factor)
    return frames


def upsample(entry, frames):
    """Outputs ``[T,H,W,3]`` of a model entry over a time-major ``Frame`` with B=1."""

    validate(frames, time_major=True)
    fj = jax.tree_util.tree_map(jnp.asarray, frames)
    return np.asarray(rollout.video(entry.model, entry.params, fj, check=False))[:, 0]


def check_mp4(path, force=False):
    """Refuse, before any work, an ``--mp4`` path that cannot take the video."""
    if not path.lower().endswith(".mp4"):
        raise ValueError(f"--mp4: expected a path ending in .mp4, got {path}")
    check_out_file(path, force, field="--mp4", kind="an .mp4 file")


def write_mp4(path, frames_lr, outputs, factor, fps=30):
    """Input (nearest-enlarged) | output side by side, display-referred ``[T,H,W,3]``
    in [0,1], as H.264; written beside ``path`` and renamed onto it once ffmpeg has
    finished, so a failure leaves no file."""
    try:
        import imageio.v2 as imageio  # lazy: optional (the video extra), only for --mp4
        import imageio_ffmpeg  # noqa: F401  lazy: optional, imageio's ffmpeg writer
    except ImportError as e:
        raise ValueError("--mp4 needs the video extra: pip install -e \".[video]\"") from e

    lr = np.repeat(np.repeat(frames_lr, factor, 1), factor, 2)
    both = np.concatenate([lr, outputs], 2)
    both = both[:, : both.shape[1] // 2 * 2, : both.shape[2] // 2 * 2]
    try:
        with atomic_path(path, suffix=".tmp.mp4") as tmp, warnings.catch_warnings():
            # ffmpeg runs in a subprocess; JAX warns on every fork of a threaded process,
            # which is harmless here (the child only execs ffmpeg)
            warnings.filterwarnings("ignore", message="os.fork", category=RuntimeWarning)
            with imageio.get_writer(tmp, fps=fps, codec="libx264", quality=8,
                                    macro_block_size=1, format="FFMPEG") as w:
                for img in both:
                    w.append_data(np.round(linear_to_srgb(img) * 255).astype(np.uint8))
            if os.path.getsize(tmp) == 0:
                raise ValueError(f"--mp4: ffmpeg wrote nothing to {path}")
    except (OSError, RuntimeError) as e:
        raise ValueError(f"--mp4: writing {path} failed: {e}") from e


def shown_frames(outs, lr, exposure):
    """What 8-bit images and the MP4 show: the outputs and inputs ``[T,H,W,3]`` as they
    are (LDR), or HDR's tone-mapped pre-exposed colour for ``exposure [T]``
    (docs/conventions.md); EXR frames keep the radiance."""
    if exposure is None:
        return outs, lr
    e = jnp.asarray(exposure).reshape(-1)
    return tuple(np.asarray(display(jnp.asarray(x), e)) for x in (outs, lr))


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m jtus.upsample", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--input", required=True, help="HDF5 dataset or folder of LR EXR frames")
    p.add_argument("--split", default="test")
    p.add_argument("--video", help="video name in the dataset (default: the first)")
    p.add_argument("--exr-spec", help="ImportSpec JSON for an EXR folder")
    p.add_argument("--factor", type=int, required=True)
    p.add_argument("--model", default="shipped",
                   help="a model spec of python -m jtus.evaluate; default: %(default)s")
    p.add_argument("--out", required=True)
    p.add_argument("--force", action="store_true",
                   help="replace the frames of an earlier run in --out")
    p.add_argument("--format", choices=exr.IMAGE_FORMATS, default="png")
    p.add_argument("--mp4", help="also write input | output side by side to this MP4")
    args = p.parse_args(argv)
    cli.sigterm_as_exit()
    try:
        exr.check_sequence_folder(args.out, args.force)
        if args.mp4:
            check_mp4(args.mp4, args.force)
        entry = loading.load(args.model, args.factor)
        if entry is None:
            raise ValueError(f"model {args.model!r} is not available at {args.factor}x")
        frames = _load_input(args)
        outs = upsample(entry, frames)
        e = None if frames.exposure is None else np.asarray(frames.exposure)[:, 0]
        shown, lr = shown_frames(outs, np.asarray(frames.color)[:, 0], e)
        if args.mp4:  # first: a failed video leaves the earlier frames as they were
            write_mp4(args.mp4, lr, shown, args.factor)
        paths = exr.write_sequence(outs if args.format == "exr" else shown, args.out,
                                   args.format)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {len(paths)} {args.format} frames to {args.out}"
          + (f" and {args.mp4}" if args.mp4 else ""))
    return 0


if __name__ == "__main__":
    cli.run(main)
