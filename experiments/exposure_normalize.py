"""A trained KPN or NSRR switched to exposure-normalized colour (the models' config
field ``exposure``), starting from what it computes at a given exposure: the weights
that read colour are multiplied by that mean colour, and NSRR's output layer divided
by it (``kpn.normalize_exposure``, ``nsrr.normalize_exposure``); the run config gains
``exposure="normalized"``, so ``python -m jtus.train --init-from OUT.msgpack
--model-override exposure=normalized`` fine-tunes it:

    python experiments/exposure_normalize.py experiments/weights/kpn-clamp-div-x2.msgpack \\
        --mean 0.37 --out runs/kpn-exposure-x2/init

writes ``runs/kpn-exposure-x2/init.msgpack``, ``init.json`` (the source's run config
with the new field) and ``init-training.csv`` (the source's per-epoch log, where it has
one), so that a training budget counts the runs before the switch. ``--mean`` defaults to
the median frame mean of the training data the networks learnt most from (``diverse``'s
train split: 0.37 at both factors). Refuses a checkpoint of another model, or one that
is normalized already, before anything is written.
"""

from __future__ import annotations

import argparse
import dataclasses

from jtus import checkpoint, config, loading, recipe
from jtus.models import kpn, nsrr

CONVERTERS = {"kpn": kpn.normalize_exposure, "nsrr": nsrr.normalize_exposure,
              "nsrr-fast": nsrr.normalize_exposure}


def normalized(params, cfg, mean):
    """``(params, run config)`` of the network in ``params`` fed exposure-normalized
    colour."""
    if cfg.model not in CONVERTERS:
        raise ValueError(f"model: expected a checkpoint of one of {tuple(CONVERTERS)}, "
                         f"got {cfg.model}")
    model_config = recipe.model_config(cfg)
    overrides = dict(cfg.model_overrides)
    overrides["exposure"] = "normalized"
    return (CONVERTERS[cfg.model](params, model_config, mean),
            dataclasses.replace(cfg, model_overrides=tuple(overrides.items())))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="a KPN or NSRR checkpoint or exported weights (.msgpack)")
    p.add_argument("--mean", type=float, default=0.37,
                   help="the frame mean colour at which the outputs stay as they are")
    p.add_argument("--out", required=True, help="output base: writes OUT.msgpack, OUT.json")
    args = p.parse_args(argv)
    try:
        params, cfg = normalized(*loading.load_params(args.checkpoint), args.mean)
    except ValueError as e:
        raise SystemExit(f"{args.checkpoint}: {e}") from e
    print(checkpoint.write_params(args.out, params, config.to_json(cfg),
                                  loading.training_log(args.checkpoint)))


if __name__ == "__main__":
    main()
