"""JAU and TUS (thesis sec. 2.4) as models."""

import dataclasses
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


@pytest.mark.parametrize("factor", [2, 4])
def test_tus_with_unit_alpha_and_beta_is_jau(factor):
    frames, _ = _frames(factor=factor)
    m = tus.make(tus.Config(factor=factor, alpha=1.0, beta="one"))
    outs, _ = rollout.outputs(m.step, {}, m.init_state(seqdata.first(frames)), frames)
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
    xy = sampling.jitter_aligned_coords(jit, 4, 5, 7, factor)
    to = sampling.rgb_to_ycocg if space == "ycocg" else (lambda x: x)
    lo, hi, mean = sampling.neighbourhood_box(to(color), xy, True)
    neigh = np.asarray(_neighbours(to(color), xy))
    np.testing.assert_array_equal(lo, neigh.min(0))
    np.testing.assert_array_equal(hi, neigh.max(0))
    np.testing.assert_allclose(mean, neigh.mean(0), rtol=0, atol=1e-6)


@pytest.mark.parametrize("rectify,space", [("clamp", "rgb"), ("clamp", "ycocg"), ("clip", "rgb"),
                                           ("clip", "ycocg")])
def test_rectified_history_lies_in_the_neighbourhood_box(rectify, space):
    frames, _ = _frames(T=2)
    config = tus.Config(factor=4, rectify=rectify, color_space=space)
    frame = seqdata.first(frames)
    rng = np.random.default_rng(0)
    hist = jnp.asarray(rng.uniform(-0.5, 1.5, size=(2, 32, 32, 3)), jnp.float32)
    xy = sampling.jitter_aligned_coords(frame.jitter, 2, 8, 8, 4)
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
    outs, state = rollout.outputs(m.step, {}, m.init_state(seqdata.first(frames)), frames)
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
    outs, _ = rollout.outputs(m.step, {}, m.init_state(seqdata.first(frames)), frames)
    assert np.all(np.isfinite(outs)) and outs.shape == (3, 2, 32, 32, 3)
    # A constant input stays constant through any filter, rectification and β.
    const = frames._replace(color=jnp.full_like(frames.color, 0.3))
    outs, _ = rollout.outputs(m.step, {}, m.init_state(seqdata.first(const)), const)
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
    color = np.maximum(img[None] + noise, 0.0)  # the "samples" differ per frame (>= 0)
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


