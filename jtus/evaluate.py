"""Evaluation: ``python -m jtus.evaluate`` runs models over whole test videos.

    python -m jtus.evaluate --models jau tus shipped
    python -m jtus.evaluate --factor 4 --models jau tus trained=runs/default-x4/checkpoint.msgpack
    python -m jtus.evaluate --models tus thesis=thesis_dlctus_x4.pt --json
    python -m jtus.evaluate --models jau tus shipped 'nsrr=runs/nsrr-x{f}/checkpoint.msgpack'

Model specs: a built-in name (``jau``, ``jau-bicubic``, ``tus``, ``tus-clip``, ``tus-mean``),
``shipped`` (the weights under ``jtus/weights/`` for the factor), or ``LABEL=PATH``
for a checkpoint written by ``jtus.train`` (``.msgpack``) or a PyTorch DLCTUS
checkpoint (``.pt``); ``{f}`` in PATH becomes the factor being evaluated, so one spec
covers a model trained per factor. Every video starts from a fresh state.

As a library: ``evaluate.run(specs, dataset, factors, out)`` returns the summary
(``train`` calls it after training); ``video_metrics`` is the per-video measurement
training validates with. Models come from ``jtus.loading.load``.

Writes into ``--out``: ``results.md`` (per factor: PSNR / SSIM / temporal error per
method, thesis Table 2 layout), ``results.json``, ``per_frame_x{f}.png`` (PSNR and SSIM
per frame over the test videos, thesis Figures 8-13) and ``crops_x{f}.png`` (input,
each method, reference; thesis Table 3).
"""

from __future__ import annotations

import argparse
import fnmatch
import functools
import json
import os
import platform
import sys

import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.figure import Figure
from PIL import Image, ImageDraw
from tqdm import tqdm

from jtus import cli, loading, losses, metrics, models, rollout
from jtus.config import PRESETS
from jtus.data.dataset import Dataset
from jtus.data.exr import linear_to_srgb
from jtus.files import atomic_path, check_out_folder
from jtus.sim.generate import ensure_dataset


def frame_metrics(factor):
    """Per-frame PSNR, SSIM, spatial error (L_st-linear at θ=0) and temporal error
    (L_st-linear at θ=1, NaN on the first frame), for ``rollout.metrics``; on HDR
    frames all of them on the tone-mapped pre-exposed colour (``losses.displayed``)."""
    @losses.displayed
    def fn(out, target, prev_out, prev_target, has_prev, frame):
        x, y = losses.errors(out, target, prev_out, prev_target, has_prev, frame, factor)
        mean = lambda v: jnp.mean(v, axis=(1, 2, 3))  # noqa: E731
        return {"psnr": metrics.psnr(out, target), "ssim": metrics.ssim(out, target),
                "spatial": mean(losses.st_linear_terms(x, y, 0.0)),
                "temporal": jnp.where(has_prev, mean(losses.st_linear_terms(x, y, 1.0)),
                                      jnp.nan)}
    return fn


@functools.lru_cache(maxsize=64)
def _video_metrics_fn(model, factor):
    """One jitted function per (model, factor), built once: videos of one shape
    compile once."""
    return jax.jit(lambda p, s, f, t: rollout.metrics(model.step, p, s, f, t,
                                                      frame_metrics(factor))[0])


def video_metrics(model, params, frames, targets, factor):
    """``frame_metrics`` over one time-major video (B=1), as numpy arrays ``[T]``."""
    fn = _video_metrics_fn(model, factor)
    ms = fn(params, rollout.first_state(model, frames), frames, targets)
    return {k: np.asarray(v)[:, 0] for k, v in ms.items()}


def evaluate(entries, dataset_path, factor, split="test", max_videos=None, progress=True,
             videos=None):
    """``{label: {"psnr": [...], "ssim": [...], "spatial": [...], "temporal": [...]}}``
    per frame (``frame_metrics``), all videos concatenated, plus the video names.
    ``videos``: a shell-style pattern of the video names to take (``random_*`` for the
    randomized test family)."""
    out = {e.label: {} for e in entries}
    with Dataset(dataset_path) as ds:
        names = ds.videos(split)
        if videos:
            names = [n for n in names if fnmatch.fnmatch(n, videos)]
        names = names[:max_videos]
        if not names:
            raise ValueError(f"{dataset_path}: no videos in split {split!r}"
                             + (f" match {videos!r}" if videos else ""))
        for name in tqdm(names, desc=f"evaluate x{factor}", disable=not progress):
            frames, targets = ds.video(split, name, factor)
            frames, targets = jax.tree_util.tree_map(jnp.asarray, (frames, targets))
            for e in entries:
                m = video_metrics(e.model, e.params, frames, targets, factor)
                for k, v in m.items():
                    out[e.label].setdefault(k, []).append(v)
    res = {lab: {k: np.concatenate(v) for k, v in d.items()} for lab, d in out.items()}
    return res, names


