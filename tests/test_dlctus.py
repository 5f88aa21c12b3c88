"""DLCTUS as the thesis defines it (sec. 4.1), checked stage by stage: the history a
reset starts from, the accumulation buffer switched off, motion dilation, the warp and
Keys parameter its history is read with, float64 carried through every stage."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtus import sampling
from jtus.models import dlctus
from tests import seqdata


def _dlctus_hist(config, frame, history):
    pre = dlctus.prepare_frame(frame, config)
    return dlctus.reproject(dlctus.State(history), pre, config)[2]


def test_dlctus_reset_history_is_the_jitter_aligned_input():
    """A reset frame's history is its own jitter-aligned bilinear input with
    accumulation 1 (thesis sec. 4.2: the first frame), whatever the state held.
    Catches: a reset writing zeros, or keeping the reprojected history (the comparison
    with a "fresh" rollout in test_rollout cannot: both sides run the reset code)."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, reset_at=(1, 0)))
    config = dlctus.Config(factor=4)
    frame = seqdata.at(frames, 1)
    garbage = dlctus.State(jnp.asarray(np.random.default_rng(1).uniform(size=(2, 32, 32, 4)),
                                       jnp.float32))
    _, _, hist = dlctus.reproject(garbage, dlctus.prepare_frame(frame, config), config)
    ones = jnp.ones(frame.color.shape[:-1] + (1,))
    want = sampling.jitter_aligned_upsample(jnp.concatenate([frame.color, ones], -1),
                                            frame.jitter, 4, "bilinear")
    np.testing.assert_allclose(hist[0], want[0], rtol=0, atol=1e-6)  # reset element
    assert float(jnp.abs(hist[1] - want[1]).max()) > 0.05  # control: element 1 reprojects


def test_dlctus_without_accumulation_reads_a_count_of_one():
    """``accumulation=False`` (the thesis's ablation, Table 16): the reprojected
    history's fourth channel is 1 everywhere, whatever the buffer held. Catches: the
    option ignored."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2))
    frame = seqdata.at(frames, 1)
    rng = np.random.default_rng(4)
    history = jnp.asarray(rng.uniform(0.1, 0.9, size=(2, 32, 32, 4)), jnp.float32)
    off = _dlctus_hist(dlctus.Config(factor=4, accumulation=False), frame, history)
    on = _dlctus_hist(dlctus.Config(factor=4), frame, history)
    # bicubic weights of a constant 1 sum to 1 within float32 rounding (measured 1.1e-6)
    np.testing.assert_allclose(off[..., 3], 1.0, rtol=0, atol=2.5e-6)
    np.testing.assert_allclose(off[..., :3], on[..., :3], rtol=0, atol=1e-6)
    assert float(jnp.abs(on[..., 3] - 1.0).max()) > 0.1  # control: the buffer's count


def test_dlctus_dilation_reprojects_with_the_dilated_motion():
    """``dilation=True`` reads the history at the motion of the nearest depth in each
    3x3 neighbourhood (``sampling.dilate_motion``, tested on its own): the model's read
    equals the undilated model's fed the dilated motion. Catches: the option ignored,
    or dilated motion computed and not used."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, max_motion=2.0))
    frame = seqdata.at(frames, 1)
    history = jnp.asarray(np.random.default_rng(6).uniform(size=(2, 32, 32, 4)), jnp.float32)
    got = _dlctus_hist(dlctus.Config(factor=4, dilation=True), frame, history)
    dilated = frame._replace(motion=sampling.dilate_motion(frame.motion, frame.depth))
    want = _dlctus_hist(dlctus.Config(factor=4), dilated, history)
    plain = _dlctus_hist(dlctus.Config(factor=4), frame, history)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    assert float(jnp.abs(plain - want).max()) > 1e-3  # control: dilation changes the read


@pytest.mark.parametrize("warp", ["bicubic", "bicubic9", "bicubic5"])
def test_dlctus_reads_its_history_with_its_warp_and_keys_a(x64, warp):
    """The history is read at ``P + f * mv`` with the configured warp and Keys ``a``
    (thesis sec. 5.5.1; a=-0.5 is the thesis's Bicubic5 before its change), the
    jitter-aligned input where that falls outside: against ``sampling.sample`` (checked
    against PyTorch's grid_sample); for ``bicubic`` at that position summed in float64,
    since DLCTUS keeps the pixel and its displacement apart there
    (``sampling.reproject_plan``; the 9- and 5-fetch reads take the float32 sum). Catches:
    ``warp_a`` dropped on the way to the plan or the read (PyTorch's -0.75 then)."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, max_motion=2.0))
    frame = seqdata.at(frames, 1)
    history = jnp.asarray(np.random.default_rng(8).uniform(size=(2, 32, 32, 4)), jnp.float32)
    config = dlctus.Config(factor=4, warp=warp, warp_a=-0.5)
    got = _dlctus_hist(config, frame, history)
    d = 4 * sampling.upsample(frame.motion, 4)   # float32, as the model computes it
    xy = (sampling.pixel_grid(2, 32, 32, jnp.float64) + d.astype(jnp.float64)
          if warp == "bicubic" else sampling.reproject_coords(frame.motion, 4))
    read, inside = sampling.sample(history, xy, warp, a=-0.5, return_mask=True)
    jau = sampling.jitter_aligned_upsample(
        jnp.concatenate([frame.color, jnp.ones_like(frame.depth)], -1), frame.jitter, 4)
    np.testing.assert_allclose(got, jnp.where(inside, read, jau), rtol=0, atol=1e-6)
    assert not bool(inside.all())  # the motion reaches outside somewhere
    other = _dlctus_hist(dlctus.Config(factor=4, warp=warp), frame, history)
    assert float(jnp.abs(other - got).max()) > 1e-3  # control: a=-0.75 reads otherwise


def test_dlctus_float64_carries_float64_through_every_stage(x64):
    """``dtype="float64"`` (references, gradient checks) prepares, reads, constructs and
    carries in float64, as the module says: every floating array of the prepared frame,
    the output and the state. Catches: the frame cast to the default dtype, or the warp
    plan's weights made in float32, which would leave float32 rounding (1e-7) in checks
    meant to reach 1e-12."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, dtype=np.float64))
    config = dlctus.Config(factor=4, dtype="float64")
    model = dlctus.make(config)
    params = jax.tree_util.tree_map(lambda x: x.astype(jnp.float64),
                                    model.init(jax.random.PRNGKey(0)))
    frame = seqdata.at(frames, 1)
    pre = dlctus.prepare_frame(frame, config)
    out, state = dlctus.advance(params, model.init_state(seqdata.first(frames)), pre, config)
    leaves = [x for x in jax.tree_util.tree_leaves((pre, out, state))
              if jnp.issubdtype(x.dtype, jnp.floating)]
    assert len(leaves) >= 6 and {x.dtype for x in leaves} == {jnp.dtype(jnp.float64)}
    f32 = dlctus.prepare_frame(frame, dlctus.Config(factor=4))  # control: float32 there
    assert f32.jau.dtype == jnp.float32