def _tus_golden(filter_, beta_name, f=2, jitter=(0.3, 0.7), alpha=0.6, sigma=0.47):
    """TUS's blend (thesis eq. 39) against eq. 38 and 40-42 written out per output
    pixel in numpy: a random LR frame, zero motion, a constant history of 0.5, no
    rectification, so ``out = αβ s̄ + (1 - αβ) 0.5``. LR sample ``j`` sits at HR
    position ``f (j + jitter)`` (docs/conventions.md). N(p), the thesis's "fixed
    neighbourhood around p", is the 3x3 LR samples around p's nearest sample (jtus's
    choice). Interior pixels only (no edge clamping)."""
    from jtus.frame import Frame
    from jtus.models import tus

    rng = np.random.default_rng(3)
    h = w = 6
    color = rng.uniform(size=(1, h, w, 3)).astype(np.float32)
    frame = Frame(jnp.asarray(color), jnp.full((1, h, w, 1), 0.5, jnp.float32),
                  jnp.zeros((1, h, w, 2), jnp.float32), jnp.asarray([jitter], jnp.float32),
                  jnp.zeros((1,), bool))
    config = tus.Config(factor=f, filter=filter_, beta=beta_name, rectify="none",
                        alpha=alpha, sigma=sigma)
    # N = 0.5 in the history: α = max(1/N, α) would differ from the constant α asked
    state = tus.State(jnp.concatenate([jnp.full((1, h * f, w * f, 3), 0.5),
                                       jnp.full((1, h * f, w * f, 1), 0.5)], -1))
    out = np.asarray(tus.make(config).step({}, state, frame)[0])[0]
    jx, jy = jitter
    checked = 0
    for y in range(f, (h - 1) * f):
        for x in range(f, (w - 1) * f):
            px, py = x + 0.5, y + 0.5  # HR pixel centre
            nx, ny = round(px / f - jx), round(py / f - jy)  # nearest sample
            if not (1 <= nx <= w - 2 and 1 <= ny <= h - 2):
                continue
            num, den, bmax, box = np.zeros(3), 0.0, 0.0, 0.0
            for b in (ny - 1, ny, ny + 1):
                for a in (nx - 1, nx, nx + 1):
                    dx, dy = px - f * (a + jx), py - f * (b + jy)  # HR pixels
                    if filter_ == "tent":  # eq. 40, one LR pixel (f HR pixels) wide
                        wgt = max(0.0, 1 - abs(dx) / f) * max(0.0, 1 - abs(dy) / f)
                    else:  # eq. 41
                        wgt = np.exp(-(dx * dx + dy * dy) / (2 * sigma ** 2))
                    num += wgt * color[0, b, a]
                    den += wgt
                    bmax = max(bmax, wgt)  # eq. 42
                    # Yang et al.'s box: 1 when the sample lies in this output pixel
                    box = max(box, float(x <= f * (a + jx) < x + 1 and y <= f * (b + jy) < y + 1))
            s = num / den  # eq. 38
            beta = {"max": bmax, "box": box}[beta_name]
            want = alpha * beta * s + (1 - alpha * beta) * 0.5  # eq. 39
            np.testing.assert_allclose(out[y, x], want, rtol=0, atol=2e-6, err_msg=(y, x))
            checked += 1
    return checked


def test_tus_gaussian_filter_and_max_beta_follow_eq_38_41_42():
    """Catches: β forced to 1, or the mean weight instead of the largest."""
    assert _tus_golden("gaussian", "max") > 50


def test_tus_tent_filter_and_max_beta_follow_eq_38_40_42():
    """Catches: the tent's β (its largest weight, eq. 42) taken at the wrong distance,
    over the wrong axis, or saturated at 1."""
    assert _tus_golden("tent", "max", f=4, jitter=(0.2, 0.85)) > 50


def test_tus_tent_filter_and_box_beta_follow_eq_38_40():
    """Catches: β forced to 1, or the box β on the wrong pixel."""
    assert _tus_golden("tent", "box", f=4, jitter=(0.6, 0.1)) > 50


def test_tus_dilation_reprojects_with_the_dilated_motion():
    """TUS with ``dilation=True`` equals TUS fed the dilated motion (replaces a test
    that asserted the field it had just set). Catches: the option ignored."""
    from jtus.models import tus

    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, max_motion=2.0))
    frame = seqdata.at(frames, 1)
    base = tus.thesis(4)
    state = tus.init_state(seqdata.at(frames, 0), base)
    state = tus.State(state.history + jnp.asarray(
        np.random.default_rng(9).uniform(-0.2, 0.2, size=state.history.shape), jnp.float32))
    got, _ = tus.step({}, state, frame, dataclasses.replace(base, dilation=True))
    dilated = frame._replace(motion=sampling.dilate_motion(frame.motion, frame.depth))
    want, _ = tus.step({}, state, dilated, base)
    plain, _ = tus.step({}, state, frame, base)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    assert float(jnp.abs(plain - want).max()) > 1e-3  # control


