"""A trained KPN given the sample-mask input (``kpn.Config.sample_mask``), starting from
what it already computes: the first convolution gains a zero weight for the mask
channel (``kpn.add_sample_mask``), and the run config gains ``sample_mask=True``, so
``python -m jtus.train --init-from OUT.msgpack --model-override sample_mask=true``
fine-tunes it and ``candidate_scores.py`` loads it like any checkpoint:

    python experiments/kpn_sample_mask.py experiments/weights/kpn-x4.msgpack \\
        --out runs/kpn-mask-x4/init

writes ``runs/kpn-mask-x4/init.msgpack`` and ``init.json``. Refuses a checkpoint of
another model, or one whose KPN already takes the mask, before anything is written.
"""

from __future__ import annotations

import argparse
import dataclasses

from jtus import checkpoint, config, loading
from jtus.models import kpn


def widened(params, cfg):
    """``(params, run config)`` of the KPN in ``params`` with the sample-mask input."""
    if cfg.model != "kpn":
        raise ValueError(f"model: expected a kpn checkpoint, got {cfg.model}")
    overrides = dict(cfg.model_overrides)
    if overrides.get("sample_mask"):
        raise ValueError("model_overrides: the KPN already takes the sample mask")
    overrides["sample_mask"] = True
    return (kpn.add_sample_mask(params),
            dataclasses.replace(cfg, model_overrides=tuple(overrides.items())))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint", help="a KPN checkpoint or exported weights (.msgpack)")
    p.add_argument("--out", required=True, help="output base: writes OUT.msgpack, OUT.json")
    args = p.parse_args(argv)
    try:
        params, cfg = widened(*loading.load_params(args.checkpoint))
    except ValueError as e:
        raise SystemExit(f"{args.checkpoint}: {e}") from e
    print(checkpoint.write_params(args.out, params, config.to_json(cfg)))


if __name__ == "__main__":
    main()
