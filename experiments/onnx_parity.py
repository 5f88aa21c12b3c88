"""ONNX parity and speed: the exported DLCTUS step run by onnxruntime against jtus's
step over a video at several sizes, both fed their own history, with cuts at frames 0
and 15 and an exposure that changes every frame. One export per factor serves every
size (the native graph's sizes are symbolic). Needs the ``export`` extra
(``pip install -e ".[export]"``).

    python experiments/onnx_parity.py                        # 64x96, 720p, 1080p; 4x, 2x
    python experiments/onnx_parity.py --sizes 64 96 --frames 60

Two kinds of input: ``noise`` (colour, depth and jitter uniform per pixel, motion
normal with a 1.5 LR-pixel spread: every pixel independent, the hardest case) and
``smooth`` (the same draws on a grid 8x coarser, up-sampled bilinearly: images and
motion fields with the spatial coherence of rendered frames). Beside the differences,
the model's own sensitivity: the largest change of jtus's history after one step when
the history it reads is moved by +-1e-5 (``gain``), which bounds how far two correct
float32 implementations may drift apart per frame.

Timing: per size, jtus's jitted step and the onnxruntime session (CPU provider, its
default threads) run alternately on the same frames; the medians of the frames after
the first are reported, with their ratio.

Writes ``docs/results/onnx-parity/result.{md,json}``. With ``--profile H W``: instead,
onnxruntime's own per-operator timing of the 4x graph at that size (its profiler,
summed by operator type over 3 warm runs) beside jtus's whole step, into
``docs/results/onnx-profile/``.

    python experiments/onnx_parity.py --profile 1080 1920
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
from common import write

from jtus import export
from jtus.frame import Frame
from jtus.models import dlctus

INPUTS = ("color", "depth", "motion", "jitter", "reset", "exposure")  # Frame's order


def _field(rng, shape, smooth, scale=1.0, normal=False):
    """``[1,h,w,c]`` float32 draws, independent per pixel or on a coarser grid
    up-sampled bilinearly (``smooth``)."""
    _, h, w, c = shape
    if not smooth:
        x = rng.standard_normal(shape) if normal else rng.random(shape)
        return (scale * x).astype(np.float32)
    coarse = (max(1, h // 8), max(1, w // 8))
    x = rng.standard_normal((1, *coarse, c)) if normal else rng.random((1, *coarse, c))
    x = jax.image.resize(jnp.asarray(scale * x, jnp.float32), shape, "linear")
    return np.asarray(x)


def feeds(frames, h, w, factor, kind="noise", cuts=(0, 15), seed=7):
    """The onnxruntime inputs of each frame (without ``history``)."""
    rng = np.random.default_rng(seed)
    lh, lw = h // factor, w // factor
    smooth = kind == "smooth"
    for t in range(frames):
        yield {"color": _field(rng, (1, lh, lw, 3), smooth),
               "depth": _field(rng, (1, lh, lw, 1), smooth),
               "motion": _field(rng, (1, lh, lw, 2), smooth, 1.5, normal=True),
               "jitter": rng.random((1, 2), np.float32),
               "exposure": np.array([0.8 + 0.02 * t], np.float32),
               "reset": np.array([t in cuts])}


def gain(model, params, h, w, factor, kind, eps=1e-5):
    """The largest change of the history after one jtus step when the history read is
    moved by ``+-eps`` per value (random signs), divided by ``eps``."""
    step = jax.jit(model.step)
    f0, f1 = (Frame(*(jnp.asarray(x[k]) for k in INPUTS))
              for x in feeds(2, h, w, factor, kind, cuts=(0,)))
    _, s0 = step(params, dlctus.State(jnp.zeros((1, h, w, 4), jnp.float32)), f0)
    signs = np.random.default_rng(1).choice([-1.0, 1.0], s0.history.shape)
    moved = dlctus.State(s0.history + jnp.asarray(eps * signs, jnp.float32))
    _, a = step(params, s0, f1)
    _, b = step(params, moved, f1)
    return float(jnp.abs(a.history - b.history).max()) / eps


def _torch_stepper(params, factor):
    """The independent PyTorch DLCTUS (``jtus.reference.torch_dlctus``) with these
    weights: ``step(feed, history NHWC) -> history NHWC``, exposure applied as jtus's
    edge applies it (pre-exposed colour, history in that space)."""
    import torch  # the test extra: an independent reference only

    from jtus.reference import torch_dlctus

    net = torch_dlctus.Net()
    net.load_state_dict(dlctus.params_to_torch(params))
    net.eval()

    def step(feed, hist):
        t = {k: torch.from_numpy(np.ascontiguousarray(feed[k].transpose(0, 3, 1, 2)))
             for k in ("color", "depth", "motion")}
        e = float(feed["exposure"][0])
        with torch.no_grad():
            _, out = torch_dlctus.step(
                net, torch.from_numpy(hist.transpose(0, 3, 1, 2).copy()), t["color"] * e,
                t["depth"], t["motion"], torch.from_numpy(feed["jitter"]), factor,
                reset=torch.from_numpy(feed["reset"]))
        return out.numpy().transpose(0, 2, 3, 1)

    return step


def run(sess, model, params, factor, frames, h, w, kind, torch_too=True):
    """Largest ``|onnx - jtus|`` of the frame and the history, the same for the PyTorch
    reference's history (``torch_too``), and median times."""
    step = jax.jit(model.step)
    torch_step = _torch_stepper(params, factor) if torch_too else None
    hist = np.zeros((1, h, w, 4), np.float32)
    hist_torch = hist
    state = dlctus.State(jnp.asarray(hist))
    worst_frame = worst_hist = worst_torch = 0.0
    t_onnx, t_jtus = [], []
    for feed in feeds(frames, h, w, factor, kind):
        t0 = time.perf_counter()
        got, hist = sess.run(None, {**feed, "history": hist})
        t1 = time.perf_counter()
        want, state = step(params, state, Frame(*(jnp.asarray(feed[k]) for k in INPUTS)))
        want.block_until_ready()
        t2 = time.perf_counter()
        t_onnx.append(t1 - t0)
        t_jtus.append(t2 - t1)
        worst_frame = max(worst_frame, float(np.abs(got - np.asarray(want)).max()))
        worst_hist = max(worst_hist, float(np.abs(hist - np.asarray(state.history)).max()))
        if torch_step is not None:
            hist_torch = torch_step(feed, hist_torch)
            worst_torch = max(worst_torch,
                              float(np.abs(hist_torch - np.asarray(state.history)).max()))
    ms = {"onnx_ms": 1e3 * statistics.median(t_onnx[1:]),
          "jtus_ms": 1e3 * statistics.median(t_jtus[1:])}
    out = {"factor": factor, "frames": frames, "size": [h, w], "input": kind,
           "max_abs_frame": worst_frame, "max_abs_history": worst_hist, **ms,
           "ratio": ms["onnx_ms"] / ms["jtus_ms"]}
    if torch_step is not None:
        out["torch_max_abs_history"] = worst_torch
    return out


