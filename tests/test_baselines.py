"""JAU and TUS (thesis sec. 2.4) as models."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtus import models, rollout, sampling
from jtus.frame import Frame
from jtus.models import jau, tus
from tests import seqdata


def _frames(T=6, factor=4, **kw):
    frames, targets = seqdata.sequence(T=T, B=2, h=8, w=8, factor=factor, **kw)
    return seqdata.to_jax((frames._replace(reset=None), targets))


def _first(tree):
    return jax.tree_util.tree_map(lambda x: x[0], tree)


@pytest.mark.parametrize("factor", [2, 4])
def test_tus_with_unit_alpha_and_beta_is_jau(factor):
    frames, _ = _frames(factor=factor)
    m = tus.make(tus.Config(factor=factor, alpha=1.0, beta="one"))
    outs, _ = rollout.outputs(m.step, {}, m.init_state(_first(frames)), frames)
    j = jau.make(jau.Config(factor=factor))
    ref, _ = rollout.outputs(j.step, {}, (), frames)
    np.testing.assert_allclose(outs, ref, rtol=0, atol=1e-6)


def _neighbours(lr, xy):
    """Reference: the 3x3 LR samples around each HR pixel's nearest sample, each a
    clamped nearest gather at HR: ``[9,B,H,W,C]``."""
    return jnp.stack([sampling.sample(lr, xy + jnp.asarray([dx, dy], jnp.float32), "nearest")
                      for dy, dx in tus._OFFSETS])


@pytest.mark.parametrize("space", ["rgb", "ycocg"])
@pytest.mark.parametrize("factor", [2, 4])
def test_box_statistics_equal_nine_hr_gathers(factor, space):
    """The LR-computed box equals the 9 clamped HR gathers, with jitters at the
    extremes that put nearest samples outside the image."""
    rng = np.random.default_rng(factor)
    color = jnp.asarray(rng.uniform(size=(4, 5, 7, 3)), jnp.float32)
    jit = jnp.asarray([[-0.5, -0.5], [0.5, 0.5], [0.49, -0.5], [0.13, 0.31]], jnp.float32)
    frame = Frame(color, jnp.zeros((4, 5, 7, 1)), jnp.zeros((4, 5, 7, 2)), jit)
    xy = tus._jau_coords(frame, factor)
    to = sampling.rgb_to_ycocg if space == "ycocg" else (lambda x: x)
    lo, hi, mean = tus._box(to(color), xy, True)
    neigh = np.asarray(_neighbours(to(color), xy))
    np.testing.assert_array_equal(lo, neigh.min(0))
    np.testing.assert_array_equal(hi, neigh.max(0))
    np.testing.assert_allclose(mean, neigh.mean(0), rtol=0, atol=1e-6)


@pytest.mark.parametrize("rectify,space", [("clamp", "rgb"), ("clamp", "ycocg"), ("clip", "rgb"),
                                           ("clip", "ycocg")])
def test_rectified_history_lies_in_the_neighbourhood_box(rectify, space):
    frames, _ = _frames(T=2)
    config = tus.Config(factor=4, rectify=rectify, color_space=space)
    frame = _first(frames)
    rng = np.random.default_rng(0)
    hist = jnp.asarray(rng.uniform(-0.5, 1.5, size=(2, 32, 32, 3)), jnp.float32)
    xy = tus._jau_coords(frame, 4)
    out = np.asarray(tus._rectify(config, hist, frame.color, xy))
    neigh = np.asarray(_neighbours(frame.color, xy))
    if space == "ycocg":
        out = np.asarray(sampling.rgb_to_ycocg(out))
        neigh = np.asarray(sampling.rgb_to_ycocg(neigh))
    assert np.all(out >= neigh.min(0) - 1e-5) and np.all(out <= neigh.max(0) + 1e-5)
    inside = np.asarray(tus._rectify(config, jnp.asarray(neigh.mean(0)) if space == "rgb"
                                     else sampling.ycocg_to_rgb(jnp.asarray(neigh.mean(0))),
                                     frame.color, xy))
    # A history already inside the box is left alone.
    ref = neigh.mean(0) if space == "rgb" else np.asarray(sampling.ycocg_to_rgb(neigh.mean(0)))
    np.testing.assert_allclose(inside, ref, atol=1e-5)


def test_inverse_count_converges_to_the_mean_of_the_jittered_samples():
    """A static scene seen through the 16 thesis jitters: with α = 1/N and no
    rectification the history is the running mean of the scaled inputs."""
    f, T = 4, 16
    rng = np.random.default_rng(0)
    seq = sampling.jitter_sequence("thesis", f)
    color = rng.uniform(size=(T, 1, 6, 6, 3)).astype(np.float32)  # what each jitter sees
    frames = Frame(jnp.asarray(color), jnp.full((T, 1, 6, 6, 1), 0.5), jnp.zeros((T, 1, 6, 6, 2)),
                   jnp.asarray(seq[:, None].astype(np.float32)))
    m = tus.make(tus.Config(factor=f, rectify="none", inverse_count=True, alpha=1e-6,
                            beta="one", warp="bilinear"))
    outs, state = rollout.outputs(m.step, {}, m.init_state(_first(frames)), frames)
    j = jau.make(jau.Config(factor=f))
    scaled, _ = rollout.outputs(j.step, {}, (), frames)
    # thesis sec. 2.4.5: with α = 1/N, eq. 34 is "an average over all samples", each
    # weighing the same (an earlier version counted the first frame twice: 2,1,...,1/17)
    expect = np.asarray(scaled).mean(0)
    np.testing.assert_allclose(outs[-1], expect, atol=1e-5)
    np.testing.assert_allclose(state.history[..., 3], T)


def test_gaussian_filter_and_max_beta():
    frames, _ = _frames(T=3)
    m = tus.make(tus.Config(factor=4, filter="gaussian", beta="max"))
    outs, _ = rollout.outputs(m.step, {}, m.init_state(_first(frames)), frames)
    assert np.all(np.isfinite(outs)) and outs.shape == (3, 2, 32, 32, 3)
    # A constant input stays constant through any filter, rectification and β.
    const = frames._replace(color=jnp.full_like(frames.color, 0.3))
    outs, _ = rollout.outputs(m.step, {}, m.init_state(_first(const)), const)
    np.testing.assert_allclose(outs, 0.3, atol=1e-6)


def test_thesis_presets_and_registry():
    """The thesis's TUS (sec. 5.3.1): α 0.5 at 2x and 1.0 at 4x, clamping, bicubic
    reprojection, no dilation; every registered model is built at the factor asked."""
    assert tus.thesis(2).alpha == 0.5 and tus.thesis(4).alpha == 1.0
    assert tus.thesis(4).rectify == "clamp" and tus.thesis(4).warp == "bicubic"
    assert not tus.thesis(4).dilation
    for f in (2, 4):
        assert tus.thesis(f).factor == f
        for name in models.NAMES:
            assert models.build(name, f).config.factor == f, (name, f)
    with pytest.raises(ValueError, match="model"):
        models.build("nerf", 4)
    with pytest.raises(ValueError, match="rectify"):
        tus.Config(rectify="reject")


@pytest.mark.parametrize("field,bad", [("rectify", "reject"), ("filter", "lanczos"),
                                       ("beta", "two"), ("color_space", "hsv"),
                                       ("warp", "sinc"), ("count", "pixels"), ("alpha", 0.0),
                                       ("alpha", 1.5), ("factor", 0)])
def test_tus_config_names_the_bad_field(field, bad):
    """A bad TUS setting is refused with an error that starts with its field's name
    (anchored: a field name inside a longer word does not match) and says what was
    expected and what it got."""
    with pytest.raises(ValueError, match=rf"^{field}: expected .*, got {re.escape(repr(bad))}$"):
        tus.Config(**{field: bad})


def test_tus_config_accepts_its_boundaries_and_every_choice():
    """Factor 1 (TAA at the render resolution), α = 1 and a tiny α > 0 are valid, as is
    every listed choice of each setting: a check that refuses one of them is wrong."""
    tus.Config(factor=1)
    tus.Config(alpha=1.0)
    tus.Config(alpha=1e-6)
    for field, allowed in (("rectify", tus.RECTIFY), ("filter", tus.FILTERS),
                           ("beta", tus.BETAS), ("color_space", ("rgb", "ycocg")),
                           ("warp", sampling.METHODS), ("count", tus.COUNTS)):
        for value in allowed:
            assert getattr(tus.Config(**{field: value}), field) == value


@pytest.mark.parametrize("name", ["tus", "tus-mean", "kpn", "dlctus"])
def test_a_reset_frame_is_not_reprojected(name):
    """On a reset (first frame, camera cut) the history is the fresh input, whatever
    the state holds and whatever the frame's motion says (that motion points into a
    frame the history never saw). Checked against the same frame with zero motion;
    fails if the fresh history (or TUS's count) is warped (the motion is large) or the
    old one kept."""
    frames, _ = seqdata.sequence(T=1, B=2, h=8, w=8, factor=4, seed=5, max_motion=2.5)
    fr = seqdata.to_jax(jax.tree_util.tree_map(lambda x: x[0], frames))
    fr = fr._replace(reset=jnp.array([True, True]))
    model = models.build(name, 4)
    params = model.init(jax.random.PRNGKey(0)) if name in models.TRAINABLE else {}
    state = model.init_state(fr)
    junk = jax.tree_util.tree_map(lambda x: jnp.full_like(x, 0.77), state)
    still = fr._replace(motion=jnp.zeros_like(fr.motion))
    out_junk, state_junk = model.step(params, junk, fr)
    out_still, state_still = model.step(params, state, still)
    if name == "kpn":  # the motion is also a network input: compare what is reprojected
        from jtus.models import kpn
        _, _, rep = kpn.prepare(junk, fr, model.config)
        _, _, rep_still = kpn.prepare(state, still, model.config)
        np.testing.assert_allclose(np.asarray(rep), np.asarray(rep_still), atol=1e-6)
    else:
        np.testing.assert_allclose(np.asarray(out_junk), np.asarray(out_still), atol=1e-6)
        # and so is what the step hands on (TUS: the count N too, which a reset frame's
        # output does not show: its history is its own scaled input)
        for a, b in zip(jax.tree_util.tree_leaves(state_junk),
                        jax.tree_util.tree_leaves(state_still)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-6)
    assert float(jnp.abs(fr.motion).max()) > 1.0


def test_counting_samples_gives_each_pixel_the_mean_of_its_samples():
    """``count="samples"``: on a still scene an HR pixel's value is the mean, over
    the frames whose sample landed in it, of that frame's scaled input there (the
    jitter-aligned bilinear input, JAU's output), computed here directly."""
    f, T = 2, 12
    rng = np.random.default_rng(3)
    img = rng.uniform(size=(1, 4, 4, 3)).astype(np.float32)
    seq = sampling.jitter_sequence("halton8", f)
    jit = np.stack([seq[t % len(seq)] for t in range(T)]).astype(np.float32)[:, None]
    noise = rng.normal(0, 0.05, size=(T, 1, 4, 4, 3)).astype(np.float32)
    color = img[None] + noise  # the "samples" differ per frame
    frames = Frame(jnp.asarray(color), jnp.full((T, 1, 4, 4, 1), 0.5), jnp.zeros((T, 1, 4, 4, 2)),
                   jnp.asarray(jit), jnp.asarray(np.arange(T)[:, None] == 0))
    model = models.build("tus-mean", f)
    state = model.init_state(jax.tree_util.tree_map(lambda x: x[0], frames))
    outs, _ = rollout.outputs(model.step, {}, state, frames)
    j = models.build("jau", f)
    scaled, _ = rollout.outputs(j.step, {}, j.init_state(jax.tree_util.tree_map(
        lambda x: x[0], frames)), frames)
    scaled = np.asarray(scaled)
    # HR pixel (2i + cy, 2j + cx) receives LR sample (i, j) on the frames whose jitter
    # falls in cell (cx, cy)
    cells = np.floor(jit[:, 0] * f).astype(int)
    for cy in range(f):
        for cx in range(f):
            hits = np.nonzero((cells[:, 0] == cx) & (cells[:, 1] == cy))[0]
            if len(hits) == 0:
                continue
            want = scaled[hits, 0, cy::f, cx::f].mean(0)
            got = np.asarray(outs[-1, 0, cy::f, cx::f])
            np.testing.assert_allclose(got, want, atol=1e-5)