def summarize(per_frame):
    """Means over every frame of ``evaluate``'s per-frame metrics (the temporal error,
    undefined on first frames, over the frames that have it)."""
    return {lab: {k: float(np.nanmean(v)) for k, v in d.items()}
            for lab, d in per_frame.items()}


def video_means(model, params, dataset_path, factor, split="test", max_videos=None,
                videos=None, progress=False):
    """``summarize`` of one model with ``params`` over the videos ``evaluate`` takes:
    ``{"psnr", "ssim", "spatial", "temporal"}``."""
    per_frame, _ = evaluate([loading.Entry("m", model, params)], dataset_path, factor, split,
                            max_videos, progress, videos)
    return summarize(per_frame)["m"]


def markdown(summary_by_factor):
    lines = ["| factor | method | PSNR (dB) | SSIM | temporal error |",
             "| --- | --- | --- | --- | --- |"]
    for f, summ in summary_by_factor.items():
        for lab, s in summ.items():
            lines.append(f"| {f}x | {lab} | {s['psnr']:.2f} | {s['ssim']:.4f} | "
                         f"{s['temporal']:.5f} |")
    return "\n".join(lines)


def plot_per_frame(per_frame, path, factor):
    fig = Figure(figsize=(11, 5))
    ax = fig.subplots(2, 1, sharex=True)
    for lab, d in per_frame.items():
        ax[0].plot(d["psnr"], label=lab, lw=1)
        ax[1].plot(d["ssim"], label=lab, lw=1)
    ax[0].set_ylabel("PSNR (dB)")
    ax[1].set_ylabel("SSIM")
    ax[1].set_xlabel("frame (test videos one after another)")
    ax[0].set_title(f"{factor}x up-sampling, per frame")
    ax[0].legend(loc="lower right", fontsize=8)
    for a in ax:
        a.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, format="png")


