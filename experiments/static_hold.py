"""Static holds on held-out content: does a temporal upsampler converge when nothing moves
but the jitter? (``hard_cases.py`` holds a built-in scene for hundreds of frames under
every jitter sequence; this script takes the held-out families.)

    python experiments/external/render_mitsuba.py --clips hold --out data/external-hold
    python experiments/static_hold.py
    python experiments/static_hold.py --factors 4 \\
        --models tus mine=runs/game-x{f}/checkpoint.msgpack

Models (default): TUS, the shipped DLCTUS, its other runs (common.DLCTUS_RUNS) and the
thesis's released model (``--thesis``), where present; ``{f}`` in a model's path is
replaced by the factor. Two families, both held out:

- ``mitsuba``: the independent renderer's ``hold`` clip (16 frames of camera glide, then
  64 frames where only the jitter moves), imported like the other Mitsuba clips;
- ``game``: the first frame of each held-out game test level (``jtus.sim.game``),
  held still for 64 frames by ``jtus.sim.video.static_hold`` (needs
  ``bash data/fetch_game_assets.sh``; skipped with a note without it).

With ``--random-val N`` a third family, for choosing weights: ``random-val``, the first
N validation scenes of the randomized family held the same way (``--levels`` then
names validation levels and ``--mitsuba ''`` leaves the test clip out).

Per model, family and factor, PSNR per frame over the hold (the game levels averaged
frame by frame). The jitter is the thesis's Halton(2,3) cycle of 16 positions at both
factors, so a converged upsampler's PSNR is periodic with period 16: each jitter
position adds a different sample, and the ripple within a cycle is its steady state,
not a drift. Hence these readings:

- ``fall``: the best PSNR among the last 12 frames minus the last frame's (the target's
  measure, at most 0.1 dB; it reads the ripple as much as any trend);
- ``cycle change``: the mean PSNR of the last jitter cycle minus that of the cycle before
  (0 for a model that has converged, negative for one that drifts down), and ``ripple``:
  the range of the last cycle;
- ``overshoot``: the hold's best frame minus the last cycle's mean (how far a model
  climbs past where it settles);
- ``gain``: the last cycle's mean minus the hold's first frame.

Writes ``docs/results/<name>/`` (``result.md``, ``result.json``, ``hold_x<f>.png``).
"""

from __future__ import annotations

import argparse
import os

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
from common import DLCTUS_RUNS, THESIS_DIR, dlctus_run, out_dir, thesis_path, write
from tqdm import tqdm

from jtus import evaluate, loading
from jtus.sim import game, get_scene, randomized
from jtus.sim.video import VideoRenderer, static_hold

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

HOLD = 64      # frames held still: four jitter cycles
WINDOW = 12    # the frames the fall is measured over
CYCLE = 16     # the thesis jitter sequence's length, at both factors
MITSUBA_MOVING = 16  # the hold clip's frames before it holds (render_mitsuba.clip_hold)


def default_models(factor, thesis_dir=THESIS_DIR):
    """TUS, the shipped DLCTUS, its other runs and the thesis's model, where present."""
    out = ["tus", "shipped"]
    for label in DLCTUS_RUNS:
        if dlctus_run(factor, label):
            out.append(f"{label}={dlctus_run(factor, label)[0]}")
    if thesis_path(factor, thesis_dir):
        out.append(f"thesis={thesis_path(factor, thesis_dir)}")
    return out


def fall_and_gain(curve, window=WINDOW):
    """``(fall, gain)`` of a PSNR curve over a hold: the best of the last ``window``
    frames minus the last, and the last minus the first."""
    curve = np.asarray(curve, float)
    if curve.ndim != 1 or len(curve) < window:
        raise ValueError(f"curve: expected at least {window} frames, got shape {curve.shape}")
    return float(curve[-window:].max() - curve[-1]), float(curve[-1] - curve[0])


