"""How long a memory DLCTUS's blend wants: the trained network with its blend factor
``o1`` (the weight of the fresh jitter-aligned input, thesis eq. 44) multiplied by a
constant ``c`` at inference, on validation holds and on moving validation videos.

    python experiments/blend_scale.py --factor 2 --scales 1 0.9 0.8 0.7 \\
        --name blend-scale-x2

``c < 1`` keeps more of the history in every pixel of every frame: a probe of the
trained blend, not a model (no trained weights use it). On a static hold it tells
whether the settled hold would score higher with a longer memory; on moving videos what
that longer memory costs where the history is stale. Validation data only: the first
``--random-val`` randomized validation scenes and the game validation levels as 64-frame
holds (``static_hold.py``'s), and the validation splits of ``data/diverse.h5`` and
``data/game.h5``. Before any scoring the script checks that ``c = 1`` is the model's
own step (the same outputs to 1e-6 on a hold).

Writes ``docs/results/<name>/result.{md,json}``.
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
from common import ROOT, write
from static_hold import cycles, fall_and_gain, game_holds, hold_curves, random_val_holds

from jtus import evaluate, loading, rollout, sampling
from jtus.models import dlctus
from jtus.models.base import bind

VAL_LEVELS = ("oa_dm6", "oacmpdm7", "czest1dm", "czest1tourney", "fan")
MOVING = {"diverse val": "data/diverse.h5", "game val": "data/game.h5"}


def scaled_advance(params, state, pre, config, scale):
    """``dlctus.advance`` with ``o1`` multiplied by ``scale``: the clamped network output
    times ``scale`` on its ``o1`` channels (``pixel_unshuffle`` of the per-pixel factors
    ``(scale, 1)``), then the model's own output construction."""
    net_in, jau, hist = dlctus.reproject(state, pre, config)
    net = jnp.clip(dlctus.network(params, net_in, config).astype(jau.dtype), 0.0, 1.0)
    factors = jnp.broadcast_to(jnp.asarray([scale, 1.0], jau.dtype), jau.shape[:-1] + (2,))
    out = dlctus.output(jau, hist, net * sampling.pixel_unshuffle(factors, dlctus.DOWN),
                        config)
    return out[..., :3], dlctus.State(out)


def scaled_entry(entry, scale):
    """``entry``'s DLCTUS with ``o1`` scaled by ``scale``, as a ``loading.Entry``."""
    config = entry.model.config
    if not isinstance(config, dlctus.Config) or config.hdr:
        raise SystemExit(f"{entry.label}: expected an LDR DLCTUS model")

    def advance(params, state, pre, config):
        return scaled_advance(params, state, pre, config, scale)

    model = bind(config, dlctus.step, init=dlctus.init, init_state=dlctus.init_state,
                 prepare=dlctus.prepare_frame, advance=advance)
    return loading.Entry(f"c={scale:g}", model, entry.params, entry.name)


def check_identity(entry, hold):
    """``c = 1`` gives the model's own outputs on ``hold`` (to 1e-6): what every other
    scale is compared with is the trained model."""
    frames = jax.tree_util.tree_map(jnp.asarray, hold[0])
    got = rollout.video(scaled_entry(entry, 1.0).model, entry.params, frames)
    want = rollout.video(entry.model, entry.params, frames)
    err = float(jnp.abs(got - want).max())
    if err > 1e-6:
        raise SystemExit(f"c = 1 differs from the model's step by {err:.2e} (> 1e-6)")
    return err


def hold_rows(entries, factor, holds):
    curves, _ = hold_curves(entries, factor, holds)
    rows = {}
    for label, curve in curves.items():
        fall, gain = fall_and_gain(curve)
        change, ripple, last = cycles(curve)
        rows[label] = {"last cycle": last, "gain": gain,
                       "ripple": ripple, "cycle change": change, "fall": fall}
    return rows


def moving_rows(entries, factor, data_root):
    out = {}
    for col, path in MOVING.items():
        per_frame, _ = evaluate.evaluate(entries, os.path.join(data_root, path), factor,
                                         split="val", progress=False)
        out[col] = {lab: float(s["psnr"]) for lab, s in evaluate.summarize(per_frame).items()}
    return out


def table(holds, moving, labels):
    head = ("| scale | " + " | ".join(f"{k} PSNR" for k in moving) + " | "
            + " | ".join(f"{fam} holds: last cycle / ripple / cycle change" for fam in holds)
            + " |")
    lines = [head, "| --- " * (1 + len(moving) + len(holds)) + "|"]
    for lab in labels:
        cells = [f"{moving[k][lab]:.3f}" for k in moving]
        cells += [f"{h[lab]['last cycle']:.3f} / {h[lab]['ripple']:.2f} / "
                  f"{h[lab]['cycle change']:+.2f}" for h in holds.values()]
        lines.append(f"| {lab} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--factor", type=int, default=2, choices=(2, 4))
    p.add_argument("--model", default="shipped", help="shipped or LABEL=PATH (a DLCTUS)")
    p.add_argument("--scales", type=float, nargs="+", default=[1.0, 0.9, 0.8, 0.7])
    p.add_argument("--random-val", type=int, default=8)
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--data-root", default=ROOT)
    p.add_argument("--name", default=None)
    args = p.parse_args()
    bad = [s for s in args.scales if not 0.0 < s <= 1.0]
    if bad:
        p.error(f"--scales: expected values in (0, 1], got {bad}")
    name = args.name or f"blend-scale-x{args.factor}"
    entry = loading.load(args.model, args.factor)
    holds = {"game": game_holds([args.factor], args.size, VAL_LEVELS)[args.factor],
             "random-val": random_val_holds([args.factor], args.size,
                                            args.random_val)[args.factor]}
    err = check_identity(entry, holds["game"][0])
    entries = [scaled_entry(entry, s) for s in args.scales]
    hold_res = {fam: hold_rows(entries, args.factor, h) for fam, h in holds.items()}
    moving = moving_rows(entries, args.factor, args.data_root)
    labels = [e.label for e in entries]
    md = table(hold_res, moving, labels)
    note = (f"{args.model} DLCTUS at {args.factor}x with o1 scaled by c at inference "
            f"(c = 1: the model itself, checked to {err:.1e}). Holds: 64 still frames "
            f"at {args.size}x{args.size}, the mean curve over the game validation levels "
            f"{', '.join(VAL_LEVELS)} and over the first {args.random_val} randomized "
            f"validation scenes; last cycle: the mean of the last 16 frames; ripple: their "
            f"range; cycle change: the last cycle's mean minus the one before.")
    write(name, md, {"holds": hold_res, "moving": moving, "scales": args.scales}, note)


if __name__ == "__main__":
    main()
