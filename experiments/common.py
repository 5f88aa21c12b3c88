"""Shared pieces of the experiment scripts: output folders, hardware, tables."""

from __future__ import annotations

import json
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "docs", "results")
sys.path.insert(0, ROOT)


def out_dir(name):
    d = os.path.join(RESULTS, name)
    os.makedirs(d, exist_ok=True)
    return d


def hardware_line():
    from jtus.bench import hardware
    hw = hardware()
    return f"{hw['cpu']}, {hw['cores']} cores, JAX {hw['jax']} on {hw['backend']}"


def command_line():
    return "python " + " ".join([os.path.relpath(sys.argv[0], ROOT)] + sys.argv[1:])


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


def st_metrics(factor):
    """Per frame: PSNR, SSIM and L_st-linear at θ=0 (spatial) and θ=1 (temporal)."""
    from jtus import losses, metrics

    def fn(out, target, prev_out, prev_target, has_prev, frame):
        x, y = losses.errors(out, target, prev_out, prev_target, has_prev, frame, factor)
        mean = lambda v: jnp.mean(v, axis=(1, 2, 3))  # noqa: E731
        return {"psnr": metrics.psnr(out, target), "ssim": metrics.ssim(out, target),
                "st0": mean(losses.st_linear_terms(x, y, 0.0)),
                "st1": jnp.where(has_prev, mean(losses.st_linear_terms(x, y, 1.0)), jnp.nan)}
    return fn


def evaluate_videos(model, params, dataset_path, factor, split="test", max_videos=None):
    """Means over whole videos of ``st_metrics``."""
    from jtus import rollout
    from jtus.data.dataset import Dataset

    fn = st_metrics(factor)
    run = jax.jit(lambda p, s, f, t: rollout.metrics(model.step, p, s, f, t, fn, check=False)[0])
    acc = {}
    with Dataset(dataset_path) as ds:
        for name in ds.videos(split)[:max_videos]:
            frames, targets = jax.tree_util.tree_map(jnp.asarray, ds.video(split, name, factor))
            first = jax.tree_util.tree_map(lambda x: x[0], frames)
            ms = run(params, model.init_state(first), frames, targets)
            for k, v in ms.items():
                acc.setdefault(k, []).append(np.asarray(v)[:, 0])
    return {k: float(np.nanmean(np.concatenate(v))) for k, v in acc.items()}
