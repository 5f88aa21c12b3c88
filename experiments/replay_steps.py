"""A run's first epoch replayed step by step: the loss and the gradient norm of every
optimizer step, where the epoch log (``metrics.json``) keeps only their mean and maximum.
The replay starts from the run's starting weights (``init_from``, else its seed's
initialization) and draws the same crops (``default_rng([seed, 1])``), so it takes the
same steps: its mean and maximum equal the log's first epoch.

    python experiments/replay_steps.py runs/steady-x4 --name replay-steady-x4
    python experiments/replay_steps.py runs/steady-x4 --frozen --name replay-steady-x4-frozen

``--frozen`` takes every gradient at the starting weights instead (the same crops, no
update applied): whether a spike lies in a batch or in the weights the steps reached.

Writes ``docs/results/<name>/result.{md,json}``: every step's loss and gradient norm,
and the steps whose gradient norm exceeds ``--above`` times the epoch's median.
"""

from __future__ import annotations

import argparse
import contextlib
import os

import jax
import numpy as np
from common import write

from jtus import config as run_config
from jtus import loading, recipe, train
from jtus.data.dataset import Dataset


def replay(workdir, steps=None, frozen=False):
    """``[(step, loss, gradient norm)]`` of the first epoch of the run in ``workdir``
    (its first ``steps`` sequences' optimizer steps, default all). ``frozen``: every
    gradient at the starting weights (the same crops, no update applied)."""
    cfg = run_config.from_json(os.path.join(workdir, "config.json"))
    model, loss_fn, opt = (recipe.model_for(cfg), recipe.loss_for(cfg),
                           recipe.optimizer_for(cfg))
    plan = recipe.plan(cfg)
    ts = train.create_train_state(loading.init_params(cfg), opt)
    step_fn = jax.jit(train.make_train_step(model, loss_fn, opt, loss_frames=plan.loss_frames,
                                            keep_at=plan.keep_at, remat=cfg.remat,
                                            hoist=cfg.hoist, jit=False))
    rng = np.random.default_rng([cfg.seed, 1])
    rows = []
    with Dataset(cfg.dataset) as ds, contextlib.ExitStack() as stack:
        mix = stack.enter_context(Dataset(cfg.mix_dataset)) if cfg.mix_dataset else None
        for _ in range(steps or cfg.steps_per_epoch):
            frames, targets, carry = recipe.training_sequence(cfg, model, ds, mix, cfg.batch,
                                                              rng, recipe.accept_for(cfg))
            for sl in recipe.window_slices(plan, frames, targets):
                after, carry, st = step_fn(ts, carry, *sl)
                ts = ts if frozen else after
                rows.append((len(rows) + 1, float(st["loss"]), float(st["grad_norm"])))
    return rows


def spikes(rows, above):
    """The rows whose gradient norm exceeds ``above`` times the median of all rows."""
    median = float(np.median([r[2] for r in rows]))
    return [r for r in rows if r[2] > above * median], median


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("workdir")
    p.add_argument("--steps", type=int, default=None, help="sequences to replay (default: "
                   "the epoch's)")
    p.add_argument("--above", type=float, default=100.0)
    p.add_argument("--frozen", action="store_true", help="every gradient at the starting "
                   "weights: the same crops, no update applied")
    p.add_argument("--name", default="replay-steps", help="docs/results/NAME/")
    args = p.parse_args(argv)
    rows = replay(args.workdir, args.steps, args.frozen)
    big, median = spikes(rows, args.above)
    norms = [r[2] for r in rows]
    kind = "at the starting weights (frozen)" if args.frozen else "first epoch"
    lines = [f"{args.workdir}, {kind}: {len(rows)} optimizer steps; gradient norm "
             f"median {median:.4g}, mean {np.mean(norms):.4g}, max {max(norms):.6g}.", "",
             f"Steps above {args.above:g} x the median:", "",
             "| step | loss | gradient norm |", "| --- | --- | --- |"]
    lines += [f"| {s} | {loss:.5f} | {g:.6g} |" for s, loss, g in big]
    write(args.name, "\n".join(lines),
          {"workdir": args.workdir, "frozen": args.frozen, "median": median, "rows": rows,
           "above": args.above})


if __name__ == "__main__":
    main()
