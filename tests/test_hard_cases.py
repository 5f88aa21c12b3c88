"""Hard cases: a static hold under every supported jitter sequence.

On a hold, a temporal up-sampler that accumulates must settle: whatever it shows once
the jitter cycle has been seen is its steady state, and a still image must not
flicker. The classical running-mean TUS (``tus-mean``) is the control here; the
shipped DLCTUS's version of this test belongs with its training (docs/weights.md).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtus import metrics, models, rollout, sim
from jtus.sampling.jitter import VARIETY
from jtus.sim.video import VideoRenderer, static_hold

T = 384


@pytest.fixture(scope="module")
def holds():
    scene = sim.get_scene("textures")  # texture detail, camera still
    r = VideoRenderer(scene, (128, 128), (4, 2), 16)  # one compilation for all holds
    return {(f, j): static_hold(scene, 128, f, j, T, renderer=r) for f in (4, 2)
            for j in VARIETY}


@functools.lru_cache(maxsize=None)
def _rollout(name, factor):
    """The model and its jitted rollout, compiled once per model and factor: every
    jitter's hold has the same shapes."""
    model = models.build(name, factor)
    return model, jax.jit(lambda s, f: rollout.outputs(model.step, {}, s, f))


def _psnr_curve(name, factor, frames, targets):
    model, run = _rollout(name, factor)
    fr = jax.tree_util.tree_map(jnp.asarray, frames)
    state = model.init_state(jax.tree_util.tree_map(lambda x: x[0], fr))
    outs, _ = run(state, fr)
    return np.asarray(jax.vmap(metrics.psnr)(outs, jnp.asarray(targets)))[:, 0]


@pytest.mark.parametrize("factor", [4, 2])
@pytest.mark.parametrize("jitter", VARIETY)
def test_running_mean_tus_settles_on_a_hold(holds, factor, jitter):
    """PSNR rises by more than 1.5 dB over the first frame's, and over the last 32 of
    384 frames stays within a 0.15 dB band (measured: at most 0.113 dB, 4x FSR 2,
    whose 128-frame cycle has then been seen three times; 0.000 for the thesis's 4x4
    pattern, whose samples land on HR pixel centres; `python experiments/hard_cases.py`).
    A tighter form, within 0.1 dB of the best, does not hold at 2x: there the best
    is an early peak 0.2-1.3 dB above the converged value (docs/simulator.md)."""
    p = _psnr_curve("tus-mean", factor, *holds[factor, jitter])
    assert np.all(np.isfinite(p))
    assert p[-32:].mean() > p[0] + 1.5
    assert np.ptp(p[-32:]) < 0.15, np.ptp(p[-32:])


def test_thesis_tus_keeps_swinging_on_a_hold(holds):
    """The control can fail: the thesis's TUS (α = 1 at 4x, clamped history) replaces
    each HR pixel by its newest sample and clamps the rest to the current samples'
    box, so its PSNR keeps moving with the jitter cycle (measured 0.58 dB over the
    last 32 frames with Halton(2,3) x32 at 4x)."""
    p = _psnr_curve("tus", 4, *holds[4, "halton32"])
    assert np.ptp(p[-32:]) > 0.2
