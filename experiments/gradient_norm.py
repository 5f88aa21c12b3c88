"""The gradient norm of a training run's loss on one training batch, at initialization
and with the run's trained parameters: zero after training means a collapsed network
(saturated clamped outputs pass no gradient; docs/weights.md). Runs trained since
the epoch log kept gradient norms (``grad_norm``, ``grad_norm_max`` per epoch in
``metrics.json``) are also read from the log: every step of training, not one batch.

    python experiments/gradient_norm.py runs/ablation_no_accumulation runs/sweep_theta/L1

Writes ``docs/results/<--name>/result.{md,json}`` (default ``gradient_norm``).
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np
from common import write

from jtus import loading, recipe, rollout
from jtus.data.dataset import Dataset


def gradient_norms(workdir, seed=1):
    params, cfg = loading.load_params(os.path.join(workdir, "checkpoint.msgpack"))
    model, loss_fn = recipe.model_for(cfg), recipe.loss_for(cfg)
    plan = recipe.plan(cfg)
    window, loss_frames = plan.window, plan.loss_frames
    with Dataset(cfg.dataset) as ds:
        fr, tg = jax.tree_util.tree_map(jnp.asarray, ds.crops(
            "train", cfg.factor, cfg.batch, window, cfg.crop, np.random.default_rng(seed)))
    out = {}
    for name, p in (("init", model.init(jax.random.PRNGKey(cfg.seed))), ("trained", params)):
        carry = recipe.start_carry(model, fr, tg)
        g = jax.grad(lambda q: rollout.window_loss(model.step, loss_fn, q, carry, fr, tg,
                                                   loss_frames=loss_frames)[0])(p)
        out[name] = float(jnp.sqrt(sum(jnp.sum(x * x) for x in jax.tree_util.tree_leaves(g))))
    return out


def logged_norms(workdir):
    """``[(epoch, mean, max gradient norm)]`` from the run's epoch log; [] for runs
    logged before the log kept them."""
    import json

    path = os.path.join(workdir, "metrics.json")
    if not os.path.exists(path):
        return []
    with open(path) as fh:
        return [(h["epoch"], h["grad_norm"], h["grad_norm_max"]) for h in json.load(fh)
                if "grad_norm" in h]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("workdirs", nargs="+")
    p.add_argument("--name", default="gradient_norm", help="docs/results/NAME/")
    args = p.parse_args(argv)
    rows, data = [], {}
    for w in args.workdirs:
        n = gradient_norms(w)
        logged = logged_norms(w)
        data[w] = {**n, "logged": logged}
        last = (f"{logged[-1][1]:.3g} / {logged[-1][2]:.3g} (epoch {logged[-1][0]})"
                if logged else "not logged")
        rows.append(f"| `{os.path.relpath(w)}` | {n['init']:.3g} | {n['trained']:.3g} | {last} |")
    table = "\n".join(["| run | gradient norm at initialization | trained | last epoch's "
                       "mean / max over its steps |", "| --- | --- | --- | --- |"] + rows)
    write(args.name, table, data, note="One training batch (seed 1) of each run's own "
          "recipe; a trained norm of exactly zero is a collapsed network (docs/weights.md).")


if __name__ == "__main__":
    main()
