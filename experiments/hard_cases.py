"""Static holds under every supported jitter sequence: does each system settle?

    python experiments/hard_cases.py                      # TUS presets and shipped DLCTUS
    python experiments/hard_cases.py --models tus-mean tus shipped \
        mine=runs/diverse-x4/checkpoint.msgpack

The built-in ``textures`` scene held still at 128x128 (``jtus.sim.video.static_hold``),
384 frames per jitter sequence and factor. Per system: the first frame's PSNR, the
best and where it falls, the mean of the last 32 frames, their spread (max - min) and
the largest frame-to-frame swing after frame 24 (a still image should not flicker).
Writes ``docs/results/hard_cases/``.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
from common import write

from jtus import loading, metrics, rollout, sim
from jtus.sampling.jitter import VARIETY
from jtus.sim.video import static_hold


def curve(entry, frames, targets):
    fr = jax.tree_util.tree_map(jnp.asarray, frames)
    outs = rollout.video(entry.model, entry.params, fr)
    return np.asarray(jax.vmap(metrics.psnr)(outs, jnp.asarray(targets)))[:, 0]


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=["tus-mean", "tus", "shipped"])
    p.add_argument("--frames", type=int, default=384)
    p.add_argument("--size", type=int, default=128)
    args = p.parse_args()
    scene = sim.get_scene("textures")
    rows, data = [], []
    for factor in (4, 2):
        entries = loading.load_all(args.models, factor)
        for jit in VARIETY:
            frames, targets = static_hold(scene, args.size, factor, jit, args.frames)
            for e in entries:
                c = curve(e, frames, targets)
                rec = {"factor": factor, "jitter": jit, "system": e.label,
                       "first": float(c[0]), "best": float(c.max()), "best_at": int(c.argmax()),
                       "last32_mean": float(c[-32:].mean()),
                       "last32_spread": float(np.ptp(c[-32:])),
                       "max_swing_after_24": float(np.abs(np.diff(c[24:])).max())}
                data.append(rec)
                rows.append(f"| {factor}x | {jit} | {e.label} | {rec['first']:.2f} | "
                            f"{rec['best']:.2f} (frame {rec['best_at']}) | "
                            f"{rec['last32_mean']:.2f} | "
                            f"{rec['last32_spread']:.3f} | {rec['max_swing_after_24']:.3f} |")
                print(rows[-1], flush=True)
    table = ("| factor | jitter | system | first frame (dB) | best (dB) | last 32 mean (dB) | "
             "last 32 spread (dB) | largest swing after frame 24 (dB) |\n"
             "| --- | --- | --- | --- | --- | --- | --- | --- |\n" + "\n".join(rows))
    write("hard_cases", table, data,
          note=f"`textures` scene held still at {args.size}x{args.size}, {args.frames} frames.")


if __name__ == "__main__":
    main()