def parity(factor, frames, sizes, kinds, weights="shipped"):
    import onnxruntime as ort  # the export extra

    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "dlctus.onnx")
        export.main(["--model", weights, "--factor", str(factor), "--format", "onnx",
                     "--out", path, "--force"])
        sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    model, params = export.load_exportable(weights, factor)[:2]
    rows = []
    for h, w in sizes:
        for kind in kinds:
            r = run(sess, model, params, factor, frames, h, w, kind)
            r["gain"] = gain(model, params, h, w, factor, kind)
            print(r, flush=True)
            rows.append(r)
    return rows


def profile(h, w, factor=4, runs=3, weights="shipped"):
    """onnxruntime's per-operator-type milliseconds per frame and jtus's step time."""
    import onnxruntime as ort  # the export extra

    with tempfile.TemporaryDirectory() as d:
        path = os.path.join(d, "dlctus.onnx")
        export.main(["--model", weights, "--factor", str(factor), "--format", "onnx",
                     "--out", path, "--force"])
        opts = ort.SessionOptions()
        opts.enable_profiling = True
        opts.profile_file_prefix = os.path.join(d, "ort")
        sess = ort.InferenceSession(path, opts, providers=["CPUExecutionProvider"])
        feed = {**next(feeds(1, h, w, factor, "smooth", cuts=())),
                "history": np.full((1, h, w, 4), 0.5, np.float32)}
        sess.run(None, feed)
        t0 = time.perf_counter()
        for _ in range(runs):
            sess.run(None, feed)
        total = (time.perf_counter() - t0) / runs
        with open(sess.end_profiling()) as fh:
            events = json.load(fh)
    per_op = collections.Counter()
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            per_op[e["args"]["op_name"]] += e["dur"] / 1e3 / (runs + 1)
    model, params = export.load_exportable(weights, factor)[:2]
    step = jax.jit(model.step)
    fr = Frame(*(jnp.asarray(feed[k]) for k in INPUTS))
    st = dlctus.State(jnp.asarray(feed["history"]))
    step(params, st, fr)[0].block_until_ready()
    t0 = time.perf_counter()
    for _ in range(runs):
        step(params, st, fr)[0].block_until_ready()
    return per_op, total * 1e3, (time.perf_counter() - t0) / runs * 1e3