def crop_grid(entries, dataset_path, factor, path, split="test", crop=64, rows=3):
    """Rows of crops (the region of most detail in the middle frame of a video):
    input (nearest-enlarged), each method, reference."""

    tiles = []
    with Dataset(dataset_path) as ds:
        names = ds.videos(split)
        picks = [names[i * len(names) // rows] for i in range(min(rows, len(names)))]
        for name in picks:
            frames, targets = ds.video(split, name, factor)
            t = len(targets) // 2
            tgt = targets[t, 0]
            H, W, _ = tgt.shape
            c = min(crop, H, W) // factor * factor
            luma = tgt.mean(-1)
            grad = np.abs(np.diff(luma, axis=0))[:, :-1] + np.abs(np.diff(luma, axis=1))[:-1]
            best, yx = -1.0, (0, 0)
            for y in range(0, H - c + 1, c // 2):
                for x in range(0, W - c + 1, c // 2):
                    v = grad[y:y + c - 1, x:x + c - 1].sum()
                    if v > best:
                        best, yx = v, (y // factor * factor, x // factor * factor)
            y, x = yx
            lr = frames.color[t, 0][y // factor:(y + c) // factor, x // factor:(x + c) // factor]
            row = [np.repeat(np.repeat(lr, factor, 0), factor, 1)]
            fj = jax.tree_util.tree_map(lambda a: jnp.asarray(a[:t + 1]), frames)
            for e in entries:
                outs = rollout.video(e.model, e.params, fj)
                row.append(np.asarray(outs[-1, 0])[y:y + c, x:x + c])
            row.append(tgt[y:y + c, x:x + c])
            tiles.append(np.concatenate(row, 1))
    labels = ["input"] + [e.label for e in entries] + ["reference"]
    _labelled_grid(np.concatenate(tiles, 0), labels, path)
    return labels


def _labelled_grid(img, labels, path, tile_px=192, header=18):
    """Save the crops ``img`` (columns of equal width, linear RGB) enlarged to about
    ``tile_px`` per crop (nearest, so the pixels stay visible) under a header row
    naming each column."""
    width = img.shape[1] // len(labels)
    k = max(1, tile_px // width)
    big = np.repeat(np.repeat(img, k, 0), k, 1)
    pic = Image.new("RGB", (big.shape[1], big.shape[0] + header), "white")
    pic.paste(Image.fromarray(np.round(linear_to_srgb(big) * 255).astype(np.uint8)),
              (0, header))
    draw = ImageDraw.Draw(pic)
    for i, text in enumerate(labels):
        draw.text((i * width * k + 4, 3), text, fill="black")
    with atomic_path(path) as tmp:
        pic.save(tmp, format="PNG")


def _parser():
    p = argparse.ArgumentParser(prog="python -m jtus.evaluate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", default="data/default.h5",
                   help="an HDF5 dataset; default: %(default)s (generated if missing)")
    p.add_argument("--split", default="test", help="default: %(default)s")
    p.add_argument("--factor", type=int, nargs="*", help="default: every factor in the data")
    p.add_argument("--models", nargs="+", default=["jau", "tus", "shipped"],
                   help=f"weight-free models "
                        f"({', '.join(n for n in models.NAMES if n not in models.TRAINABLE)}), "
                        f"shipped, or LABEL=PATH (.msgpack, .pt); default: %(default)s")
    p.add_argument("--max-videos", type=int)
    p.add_argument("--videos", help="shell-style pattern of video names, e.g. 'random_*'")
    p.add_argument("--out", default="runs/eval",
                   help="folder for results.md/json, per-frame plots and crop grids; "
                        "default: %(default)s")
    p.add_argument("--no-crops", action="store_true")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--quiet", action="store_true")
    return p


def run(specs, dataset, factors=None, out=None, split="test", max_videos=None, videos=None,
        crops=True, progress=True, command=None):
    """Evaluate model ``specs`` (``loading.load``) on ``split`` of ``dataset`` at each
    of ``factors`` (default: every factor in the data). Returns ``{factor: {label:
    {"psnr", "ssim", "temporal"}}}``; with ``out``, writes ``results.md``,
    ``results.json``, ``per_frame_x{f}.png`` and (``crops``) ``crops_x{f}.png``."""
    if max_videos is not None and max_videos < 1:
        raise ValueError(f"max_videos: expected a positive number of videos, got {max_videos}")
    with Dataset(dataset) as ds:
        factors = list(factors or ds.factors)
    if out:
        check_out_folder(out)  # created only once there is something to write
    summary, legends, names = {}, {}, []
    for f in factors:
        entries = loading.load_all(specs, f)
        per_frame, names = evaluate(entries, dataset, f, split, max_videos, progress=progress,
                                    videos=videos)
        summary[f] = summarize(per_frame)
        if out:
            os.makedirs(out, exist_ok=True)
            plot_per_frame(per_frame, os.path.join(out, f"per_frame_x{f}.png"), f)
            if crops:
                legends[f] = crop_grid(entries, dataset, f, os.path.join(out, f"crops_x{f}.png"),
                                       split)
    if out:
        written = {f"per_frame_x{f}.png" for f in factors} | {f"crops_x{f}.png" for f in legends}
        for name in os.listdir(out):  # an earlier run's plots this run did not remake
            if fnmatch.fnmatch(name, "per_frame_x*.png") or fnmatch.fnmatch(name, "crops_x*.png"):
                if name not in written:
                    os.remove(os.path.join(out, name))
        cmd = command or f"jtus.evaluate.run({list(specs)!r}, {dataset!r}, {factors!r})"
        with atomic_path(os.path.join(out, "results.md")) as tmp, open(tmp, "w") as fh:
            fh.write(f"{markdown(summary)}\n\nCommand: `{cmd}`  \nSplit `{split}` of "
                     f"`{dataset}`, {len(names)} videos; {platform.machine()}, JAX "
                     f"{jax.__version__}, {jax.devices()[0].platform}.\n")
            for f, leg in legends.items():
                fh.write(f"\n`crops_x{f}.png` columns: {', '.join(leg)}\n")
        with atomic_path(os.path.join(out, "results.json")) as tmp, open(tmp, "w") as fh:
            json.dump({str(k): v for k, v in summary.items()}, fh, indent=1)
    return summary


def main(argv=None):
    args = _parser().parse_args(argv)
    cmd = "python -m jtus.evaluate " + " ".join(argv if argv is not None else sys.argv[1:])
    try:
        if args.dataset == PRESETS["default"].dataset:
            ensure_dataset(args.dataset, PRESETS["default"].data_preset, not args.quiet)
        summary = run(args.models, args.dataset, args.factor, args.out, args.split,
                      args.max_videos, args.videos, crops=not args.no_crops,
                      progress=not args.quiet, command=cmd)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({str(k): v for k, v in summary.items()}, indent=1) if args.json
          else markdown(summary))
    if args.out:
        print(f"wrote results, per-frame plots and crop grids to {args.out}/",
              file=sys.stderr if args.json else sys.stdout)
    return 0


if __name__ == "__main__":
    cli.run(main)