def cycles(curve, cycle=CYCLE):
    """``(change, ripple, last_mean)`` of a PSNR curve over a hold: the mean of the last
    ``cycle`` frames minus the mean of the ``cycle`` frames before them (negative: the
    model drifts down), the range (max - min) of the last cycle, and its mean."""
    c = np.asarray(curve, float)
    if c.ndim != 1 or len(c) < 2 * cycle:
        raise ValueError(f"curve: expected at least {2 * cycle} frames (two jitter cycles), "
                         f"got shape {c.shape}")
    last, before = c[-cycle:], c[-2 * cycle:-cycle]
    return float(last.mean() - before.mean()), float(last.max() - last.min()), \
        float(last.mean())


def mitsuba_curves(entries, factor, root):
    path = os.path.join(root, f"hold-x{factor}.h5")
    if not os.path.exists(path):
        raise SystemExit(f"{path} is missing: python experiments/external/render_mitsuba.py "
                         f"--clips hold --out {root}")
    per_frame, _ = evaluate.evaluate(entries, path, factor, progress=False)
    return {e.label: per_frame[e.label]["psnr"][MITSUBA_MOVING:] for e in entries}


def scene_holds(factors, size, scenes, desc):
    """``{factor: [(Frame, targets), ...]}``: one hold per scene, each scene's target
    rendered once for every factor."""
    holds = {f: [] for f in factors}
    for scene in tqdm(scenes, desc=desc):
        r = VideoRenderer(scene, (size, size), tuple(factors), 16)
        for f in factors:
            holds[f].append(static_hold(scene, size, f, "thesis", HOLD, renderer=r))
    return holds


def game_holds(factors, size, levels):
    """One hold per game level (``scene_holds``)."""
    return scene_holds(factors, size, [game.scene_of(game.PREFIX + lv) for lv in levels],
                       "game holds")


def random_val_holds(factors, size, count):
    """One hold per scene of the first ``count`` validation seeds of the randomized
    family (the ``diverse`` data's validation scenes; never a test seed)."""
    return scene_holds(factors, size, [get_scene(randomized.name_of(s))
                                       for s in randomized.split_seeds("val", count)],
                       "random holds")


def hold_curves(entries, factor, holds):
    """``(mean PSNR curve, worst scene's cycle change)`` per model over ``holds``."""
    curves = {e.label: [] for e in entries}
    for frames, targets in holds:
        frames, targets = jax.tree_util.tree_map(jnp.asarray, (frames, targets))
        for e in entries:
            m = evaluate.video_metrics(e.model, e.params, frames, targets, factor)
            curves[e.label].append(m["psnr"])
    return {lab: np.mean(np.stack(c), 0) for lab, c in curves.items()}, \
        {lab: min(cycles(c)[0] for c in cs) for lab, cs in curves.items()}


