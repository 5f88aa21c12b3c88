"""ONNX parity: the exported DLCTUS step run by onnxruntime against jtus's step over a
video (64x96 output by default, random inputs, motion of a few LR pixels, cuts at
frames 0 and 15, a varying exposure), the exported model feeding its own history back.
Needs the ``export`` extra (``pip install -e ".[export]"``).

    python experiments/onnx_parity.py                     # shipped weights, 4x and 2x
    python experiments/onnx_parity.py --frames 60 --size 128 192

Writes ``docs/results/onnx-parity/result.{md,json}``: per factor, the largest absolute
difference of the output frame and of the history over all frames.
"""

from __future__ import annotations

import argparse
import os
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
from common import write

from jtus import export
from jtus.frame import Frame
from jtus.models import dlctus

INPUTS = ("color", "depth", "motion", "jitter", "reset", "exposure")  # Frame's order


def feeds(frames, h, w, factor, cuts=(0, 15), seed=7):
    """The onnxruntime inputs of each frame (without ``history``), random but plausible."""
    rng = np.random.default_rng(seed)
    lh, lw = h // factor, w // factor
    for t in range(frames):
        yield {"color": rng.random((1, lh, lw, 3), np.float32),
               "depth": rng.random((1, lh, lw, 1), np.float32),
               "motion": (1.5 * rng.standard_normal((1, lh, lw, 2))).astype(np.float32),
               "jitter": rng.random((1, 2), np.float32),
               "exposure": np.array([0.8 + 0.02 * t], np.float32),
               "reset": np.array([t in cuts])}


def parity(factor, frames, h, w, weights="shipped"):
    """Largest ``|onnx - jtus|`` of the frame and of the history over ``frames`` frames."""
    import onnxruntime as ort

    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "dlctus.onnx")
        export.main(["--model", weights, "--factor", str(factor), "--format", "onnx",
                     "--size", str(h), str(w), "--out", path, "--force"])
        sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    model, params = export.load_exportable(weights, factor)[:2]
    step = jax.jit(model.step)
    hist = np.zeros((1, h, w, 4), np.float32)
    state = dlctus.State(jnp.asarray(hist))
    worst_frame = worst_hist = 0.0
    for feed in feeds(frames, h, w, factor):
        got, hist = sess.run(None, {**feed, "history": hist})
        want, state = step(params, state, Frame(*(jnp.asarray(feed[k]) for k in INPUTS)))
        worst_frame = max(worst_frame, float(np.abs(got - np.asarray(want)).max()))
        worst_hist = max(worst_hist, float(np.abs(hist - np.asarray(state.history)).max()))
    return {"factor": factor, "frames": frames, "size": [h, w],
            "max_abs_frame": worst_frame, "max_abs_history": worst_hist}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("--size", type=int, nargs=2, default=[64, 96], metavar=("H", "W"))
    p.add_argument("--factors", type=int, nargs="+", default=[4, 2], choices=[2, 4])
    args = p.parse_args(argv)
    h, w = args.size
    if h % 4 or w % 4:
        p.error(f"--size: expected multiples of 4 (the 4x input), got {h} {w}")
    rows = [parity(f, args.frames, h, w) for f in args.factors]
    table = ("| factor | frames | output | max abs difference, frame | max abs difference, "
             "history |\n| --- | --- | --- | --- | --- |\n" + "\n".join(
                 f"| {r['factor']}x | {r['frames']} | {h}x{w} | {r['max_abs_frame']:.2g} | "
                 f"{r['max_abs_history']:.2g} |" for r in rows))
    write("onnx-parity", table, rows, note="The shipped DLCTUS exported with `python -m "
          "jtus.export --format onnx` and run by onnxruntime's CPU provider, fed its own "
          "history; jtus's step in float32 on the same inputs. Inputs are random: colour, "
          "depth and jitter uniform, motion normal with a 1.5 LR-pixel spread, cuts at "
          "frames 0 and 15, exposure rising from 0.8 by 0.02 a frame.")


if __name__ == "__main__":
    main()
