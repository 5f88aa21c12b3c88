"""The three terms of Herveau et al.'s KPN loss, unweighted, for a KPN at its
initialization on one 4x training batch of the ``diverse`` data: what the temporal
weight in ``losses.kpn_loss`` is scaled by (its docstring; docs/comparison.md).

    python experiments/kpn_loss_terms.py [--workdir runs/kpn-diverse-x4]

With ``--workdir``, the trained parameters of that run are measured too.
"""

from __future__ import annotations

import argparse
import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
from common import write

from jtus import loading, losses, recipe, rollout
from jtus.config import PRESETS
from jtus.data.dataset import Dataset

TERMS = ("reference", "gradient", "temporal")


def terms(config, params, seed=3):
    """Unweighted terms on the last frame of one training batch (the frame KPN's loss
    is taken on), after the network has run over the whole sequence."""
    model = recipe.model_for(config)
    with Dataset(config.dataset) as ds:
        fr, tg = jax.tree_util.tree_map(jnp.asarray, ds.crops(
            "train", config.factor, config.batch, config.seq_len, config.crop,
            np.random.default_rng(seed)))
    outs = rollout.video(model, params, fr)
    last = jax.tree_util.tree_map(lambda x: x[-1], fr)
    out = {}
    for name, w in zip(TERMS, np.eye(3)):
        fn = losses.displayed(losses.kpn_loss(config.factor, weights=tuple(w)))
        out[name] = float(fn(outs[-1], tg[-1], outs[-2], tg[-2], jnp.asarray(True), last))
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--workdir", help="also measure this run's trained parameters")
    args = p.parse_args(argv)
    config = dataclasses.replace(PRESETS["diverse"], model="kpn", loss="kpn", factor=4,
                                 crop=64, seq_len=8, mode="bptt", loss_frames=1)
    rows = [("initialized", terms(config, loading.init_params(config)))]
    if args.workdir:
        params, _ = loading.load_params(os.path.join(args.workdir, "checkpoint.msgpack"))
        rows.append((f"trained ({args.workdir})", terms(config, params)))
    lines = ["| parameters | " + " | ".join(TERMS) + " | reference / temporal |",
             "| --- | --- | --- | --- | --- |"]
    for name, t in rows:
        lines.append(f"| {name} | " + " | ".join(f"{t[k]:.4f}" for k in TERMS)
                     + f" | {t['reference'] / t['temporal']:.1f} |")
    write("kpn-loss-terms", "\n".join(lines), {name: t for name, t in rows},
          "Unweighted terms on the last frame of one 4x training batch (seed 3) of the "
          "diverse data, crop 64, batch 4, 8 frames.")


if __name__ == "__main__":
    main()