def plot(curves_by_family, factor, path):
    fams = list(curves_by_family)
    fig, axes = plt.subplots(1, len(fams), figsize=(5 * len(fams), 3.6), squeeze=False)
    for ax, fam in zip(axes[0], fams):
        for lab, c in curves_by_family[fam].items():
            ax.plot(np.arange(len(c)), c, label=lab)
        ax.axvspan(len(c) - CYCLE - 0.5, len(c) - 0.5, color="0.9", zorder=0)
        ax.set_title(f"{fam}, {factor}x (shaded: the last jitter cycle)")
        ax.set_xlabel("frame of the hold")
        ax.set_ylabel("PSNR (dB)")
        ax.grid(alpha=0.3)
    axes[0][-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", nargs="+", default=None,
                   help="LABEL=PATH or built-in names (default: see above)")
    p.add_argument("--thesis", default=THESIS_DIR,
                   help="folder of the thesis's released checkpoints ('' for none)")
    p.add_argument("--factors", type=int, nargs="+", default=[4, 2], choices=(2, 4))
    p.add_argument("--mitsuba", default="data/external-hold",
                   help="folder of the Mitsuba hold clip ('' to leave that family out, as "
                        "when choosing on the validation levels)")
    p.add_argument("--size", type=int, default=128, help="game holds: frame size")
    p.add_argument("--levels", nargs="+", default=list(game.TEST_LEVELS))
    p.add_argument("--random-val", type=int, default=0, metavar="N",
                   help="add a family of holds of the first N validation scenes of the "
                        "randomized family (for choosing weights; default none)")
    p.add_argument("--name", default="static-hold")
    args = p.parse_args()
    bad = [lv for lv in args.levels if lv not in game.TEST_LEVELS + game.VAL_LEVELS]
    if bad:
        p.error(f"--levels: {bad} are training levels; a hold is measured on held-out ones")
    have_game = os.path.isdir(game.assets_dir())
    holds = game_holds(args.factors, args.size, args.levels) if have_game else {}
    rholds = random_val_holds(args.factors, args.size, args.random_val) \
        if args.random_val else {}
    rows, data = [], {}
    for f in args.factors:
        specs = args.models or default_models(f, args.thesis)
        entries = loading.load_all([s.replace("{f}", str(f)) for s in specs], f)
        families = {"mitsuba": (mitsuba_curves(entries, f, args.mitsuba), None)} \
            if args.mitsuba else {}
        if have_game:
            families["game"] = hold_curves(entries, f, holds[f])
        if args.random_val:
            families["random-val"] = hold_curves(entries, f, rholds[f])
        for fam, (curves, worst) in families.items():
            for lab, c in curves.items():
                fall, _ = fall_and_gain(c)
                change, ripple, last = cycles(c)
                w = "" if worst is None else f"{worst[lab]:+.2f}"
                over = float(np.max(c) - last)
                rows.append(f"| {f}x | {fam} | {lab} | {c[0]:.2f} | {last:.2f} | "
                            f"{last - c[0]:+.2f} | {fall:.2f} | {change:+.2f} | {ripple:.2f} "
                            f"| {over:.2f} | {w} |")
                data.setdefault(str(f), {}).setdefault(fam, {})[lab] = {
                    "psnr": [float(v) for v in c], "fall": fall, "cycle_change": change,
                    "ripple": ripple, "overshoot": over, "gain": last - c[0],
                    "worst_level_cycle_change": None if worst is None else worst[lab]}
        plot({fam: c for fam, (c, _) in families.items()}, f,
             os.path.join(out_dir(args.name), f"hold_x{f}.png"))
    table = ("| factor | family | model | first frame (dB) | last cycle's mean (dB) | "
             f"gain (dB) | fall over the last {WINDOW} (dB) | cycle change (dB) | "
             "ripple (dB) | overshoot (dB) | worst level's cycle change (dB) |\n"
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n"
             + "\n".join(rows))
    mitsuba = (f"mitsuba: the `hold` clip's frames {MITSUBA_MOVING}-"
               f"{MITSUBA_MOVING + HOLD - 1}; " if args.mitsuba else "")
    note = (f"Holds of {HOLD} frames ({HOLD // CYCLE} cycles of the {CYCLE}-position jitter). "
            f"{mitsuba}game: the mean curve over the levels {', '.join(args.levels)} at "
            f"{args.size}x{args.size}, 16-spp targets. fall: best of the last {WINDOW} frames "
            "minus the last (target: at most 0.1 dB; on a converged model it reads the "
            "jitter cycle's ripple); cycle change: the last cycle's mean minus the one "
            "before (negative: drifting down; converged: about 0); ripple: the last "
            "cycle's range; overshoot: the hold's best frame minus the last cycle's mean; "
            "gain: the last cycle's mean minus the first frame.")
    if args.random_val:
        note += (f" random-val: the mean curve over the first {args.random_val} validation "
                 f"scenes of the randomized family at {args.size}x{args.size}.")
    if not have_game:
        note += " Game holds skipped: no assets (bash data/fetch_game_assets.sh)."
    write(args.name, table, data, note=note)


if __name__ == "__main__":
    main()
