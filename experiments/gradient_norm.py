"""The gradient norm of a training run's loss on one training batch, at initialization
and with the run's trained parameters: zero after training means a collapsed network
(saturated clamped outputs pass no gradient; docs/weights.md).

    python experiments/gradient_norm.py runs/ablation_no_accumulation runs/sweep_theta/L1
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import numpy as np

from jtus import rollout, train
from jtus.data.dataset import Dataset


def gradient_norms(workdir, seed=1):
    params, cfg = train.load_params(os.path.join(workdir, "checkpoint.msgpack"))
    model, loss_fn = train._model(cfg), train._loss(cfg)
    window, loss_frames, _, _ = train._plan(cfg)
    with Dataset(cfg.dataset) as ds:
        fr, tg = jax.tree_util.tree_map(jnp.asarray, ds.crops(
            "train", cfg.factor, cfg.batch, window, cfg.crop, np.random.default_rng(seed)))
    out = {}
    for name, p in (("init", model.init(jax.random.PRNGKey(cfg.seed))), ("trained", params)):
        carry = train._start_carry(model, fr, tg)
        g = jax.grad(lambda q: rollout.window_loss(model.step, loss_fn, q, carry, fr, tg,
                                                   loss_frames=loss_frames)[0])(p)
        out[name] = float(jnp.sqrt(sum(jnp.sum(x * x) for x in jax.tree_util.tree_leaves(g))))
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("workdirs", nargs="+")
    args = p.parse_args(argv)
    for w in args.workdirs:
        n = gradient_norms(w)
        print(f"{w}: gradient norm at initialization {n['init']:.3g}, trained {n['trained']:.3g}")


if __name__ == "__main__":
    main()