def test_tus_reads_its_history_with_its_own_warp():
    """TUS reads its history's colour and its count N with the warp it is configured
    with (method and Keys parameter), where the motion lands inside the previous frame,
    and the scaled input (N = 0) outside it; with β = 1 and α = max(1/N, α₀) the output
    is α s + (1 - α) h and N grows by one (eq. 39). The reference composes jtus's warp
    (checked against PyTorch's ``grid_sample``) and its up-sampling. Catches: either
    read falling back to ``sample``'s default method or Keys parameter; α's floor
    ignored."""
    from jtus.models import tus

    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=1, h=6, w=5, max_motion=1.5))
    frame = seqdata.at(frames, 1)
    f = 4
    rng = np.random.default_rng(11)
    hist = rng.uniform(size=(1, 6 * f, 5 * f, 4)).astype(np.float32)
    hist[..., 3] = rng.uniform(1.0, 6.0, size=hist.shape[:3])  # N, read by its own warp
    pos = sampling.reproject_coords(frame.motion, f)
    s = sampling.jitter_aligned_upsample(frame.color, frame.jitter, f)  # the tent, eq. 40
    outs = {}
    for warp, a in (("bicubic", -0.75), ("bicubic", -0.5), ("bilinear", -0.75)):
        config = tus.Config(factor=f, warp=warp, warp_a=a, rectify="none", beta="one",
                            inverse_count=True, alpha=0.3)  # the floor binds where N > 3.3
        out, state = tus.make(config).step({}, tus.State(jnp.asarray(hist)), frame)
        rep, inside = sampling.sample(jnp.asarray(hist), pos, warp, a=a, return_mask=True)
        h = jnp.where(inside, rep[..., :3], s)
        n = jnp.where(inside, rep[..., 3:], 0.0) + 1.0
        alpha = jnp.clip(1.0 / n, 0.3, 1.0)
        assert 0 < float((1.0 / n < 0.3).mean()) < 1
        # float32; 0 measured for both (the same ops in another order could round)
        np.testing.assert_allclose(state.history[..., 3:], n, rtol=0, atol=1e-6)
        np.testing.assert_allclose(out, alpha * s + (1 - alpha) * h, rtol=0, atol=1e-6)
        assert 0 < float(inside.mean()) < 1  # both sides of the image's edge are read
        outs[warp, a] = np.asarray(out)
    # control: the three warps give different outputs on this history
    assert np.abs(outs["bicubic", -0.75] - outs["bicubic", -0.5]).max() > 1e-3
    assert np.abs(outs["bicubic", -0.75] - outs["bilinear", -0.75]).max() > 1e-3


def test_tus_counts_frames_or_samples_and_bounds_alpha_by_one():
    """N counts every frame (``count="frames"``: +1 whatever β) or the samples a pixel
    received (``"samples"``: +β); α = 1/N is clipped to [α₀, 1], so a pixel whose N is
    below 1 (a first sample with β < 1, the tent's largest weight, eq. 42) takes
    α = 1: out = β s + (1 - β) h. Catches: frames counted as β, the upper bound of α
    dropped (αβ = 1 there)."""
    from jtus.models import tus

    frames, _ = seqdata.to_jax(seqdata.sequence(T=1, B=1, h=6, w=5, max_motion=0.0))
    frame = seqdata.at(frames, 0)._replace(reset=jnp.zeros((1,), bool))
    f = 4
    hist = jnp.concatenate([jnp.full((1, 6 * f, 5 * f, 3), 0.5),
                            jnp.zeros((1, 6 * f, 5 * f, 1))], -1)  # 0.5, no sample yet
    s = sampling.jitter_aligned_upsample(frame.color, frame.jitter, f)
    xy = seqdata.jau_positions(np.asarray(frame.jitter), 6, 5, f) - 0.5
    tent = np.prod(1 - np.abs(xy - np.round(xy)), -1)[..., None]  # eq. 40 at the nearest
    m = tus.make(tus.Config(factor=f, rectify="none", inverse_count=True, alpha=0.01,
                            count="samples", beta="max"))
    out, state = m.step({}, tus.State(hist), frame)
    np.testing.assert_allclose(state.history[..., 3:], tent, rtol=0, atol=1e-6)
    assert float(tent.min()) < 0.5  # N < 1 somewhere
    np.testing.assert_allclose(out, tent * s + (1 - tent) * 0.5, rtol=0, atol=1e-6)
    m = tus.make(tus.Config(factor=f, rectify="none", inverse_count=True, alpha=0.01,
                            count="frames", beta="box"))
    out, state = m.step({}, tus.State(hist), frame)
    np.testing.assert_array_equal(state.history[..., 3], 1.0)


