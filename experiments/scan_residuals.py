"""What a DLCTUS training window keeps for its backward pass, and how much of it the scan
stacks over the frames.

JAX's autodiff of ``lax.scan`` writes each frame's residuals into buffers stacked over
the frames (``[T, ...]``). On XLA:CPU those buffers are first filled from a broadcast of
zeros and then written one frame at a time; ``python -m jtus.profile`` files the two as
the ``fill`` and ``stacking`` kinds. This script lists the residuals of one window of the
bench's training step (random frames, the window's loss on every frame) with
``jax.ad_checkpoint.print_saved_residuals`` and sums the stacked ones.

    python experiments/scan_residuals.py                # 2x, crop 128, batch 4, 8 frames

Writes ``docs/results/scan-bookkeeping/result.{md,json}``.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import io
import re

import jax
from jax.ad_checkpoint import print_saved_residuals
import numpy as np
from common import write

from jtus import losses, models, rollout
from jtus.bench import random_window

_LINE = re.compile(r"(\w+)\[([\d,]*)\]\s*(.*)")
ITEMSIZE = {"bool": 1, "i8": 1, "u8": 1, "f16": 2, "bf16": 2, "f32": 4, "i32": 4, "u32": 4,
            "f64": 8, "i64": 8}


def parse(text):
    """``print_saved_residuals`` output -> one ``(dtype, shape, bytes, source)`` per line;
    ``source`` is the text after the shape (``output of scan from ...`` for a stacked one)."""
    rows = []
    for line in text.splitlines():
        m = _LINE.match(line.strip())
        if not m:
            continue
        dtype, dims, source = m.groups()
        shape = tuple(int(d) for d in dims.split(",") if d)
        rows.append((dtype, shape, ITEMSIZE[dtype] * int(np.prod(shape, dtype=np.int64)),
                     source))
    return rows


def stacked(rows):
    """The residuals the scan stacks over the frames."""
    return [r for r in rows if r[3].startswith("output of scan")]


def residuals(factor, crop, batch, seq, remat_edges=True):
    model = models.build("dlctus", factor, remat_edges=remat_edges)
    params = model.init(jax.random.PRNGKey(0))
    frames, targets = random_window(factor, crop, batch, seq)
    loss_fn = losses.make(models.spec("dlctus").loss, factor)
    advance, prepare = rollout.parts(model)

    def loss(p):
        carry = rollout.start(rollout.first_state(model, frames), targets[0])
        return rollout.window_loss(advance, loss_fn, p, carry, frames, targets,
                                   loss_frames=seq, prepare=prepare)[0]

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        print_saved_residuals(loss, params)
    return parse(out.getvalue())


def table(rows, seq):
    kept = stacked(rows)
    groups, counts = collections.Counter(), collections.Counter()
    for dtype, shape, size, _ in kept:
        key = f"{dtype}[{','.join(map(str, shape))}]"
        groups[key] += size
        counts[key] += 1
    lines = ["| stacked residual (frames first) | count | MiB |", "| --- | --- | --- |"]
    for k, size in groups.most_common():
        lines.append(f"| {k} | {counts[k]} | {size / 2 ** 20:.1f} |")
    total = sum(groups.values())
    lines += ["", f"Stacked over the {seq} frames: {total / 2 ** 20:.1f} MiB "
              f"({total / seq / 2 ** 20:.2f} MiB per frame), in {len(kept)} buffers; "
              f"other residuals (parameters, the prepared frames): "
              f"{(sum(r[2] for r in rows) - total) / 2 ** 20:.1f} MiB."]
    return "\n".join(lines)


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--factor", type=int, default=2, choices=(2, 4))
    p.add_argument("--crop", type=int, default=128)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--seq", type=int, default=8)
    p.add_argument("--keep-edges", action="store_true",
                   help="dlctus.Config.remat_edges=False: keep the residuals of the "
                        "down-sampling and the output construction")
    p.add_argument("--name", default="scan-bookkeeping")
    args = p.parse_args()
    rows = residuals(args.factor, args.crop, args.batch, args.seq, not args.keep_edges)
    md = (f"DLCTUS {args.factor}x training window: crop {args.crop}, batch {args.batch}, "
          f"{args.seq} frames, the loss on every frame; remat_edges="
          f"{not args.keep_edges}.\n\n" + table(rows, args.seq))
    kept = stacked(rows)
    write(args.name, md, {"stacked_bytes": sum(r[2] for r in kept), "buffers": len(kept),
                          "rows": [list(r) for r in rows]})


if __name__ == "__main__":
    main()
