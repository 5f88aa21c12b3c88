"""Inside a DLCTUS static hold: what the network steers while the PSNR drifts.

    python experiments/hold_dynamics.py
    python experiments/hold_dynamics.py --frames 256 --scenes 8 \\
        --models shipped mine=runs/deepholds-x{f}/checkpoint.msgpack

Holds the first ``--scenes`` validation scenes of the randomized family (never a test
seed) still for ``--frames`` frames under the thesis's 16-position jitter (as
``static_hold.py``), runs each DLCTUS model over them frame by frame and reports, per
jitter cycle and averaged over the scenes:

- ``psnr``: of the output against the 16-spp target;
- ``blend``: the mean of ``o1``, the share of the jitter-aligned input in the new history
  (eq. 44; the rest is the reprojected history);
- ``acc``: the mean of the accumulation channel the history carries (eq. 45);
- ``sharpness``: the output's mean squared difference between neighbouring pixels over
  the target's (1: as sharp as the target; above 1: sharper, i.e. aliased or ringing).

Writes ``docs/results/<name>/`` (``result.md``, ``result.json``, ``dynamics_x<f>.png``).
"""

from __future__ import annotations

import argparse
import functools
import os

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
from common import out_dir, write
from tqdm import tqdm

from jtus import loading, sampling
from jtus.models import dlctus
from jtus.sim import get_scene, randomized
from jtus.sim.video import VideoRenderer, static_hold

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

CYCLE = 16  # the thesis jitter sequence's length, at both factors
QUANTITIES = ("psnr", "blend", "acc", "sharpness")


def _energy(img):
    """Mean squared difference between neighbouring pixels of ``[..., H, W, C]``."""
    return float(np.mean(np.diff(img, axis=-3) ** 2) + np.mean(np.diff(img, axis=-2) ** 2))


@functools.partial(jax.jit, static_argnames="config")
def _step(params, state, frame, config):
    """One frame: ``(state, (output, mean o1, mean accumulation))``. The blend ``o1``
    comes from the network run once more beside ``advance`` (its output construction is
    the model's own, not public), so a traced frame costs two network evaluations."""
    pre = dlctus.prepare_frame(frame, config)
    net_in, _, _ = dlctus.reproject(state, pre, config)
    o = sampling.pixel_shuffle(jnp.clip(dlctus.network(params, net_in, config), 0, 1),
                               dlctus.DOWN)
    out, state = dlctus.advance(params, state, pre, config)
    return state, (out, jnp.mean(o[..., 0]), jnp.mean(state.history[..., 3]))


def trace(params, config, frames, targets):
    """``{quantity: [T]}`` of one DLCTUS model over one hold (``frames``: a ``Frame``
    ``[T,1,...]``; ``targets`` ``[T,1,H,W,3]``)."""
    first = jax.tree_util.tree_map(lambda a: jnp.asarray(a[0]), frames)
    state = dlctus.init_state(first, config)
    rows = {q: [] for q in QUANTITIES}
    for t in range(targets.shape[0]):
        state, (out, blend, acc) = _step(params, state, jax.tree_util.tree_map(
            lambda a: jnp.asarray(a[t]), frames), config=config)
        out, tgt = np.asarray(out, np.float64), np.asarray(targets[t], np.float64)
        rows["psnr"].append(float(-10 * np.log10(np.mean((out - tgt) ** 2))))
        rows["blend"].append(float(blend))
        rows["acc"].append(float(acc))
        rows["sharpness"].append(_energy(out) / _energy(tgt))
    return {q: np.asarray(v) for q, v in rows.items()}


def per_cycle(curve):
    """The mean of each whole jitter cycle of ``curve``."""
    n = len(curve) // CYCLE
    return np.asarray(curve[:n * CYCLE]).reshape(n, CYCLE).mean(1)


def plot(curves, factor, path):
    fig, axes = plt.subplots(1, len(QUANTITIES), figsize=(4.2 * len(QUANTITIES), 3.4))
    for ax, q in zip(axes, QUANTITIES):
        for lab, c in curves.items():
            ax.plot(np.arange(len(c[q])), c[q], label=lab)
        ax.set_title(f"{q}, {factor}x")
        ax.set_xlabel("frame of the hold")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=["shipped"],
                   help="DLCTUS models, LABEL=PATH or shipped; {f} is the factor")
    p.add_argument("--factors", type=int, nargs="+", default=[4, 2], choices=(2, 4))
    p.add_argument("--scenes", type=int, default=4, help="validation scenes held")
    p.add_argument("--frames", type=int, default=256, help="frames held still")
    p.add_argument("--size", type=int, default=128)
    p.add_argument("--name", default="hold-dynamics")
    args = p.parse_args()
    if args.frames < 4 * CYCLE:
        p.error(f"--frames: expected at least four jitter cycles ({4 * CYCLE}), "
                f"got {args.frames}")
    seeds = randomized.split_seeds("val", args.scenes)
    rows, data = [], {}
    for f in args.factors:
        entries = loading.load_all([m.replace("{f}", str(f)) for m in args.models], f)
        for e in entries:
            if not isinstance(e.model.config, dlctus.Config):
                p.error(f"--models: {e.label} is not a DLCTUS model")
        sums = {e.label: {q: 0.0 for q in QUANTITIES} for e in entries}
        for s in tqdm(seeds, desc=f"{f}x holds"):
            scene = get_scene(randomized.name_of(s))
            r = VideoRenderer(scene, (args.size, args.size), (f,), 16)
            frames, targets = static_hold(scene, args.size, f, "thesis", args.frames,
                                          renderer=r)
            for e in entries:
                t = trace(e.params, e.model.config, frames, targets)
                for q in QUANTITIES:
                    sums[e.label][q] = sums[e.label][q] + t[q] / len(seeds)
        for lab, c in sums.items():
            cyc = {q: per_cycle(c[q]) for q in QUANTITIES}
            best = int(np.argmax(c["psnr"]))
            rows.append(f"| {f}x | {lab} | {c['psnr'].max():.2f} (frame {best}) | "
                        + " | ".join(f"{cyc['psnr'][i]:.2f}" for i in (1, 3, -1))
                        + f" | {cyc['blend'][1]:.3f} -> {cyc['blend'][-1]:.3f} | "
                        f"{cyc['acc'][1]:.3f} -> {cyc['acc'][-1]:.3f} | "
                        f"{cyc['sharpness'][1]:.2f} -> {cyc['sharpness'][-1]:.2f} |")
            data.setdefault(str(f), {})[lab] = {q: [float(v) for v in c[q]]
                                                for q in QUANTITIES}
        plot(sums, f, os.path.join(out_dir(args.name), f"dynamics_x{f}.png"))
    n = args.frames // CYCLE
    table = ("| factor | model | best PSNR (dB) | PSNR, cycle 2 | cycle 4 | "
             f"cycle {n} (last) | blend o1, cycle 2 -> last | accumulation | "
             "sharpness / target's |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n"
             + "\n".join(rows))
    note = (f"Holds of {args.frames} still frames of the validation scenes "
            f"{', '.join(randomized.name_of(s) for s in seeds)} at {args.size}x{args.size} "
            "(thesis jitter, 16 positions), each quantity averaged over the scenes frame by "
            "frame, then over each jitter cycle.")
    write(args.name, table, data, note=note)


if __name__ == "__main__":
    main()