@pytest.mark.parametrize("space,flat", [("rgb", False), ("ycocg", False), ("rgb", True)])
def test_tus_clamp_and_clip_rectify_by_their_definitions(space, flat):
    """Rectification against the box of the 3x3 LR samples around each HR pixel's
    nearest sample (clamped to the image), in RGB or YCoCg, written out per pixel in
    numpy: ``clamp`` clips each channel to [min, max]; ``clip`` moves the history
    along the segment from the samples' mean to it until it is inside the box. Read
    where β = 0 (the box β: no sample in the pixel), so the output is the rectified
    history. ``flat``: green is 0.25 in every sample and in the history (a flat-shaded
    surface), so v = 0 there: that channel sets no bound on the clip. Catches: the two
    swapped, the box taken at the wrong pixel, a channel with v = 0 taken as a face of
    the box (the history then snapped to the mean)."""
    from jtus.models import tus

    frames, _ = seqdata.to_jax(seqdata.sequence(T=1, B=1, h=6, w=5, max_motion=0.0))
    frame = seqdata.at(frames, 0)._replace(reset=jnp.zeros((1,), bool))
    f, h, w = 4, 6, 5
    rng = np.random.default_rng(7)
    hist = rng.uniform(-0.5, 1.5, size=(1, h * f, w * f, 3))
    if flat:
        frame = frame._replace(color=frame.color.at[..., 1].set(0.25))
        hist[..., 1] = 0.25
    state = tus.State(jnp.asarray(np.concatenate([hist, np.full(hist.shape[:3] + (1,), 3.0)],
                                                 -1), jnp.float32))
    ycocg = np.asarray([[0.25, 0.5, 0.25], [0.5, 0.0, -0.5], [-0.25, 0.5, -0.25]])
    to = (lambda x: x @ ycocg.T) if space == "ycocg" else (lambda x: x)
    back = (lambda x: x @ np.linalg.inv(ycocg).T) if space == "ycocg" else (lambda x: x)
    color = to(np.asarray(frame.color, np.float64)[0])
    jx, jy = np.asarray(frame.jitter, np.float64)[0]
    outs = {}
    for rectify in ("clamp", "clip"):
        m = tus.make(tus.Config(factor=f, rectify=rectify, color_space=space, alpha=0.5,
                                warp="bilinear"))
        outs[rectify] = np.asarray(m.step({}, state, frame)[0])[0]
    checked = 0
    for y in range(h * f):
        for x in range(w * f):
            nx = int(np.floor((x + 0.5) / f - jx + 0.5))  # the nearest sample
            ny = int(np.floor((y + 0.5) / f - jy + 0.5))
            if any(x <= f * (a + jx) < x + 1 and y <= f * (b + jy) < y + 1
                   for a in range(w) for b in range(h)):
                continue  # a sample in this pixel: β = 1
            taps = np.stack([color[min(max(b, 0), h - 1), min(max(a, 0), w - 1)]
                             for b in (ny - 1, ny, ny + 1) for a in (nx - 1, nx, nx + 1)])
            lo, hi, mean = taps.min(0), taps.max(0), taps.mean(0)
            hv = to(hist[0, y, x])
            want = {"clamp": np.clip(hv, lo, hi)}
            v = hv - mean
            t = min([(hi[c] - mean[c]) / v[c] if v[c] > 0 else (lo[c] - mean[c]) / v[c]
                     for c in range(3) if v[c] != 0] + [np.inf])
            want["clip"] = mean + min(max(t, 0.0), 1.0) * v
            for rectify in ("clamp", "clip"):
                np.testing.assert_allclose(outs[rectify][y, x], back(want[rectify]), rtol=0,
                                           atol=2e-6, err_msg=(rectify, y, x))
            checked += 1
    assert checked > 300
    assert np.abs(outs["clamp"] - outs["clip"]).max() > 0.05  # control: they differ
