"""Analytic FLOPs and bytes per frame, from a model's config and the HR size.

Each model module holds its formula (``cost`` in its ``SPECS``). Counts are
multiply-adds x 2 for convolutions and matmuls, and the arithmetic of the hand-written
stages (taps x channels x 2 for a warp). Bytes are the compulsory
traffic of one frame in float32: the LR inputs read, the carried state read and
written, the output written; ``activation_bytes`` adds one write and one read of every
intermediate network tensor, the traffic of an unfused implementation.
"""

from __future__ import annotations

import argparse
import sys

import jax

from jtus import models
from jtus.models.base import Cost


def cost(model_name, config, H, W) -> Cost:
    """Cost of one H x W output frame of ``model_name`` (a ``jtus.models`` name, whose
    module registers the formula) with ``config``."""
    return models.spec(model_name).cost(config, H, W)


def table(names=None, factors=(4, 2), height=1080, width=1920) -> str:
    """A markdown table of parameters, FLOPs and bytes per output pixel and per frame
    (the layout of Table 2 of Herveau et al.)."""

    names = names or models.NAMES
    lines = [f"Per output pixel and per {width}x{height} frame, float32 "
             "(`jtus/cost.py`):", "",
             "| model | factor | parameters | FLOP / pixel | network FLOP / pixel | "
             "bytes / pixel (compulsory) | GFLOP / frame | MB / frame |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name in names:
        for f in factors:
            m = models.build(name, f)
            c = cost(name, m.config, height, width)
            params = (models.param_count(jax.eval_shape(m.init, jax.random.PRNGKey(0)))
                      if name in models.TRAINABLE else 0)
            px = height * width
            lines.append(f"| {name} | {f}x | {params:,} | {c.flops / px:,.0f} | "
                         f"{c.network_flops / px:,.0f} | {c.bytes / px:.1f} | "
                         f"{c.flops / 1e9:.2f} | {c.bytes / 1e6:.0f} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m jtus.cost",
                                description="FLOPs and bytes per output pixel of every model.")
    p.add_argument("--models", nargs="+", default=list(models.NAMES), choices=models.NAMES)
    p.add_argument("--factors", nargs="+", type=int, default=[4, 2])
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--width", type=int, default=1920)
    args = p.parse_args(argv)
    try:
        for f in args.factors:
            if f not in (2, 4):
                raise ValueError(f"--factors: expected 2 or 4, got {f}")
        for name in ("height", "width"):
            v = getattr(args, name)
            if v < 4 or v % 4 or any(v % f for f in args.factors):
                raise ValueError(f"--{name}: expected a positive multiple of 4 and of each "
                                 f"factor {args.factors}, got {v}")
        print(table(args.models, args.factors, args.height, args.width))
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
