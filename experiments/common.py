"""Shared pieces of the experiment scripts: output folders, hardware, tables."""

from __future__ import annotations

import json
import os
import shlex
import sys

import jax
import jax.numpy as jnp
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "docs", "results")
sys.path.insert(0, ROOT)

# the DLCTUS reprojection warps the experiments compare: (method, Keys a), cheapest first
WARPS = (("bilinear", -0.75), ("bicubic5", -0.75), ("bicubic9", -0.75), ("catmull_rom", -0.5),
         ("bicubic", -0.75))


def out_dir(name):
    d = os.path.join(RESULTS, name)
    os.makedirs(d, exist_ok=True)
    return d


def hardware_line():
    from jtus.bench import hardware
    hw = hardware()
    return f"{hw['cpu']}, {hw['cores']} cores, JAX {hw['jax']} on {hw['backend']}"


def command_line():
    return "python " + shlex.join([os.path.relpath(sys.argv[0], ROOT)] + sys.argv[1:])


def write(name, table, data, note=""):
    """``docs/results/<name>/result.md`` (table, command, hardware) and ``result.json``."""
    d = out_dir(name)
    with open(os.path.join(d, "result.md"), "w") as fh:
        fh.write(f"{table}\n\nCommand: `{command_line()}`  \nHardware: {hardware_line()}.\n")
        if note:
            fh.write(f"\n{note}\n")
    with open(os.path.join(d, "result.json"), "w") as fh:
        json.dump(data, fh, indent=1, default=float)
    print(table)
    return d


def weights_path(name, factor):
    """Where a trained comparison system's parameters are shipped, relative to ``ROOT``:
    ``experiments/weights/<name>-x<factor>.msgpack`` (its ``.json`` config and
    ``-training.csv`` log beside it)."""
    return f"experiments/weights/{name}-x{factor}.msgpack"


def l1_recipe(factor, epochs, dataset, steps_per_epoch=100, seed=0):
    """The short DLCTUS recipe of the θ sweep (``sweep_theta.py``): the ``default``
    preset with one validation video. Returns ``(config, workdir of the L1 run)``."""
    import dataclasses

    from jtus.config import PRESETS

    config = dataclasses.replace(PRESETS["default"], factor=factor, epochs=epochs,
                                 steps_per_epoch=steps_per_epoch, seed=seed, dataset=dataset,
                                 val_videos=1)
    return config, os.path.join(ROOT, "runs", "sweep_theta", "L1")


def evaluate_videos(model, params, dataset_path, factor, split="test", max_videos=None,
                    videos="*"):
    """Means over whole videos of ``jtus.evaluate.video_metrics`` (PSNR, SSIM, spatial and
    temporal error), on the first ``max_videos`` videos whose names match ``videos``."""
    import fnmatch

    from jtus.data.dataset import Dataset
    from jtus.evaluate import video_metrics

    acc = {}
    with Dataset(dataset_path) as ds:
        names = [n for n in ds.videos(split) if fnmatch.fnmatchcase(n, videos)]
        if not names:
            raise ValueError(f"videos: no {split} video of {dataset_path} matches {videos!r}")
        for name in names[:max_videos]:
            frames, targets = jax.tree_util.tree_map(jnp.asarray, ds.video(split, name, factor))
            for k, v in video_metrics(model, params, frames, targets, factor).items():
                acc.setdefault(k, []).append(v)
    return {k: float(np.nanmean(np.concatenate(v))) for k, v in acc.items()}
