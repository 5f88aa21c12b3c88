"""The README's picture: what temporal up-sampling gets right or wrong, at a size one
can see. Four hard cases and a game level, each a 128x128 crop of a test video
rendered here (``jtus.sim``, test split, so no training video), shown enlarged:

- thin geometry: ``fence_pan`` (a fence under a panning camera);
- fine texture: ``moire_dolly`` (high-frequency texture under a dolly);
- disocclusion: ``objects`` (moving objects uncover the background);
- static hold: ``textures`` held still (``jtus.sim.video.static_hold``): the steady
  state of an unmoving image under the jitter cycle;
- game level: a held-out game test level from ``data/game.h5`` (``--game-data``;
  OpenArena's textures and lightmaps through the mesh renderer, 128x128, so the crop
  is the whole frame): of the test videos, the one whose last reference frame has the
  most detail (mean absolute Laplacian of the luminance); left out without that file.

Columns: the input (nearest-enlarged), TUS, DLCTUS (shipped weights), the best
comparison system (``--best``: by default the one with the highest PSNR on the held-out
validation videos, read from ``docs/results/comparison-val/x<F>/results.json``, which
``python -m jtus.evaluate`` writes, at the weights the README table scores for it:
``best_on_validation``) and the reference.

The crops are not picked by eye. The frame is the last of the clip; the window is
chosen on the reference alone by a stated rule: for thin geometry, texture and the
static hold the window with the most detail (largest mean absolute Laplacian of the
reference's luminance); for the disocclusion the window where the previous reference,
warped by the motion vectors, differs most from the current one (what no history can
supply). Each crop's PSNR is written next to the picture.

    python experiments/readme_figure.py                  # docs/img/readme_crops.png
    python experiments/readme_figure.py --factor 2 --out docs/img/readme_crops_x2.png

Writes the picture and ``docs/results/readme_figure[_x2]/result.{md,json}``.
"""

from __future__ import annotations

import argparse
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
from common import ROOT, redesigned, second_stage, weights_path, write

from jtus import loading, metrics, rollout, sampling, sim
from jtus.frame import Frame
from jtus.data.dataset import Dataset
from jtus.sim.generate import scene_of
from jtus.sim.video import static_hold

CASES = (("thin geometry", "fence_pan", "detail"), ("fine texture", "moire_dolly", "detail"),
         ("disocclusion", "objects", "disocclusion"), ("static hold", "textures", "hold"))

CROP = 128


def clip(scene_name, size, factor, frames):
    """``(Frame [T,1,...], targets [T,1,H,W,3])`` of test video 0 of a built-in scene,
    or its static hold."""
    scene = scene_of(scene_name)
    if scene_name == "textures":
        return static_hold(scene, size, factor, "thesis", frames)
    v = sim.render_video(scene, "test", 0, frames, size=(size, size), factors=(factor,))
    x = v[f"x{factor}"]
    frame = Frame(x["color"][:, None], x["depth"][:, None], x["motion"][:, None],
                  x["jitter"][:, None], v["reset"][:, None])
    return frame, v["target"][:, None]


def _luma(img):
    return img @ np.array([0.2126, 0.7152, 0.0722], np.float32)


def _best_window(score, crop):
    """Top-left corner of the ``crop`` window with the largest mean of ``score [H,W]``."""
    c = np.pad(np.cumsum(np.cumsum(score, 0), 1), ((1, 0), (1, 0)))
    s = c[crop:, crop:] - c[:-crop, crop:] - c[crop:, :-crop] + c[:-crop, :-crop]
    y, x = np.unravel_index(np.argmax(s), s.shape)
    return int(y), int(x)


def detail(ref):
    """Absolute Laplacian of the luminance of ``ref [H,W,3]`` (0 on the border)."""
    lum = _luma(ref)
    lap = np.zeros_like(lum)
    lap[1:-1, 1:-1] = np.abs(4 * lum[1:-1, 1:-1] - lum[:-2, 1:-1] - lum[2:, 1:-1]
                             - lum[1:-1, :-2] - lum[1:-1, 2:])
    return lap


def game_video(path, factor, split="test"):
    """``(name, Frame [T,1,...], targets [T,1,H,W,3])`` of the test video of the game
    data whose last reference frame has the most detail."""
    with Dataset(path) as ds:
        names = ds.videos(split)
        score = {n: float(detail(ds.file[f"{split}/{n}/target"][-1].astype(np.float32)).mean())
                 for n in names}
        name = max(score, key=score.get)
        frames, targets = ds.video(split, name, factor)
        scene = ds.file[f"{split}/{name}"].attrs["scene"]
    return f"{scene} ({name})", frames, targets


def window(rule, frame, targets, factor):
    ref = targets[-1, 0]
    if rule == "disocclusion":
        mv = jnp.asarray(frame.motion[-1])
        prev = sampling.sample(jnp.asarray(targets[-2]),
                               sampling.reproject_coords(mv, factor), "bilinear")
        score = np.abs(np.asarray(prev[0]) - ref).sum(-1)
    else:
        score = detail(ref)
    return _best_window(score, CROP)


