"""ONNX parity: the exported DLCTUS step run by onnxruntime against jtus over 30 frames
(64x96 output, random inputs, motion up to a few LR pixels, cuts at frames 0 and 15,
a varying exposure), the exported model feeding its own history back.

    python experiments/onnx_parity.py
"""
import os
import tempfile

import jax
import jax.numpy as jnp
import numpy as np
import onnxruntime as ort

from jtus import export
from jtus.frame import Frame
from jtus.models import dlctus
d = tempfile.mkdtemp(); out = os.path.join(d, "x.onnx")
for f in (4, 2):
    export.main(["--model", "shipped", "--factor", str(f), "--format", "onnx", "--size", "64", "96", "--out", out, "--force"])
    sess = ort.InferenceSession(out, providers=["CPUExecutionProvider"])
    model, params = export.load_dlctus("shipped", f)
    ref = jax.jit(model.step); rng = np.random.default_rng(7); h, w = 64 // f, 96 // f
    hist = np.zeros((1, 64, 96, 4), np.float32); state = dlctus.State(jnp.asarray(hist)); worst = 0
    for t in range(30):
        feed = {"color": rng.random((1, h, w, 3), np.float32), "depth": rng.random((1, h, w, 1), np.float32),
                "motion": (1.5 * rng.standard_normal((1, h, w, 2))).astype(np.float32), "jitter": rng.random((1, 2), np.float32),
                "exposure": np.array([0.8 + 0.02 * t], np.float32), "reset": np.array([t in (0, 15)]), "history": hist}
        got, hist = sess.run(None, feed)
        want, state = ref(params, state, Frame(*(jnp.asarray(feed[k]) for k in ("color", "depth", "motion", "jitter", "reset", "exposure"))))
        worst = max(worst, float(np.abs(got - np.asarray(want)).max()), float(np.abs(hist - np.asarray(state.history)).max()))
    print(f"x{f} 64x96 30 frames: max |onnx - jtus| = {worst:.3g}")