def write_profile(h, w):
    per_op, onnx_ms, jtus_ms = profile(h, w)
    rows = per_op.most_common()
    table = ("| operator | ms per frame | share of onnxruntime's frame | x jtus's whole step |\n"
             "| --- | --- | --- | --- |\n" + "\n".join(
                 f"| {op} | {ms:.1f} | {ms / onnx_ms:.0%} | {ms / jtus_ms:.2f} |"
                 for op, ms in rows if ms >= 0.5))
    write("onnx-profile", table, {"size": [h, w], "onnx_ms": onnx_ms, "jtus_ms": jtus_ms,
                                  "per_op_ms": dict(rows)},
          note=(f"The shipped 4x DLCTUS at {h}x{w}, one export run by onnxruntime's CPU "
                f"provider with its profiler on: {onnx_ms:.0f} ms per frame against "
                f"{jtus_ms:.0f} ms for jtus's jitted step on the same inputs (the "
                f"profiler's own overhead included in the first figure). Operators under "
                f"0.5 ms are left out."))


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--sizes", type=int, nargs="+", default=[64, 96, 720, 1280, 1080, 1920],
                   metavar="H W", help="pairs of output height and width")
    p.add_argument("--factors", type=int, nargs="+", default=[4, 2], choices=[2, 4])
    p.add_argument("--inputs", nargs="+", default=["noise", "smooth"],
                   choices=["noise", "smooth"])
    p.add_argument("--profile", type=int, nargs=2, metavar=("H", "W"),
                   help="write onnxruntime's per-operator profile at this size instead")
    args = p.parse_args(argv)
    if args.profile:
        return write_profile(*args.profile)
    if len(args.sizes) % 2 or any(s % 4 for s in args.sizes):
        p.error(f"--sizes: expected pairs of multiples of 4, got {args.sizes}")
    if args.frames < 16:
        p.error(f"--frames: expected at least 16 (the second cut is at frame 15), "
                f"got {args.frames}")
    sizes = list(zip(args.sizes[::2], args.sizes[1::2]))
    rows = [r for f in args.factors for r in parity(f, args.frames, sizes, args.inputs)]
    table = ("| factor | output | input | max abs diff, frame | max abs diff, history | "
             "PyTorch reference: max abs diff, history | gain | onnxruntime ms | jtus ms | "
             "ratio |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n" +
             "\n".join(
                 f"| {r['factor']}x | {r['size'][0]}x{r['size'][1]} | {r['input']} | "
                 f"{r['max_abs_frame']:.2g} | {r['max_abs_history']:.2g} | "
                 f"{r.get('torch_max_abs_history', float('nan')):.2g} | {r['gain']:.1f} | "
                 f"{r['onnx_ms']:.1f} | {r['jtus_ms']:.1f} | {r['ratio']:.2f} |"
                 for r in rows))
    write("onnx-parity", table, rows, note=(
        f"The shipped DLCTUS exported once per factor with `python -m jtus.export "
        f"--format onnx` (the native-operator graph, symbolic sizes) and run by "
        f"onnxruntime's CPU provider at every size, fed its own history over "
        f"{args.frames} frames with cuts at frames 0 and 15 and exposure rising from 0.8 "
        f"by 0.02 a frame; jtus's step in float32 on the same inputs. The PyTorch column: "
        f"the independent PyTorch DLCTUS (`jtus.reference.torch_dlctus`: torch's "
        f"grid_sample, interpolate and Conv2d) with the same weights against jtus on the "
        f"same video, both fed their own history: how far two correct float32 "
        f"implementations drift apart. `gain`: the largest "
        f"change of jtus's history after one step per unit change of the history it "
        f"reads (+-1e-5, random signs). Times are medians of alternating runs."))


if __name__ == "__main__":
    main()