def outputs(entry, frame):
    fr = jax.tree_util.tree_map(jnp.asarray, frame)
    return np.asarray(rollout.video(entry.model, entry.params, fr)[-1, 0])


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--factor", type=int, default=4, choices=(2, 4))
    p.add_argument("--size", type=int, default=256, help="HR size of each clip")
    p.add_argument("--frames", type=int, default=32)
    p.add_argument("--best", help="the comparison system's LABEL=PATH (default: "
                   "best_on_validation)")
    p.add_argument("--game-data", default=os.path.join(ROOT, "data", "game.h5"),
                   help="the game data, for the game row (left out when missing)")
    p.add_argument("--zoom", type=int, default=2, help="nearest enlargement of each crop")
    p.add_argument("--out", default=os.path.join(ROOT, "docs", "img", "readme_crops.png"))
    args = p.parse_args(argv)
    if args.size < CROP or args.size % (4 * args.factor):
        p.error(f"--size: expected >= {CROP} and a multiple of {4 * args.factor}, "
                f"got {args.size}")
    best = args.best or best_on_validation(args.factor)
    print(f"comparison system: {best}", flush=True)
    entries = loading.load_all(["tus", "shipped", best], args.factor)
    labels = ["input"] + [e.label for e in entries] + ["reference"]
    grid, data, rows = [], [], []
    cases = list(CASES)
    if os.path.exists(args.game_data):
        cases.append(("game level", None, "detail"))
    else:
        print(f"no {args.game_data} (python -m jtus.data generate --preset game): the game "
              "row is left out", flush=True)
    for case, scene, rule in cases:
        if scene is None:
            scene, frame, targets = game_video(args.game_data, args.factor)
        else:
            frame, targets = clip(scene, args.size, args.factor, args.frames)
        y, x = window(rule, frame, targets, args.factor)
        ref = targets[-1, 0]
        lr = np.asarray(frame.color[-1, 0])
        inp = np.repeat(np.repeat(lr, args.factor, 0), args.factor, 1)
        imgs = [inp] + [outputs(e, frame) for e in entries] + [ref]
        crops = [np.clip(im[y:y + CROP, x:x + CROP], 0, 1) for im in imgs]
        psnr = [float(metrics.psnr(jnp.asarray(c[None]), jnp.asarray(crops[-1][None]))[0])
                for c in crops[:-1]]
        grid.append(crops)
        data.append({"case": case, "scene": scene, "rule": rule, "frame": len(targets) - 1,
                     "window_yx": [y, x], "psnr": dict(zip(labels[:-1], psnr))})
        rows.append(f"| {case} | `{scene}` | ({y}, {x}) | " + " | ".join(f"{v:.2f}" for v in psnr)
                    + " |")
        print(rows[-1], flush=True)
    picture(grid, labels, [d["case"] for d in data], data, args)
    name = "readme_figure" + ("" if args.factor == 4 else f"_x{args.factor}")
    table = "\n".join(["| case | scene | window (y, x) | PSNR of the crop (dB): "
                       + " | ".join(labels[:-1]) + " |", "| --- " * (3 + len(labels) - 1) + "|"]
                      + rows)
    write(name, table, data,
          note=f"{args.factor}x; {args.size}x{args.size} clips of {args.frames} frames (test "
               f"split), the last frame, {CROP}x{CROP} windows chosen on the reference by the "
               f"rule in the script's docstring; picture: `{os.path.relpath(args.out, ROOT)}`.")


BASELINES = ("jau", "tus", "dlctus-shipped")


def best_on_validation(factor, root=ROOT):
    """``LABEL=PATH`` of the trained comparison system with the highest PSNR in
    ``docs/results/comparison-val/x<F>/results.json``, at the weights the README table
    scores for it: its adopted redesign (``common.REDESIGNED``), else its adopted
    second stage, else ``experiments/weights/LABEL-x<F>.msgpack``."""
    path = os.path.join(root, "docs", "results", "comparison-val", f"x{factor}", "results.json")
    with open(path) as fh:
        scores = json.load(fh)[str(factor)]
    trained = {k: v["psnr"] for k, v in scores.items() if k not in BASELINES}
    if not trained:
        raise ValueError(f"{path}: no comparison system scored; run the command in its "
                         f"results.md with the trained systems")
    label = max(trained, key=trained.get)
    adopted = redesigned(label, factor, root) or second_stage(label, factor, root)
    return f"{label}={adopted[0] if adopted else weights_path(label, factor)}"


def picture(grid, labels, cases, data, args):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from jtus.data.exr import linear_to_srgb

    z = CROP * args.zoom
    n_r, n_c = len(grid), len(labels)
    fig, axes = plt.subplots(n_r, n_c, figsize=(n_c * z / 100, n_r * z / 100 + 0.6), dpi=100,
                             squeeze=False)
    for r, crops in enumerate(grid):
        for c, crop in enumerate(crops):
            ax = axes[r, c]
            big = np.repeat(np.repeat(crop, args.zoom, 0), args.zoom, 1)
            ax.imshow(linear_to_srgb(np.clip(big, 0, 1)), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(labels[c], fontsize=10)
            if c == 0:
                ax.set_ylabel(cases[r], fontsize=10)
            if c < n_c - 1:
                ax.text(4, z - 6, f"{data[r]['psnr'][labels[c]]:.2f} dB", color="yellow",
                        fontsize=8, bbox=dict(facecolor="black", alpha=0.6, pad=1, lw=0))
    fig.tight_layout(pad=0.3)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    fig.savefig(args.out)
    plt.close(fig)


if __name__ == "__main__":
    main()
