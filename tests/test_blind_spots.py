"""Checks for implementation bugs that the rest of the suite let through (issue 18's
audit): each test names the deliberate bug it catches, and was run against it."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jtus import losses, rollout, sampling, train
from jtus.models import dlctus, nsrr
from tests import seqdata


def _first(tree):
    return jax.tree_util.tree_map(lambda x: x[0], tree)


def _at(tree, t):
    return jax.tree_util.tree_map(lambda x: x[t], tree)


def _cast_frame(frame, dtype):
    """``frame`` with its colour, depth, motion and jitter in ``dtype``."""
    return frame._replace(**{k: jnp.asarray(getattr(frame, k), dtype)
                             for k in ("color", "depth", "motion", "jitter")})


def test_dlctus_reset_history_is_the_jitter_aligned_input():
    """A reset frame's history is its own jitter-aligned bilinear input with
    accumulation 1 (thesis sec. 4.2: the first frame), whatever the state held.
    Catches: a reset writing zeros, or keeping the reprojected history (the comparison
    with a "fresh" rollout in test_rollout cannot: both sides run the reset code)."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, reset_at=(1, 0)))
    config = dlctus.Config(factor=4)
    frame = _at(frames, 1)
    garbage = dlctus.State(jnp.asarray(np.random.default_rng(1).uniform(size=(2, 32, 32, 4)),
                                       jnp.float32))
    _, _, hist = dlctus.prepare(garbage, frame, config)
    ones = jnp.ones(frame.color.shape[:-1] + (1,))
    want = sampling.jitter_aligned_upsample(jnp.concatenate([frame.color, ones], -1),
                                            frame.jitter, 4, "bilinear")
    np.testing.assert_allclose(hist[0], want[0], rtol=0, atol=1e-6)  # reset element
    assert float(jnp.abs(hist[1] - want[1]).max()) > 0.05  # control: element 1 reprojects


def test_nsrr_reset_forgets_the_previous_features():
    """NSRR on a reset frame runs as if its previous-frame features were zero (its
    state at a sequence start). Catches: the reset flag ignored (garbage features
    reweighted into the output)."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, reset_at=(1, 0)))
    model = nsrr.make(nsrr.Config(factor=4, fast=True))
    params = model.init(jax.random.PRNGKey(0))
    frame = _at(frames, 1)
    zero = model.init_state(frame)
    garbage = nsrr.State(jnp.asarray(np.random.default_rng(2).uniform(
        size=zero.previous.shape), jnp.float32))
    out_zero, _ = model.step(params, zero, frame)
    out_garbage, _ = model.step(params, garbage, frame)
    np.testing.assert_allclose(out_garbage[0], out_zero[0], rtol=0, atol=1e-6)
    assert float(jnp.abs(out_garbage[1] - out_zero[1]).max()) > 1e-4  # control


def test_real_train_step_hands_on_the_carry_after_k1_frames():
    """TBPTT in the training step ``train`` runs (``make_train_step`` with
    ``keep_at``): the carry it returns, which starts the next window, is the state
    after k1 frames of this window, computed with the parameters before the update.
    Catches: the step handing on the carry after the whole window (``last`` for
    ``kept``), which the rollout-level chaining test does not run."""
    frames, targets = seqdata.to_jax(seqdata.sequence(T=4, B=2))
    model = dlctus.make(dlctus.Config(factor=4))
    params = model.init(jax.random.PRNGKey(0))
    opt = optax.adam(1e-2)
    step = train.make_train_step(model, losses.make("l1", 4), opt, loss_frames=2, keep_at=2)
    carry = rollout.start(model.init_state(_first(frames)), targets[0])
    ts = train.create_train_state(jax.tree_util.tree_map(jnp.copy, params), opt)
    _, nxt, _ = step(ts, carry, frames, targets)
    head = jax.tree_util.tree_map(lambda x: x[:2], frames)
    outs, state2 = rollout.outputs(model.step, params, model.init_state(_first(frames)), head)
    np.testing.assert_allclose(nxt.state.history, state2.history, rtol=0, atol=1e-5)
    np.testing.assert_allclose(nxt.prev_out, outs[1], rtol=0, atol=1e-5)
    np.testing.assert_array_equal(nxt.prev_target, targets[1])
    assert bool(nxt.has_prev)
    _, state4 = rollout.outputs(model.step, params, model.init_state(_first(frames)), frames)
    assert float(jnp.abs(state4.history - state2.history).max()) > 1e-3  # control


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


def _shifted_previous_errors(f=4, shift=1, seed=5):
    """Current and previous outputs/targets and a frame whose LR motion is ``shift``
    LR pixels to the right everywhere: the previous value under HR pixel (y, x) is at
    (y, x + f*shift), inside the image only for x + f*shift < W (docs/conventions.md)."""
    from jtus.frame import Frame

    rng = np.random.default_rng(seed)
    B, H, W = 2, 16, 20
    out, target, prev_out, prev_target = (rng.uniform(size=(B, H, W, 3)) for _ in range(4))
    h, w = H // f, W // f
    motion = np.zeros((B, h, w, 2))
    motion[..., 0] = shift
    frame = Frame(jnp.zeros((B, h, w, 3)), jnp.full((B, h, w, 1), 0.5), jnp.asarray(motion),
                  jnp.full((B, 2), 0.5), None)
    x = out - target
    y = np.zeros_like(x)
    s = f * shift
    y[:, :, :W - s] = (prev_out - prev_target)[:, :, s:]  # f_prev, eq. 48
    args = tuple(jnp.asarray(a) for a in (out, target, prev_out, prev_target))
    return args, frame, x, y


def test_st_and_st_linear_follow_thesis_eq_48_to_55(x64):
    """L_st (eq. 51-52, and equal to eq. 48-49 divided by 1 + θ̂ with θ = θ̂/(1+θ̂))
    and L_st-linear (eq. 54-55), each the mean over pixels and channels of its
    per-element form, written here from the thesis, not from losses.py. Catches: a
    sign or factor of θ, the temporal term read at the wrong pixel or without the
    out-of-image mask, y not zeroed without a previous frame."""
    args, frame, x, y = _shifted_previous_errors()
    for theta in (0.0, 0.3, 0.5, 0.9):
        st = np.mean(x * x + y * y - 2 * theta * x * y)  # eq. 52
        th_hat = theta / (1 - theta)  # eq. 50's substitution, inverted
        st_hat = np.mean(x * x + y * y + th_hat * (x - y) ** 2)  # eq. 49
        np.testing.assert_allclose(st, st_hat / (1 + th_hat), rtol=1e-12)
        lin = np.mean(np.abs(x) + np.abs(y) + theta * (np.abs(x - y) - np.abs(x) - np.abs(y)))
        got_st = float(losses.make("st", 4, theta=theta)(*args, jnp.asarray(True), frame))
        got_lin = float(losses.make("st-linear", 4, theta=theta)(*args, jnp.asarray(True), frame))
        np.testing.assert_allclose(got_st, st, rtol=1e-12)
        np.testing.assert_allclose(got_lin, lin, rtol=1e-12)
    # no previous frame: y = 0, both reduce to the current error alone
    got = float(losses.make("st-linear", 4, theta=0.5)(*args, jnp.asarray(False), frame))
    np.testing.assert_allclose(got, np.mean(np.abs(x)), rtol=1e-12)
    got = float(losses.make("st", 4, theta=0.5)(*args, jnp.asarray(False), frame))
    np.testing.assert_allclose(got, np.mean(x * x), rtol=1e-12)


def _dlctus_hist(config, frame, history):
    return dlctus.prepare(dlctus.State(history), frame, config)[2]


def test_dlctus_without_accumulation_reads_a_count_of_one():
    """``accumulation=False`` (the thesis's ablation, Table 16): the reprojected
    history's fourth channel is 1 everywhere, whatever the buffer held. Catches: the
    option ignored."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2))
    frame = _at(frames, 1)
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
    frame = _at(frames, 1)
    history = jnp.asarray(np.random.default_rng(6).uniform(size=(2, 32, 32, 4)), jnp.float32)
    got = _dlctus_hist(dlctus.Config(factor=4, dilation=True), frame, history)
    dilated = frame._replace(motion=sampling.dilate_motion(frame.motion, frame.depth))
    want = _dlctus_hist(dlctus.Config(factor=4), dilated, history)
    plain = _dlctus_hist(dlctus.Config(factor=4), frame, history)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    assert float(jnp.abs(plain - want).max()) > 1e-3  # control: dilation changes the read


@pytest.mark.parametrize("warp", ["bicubic", "bicubic9", "bicubic5"])
def test_dlctus_reads_its_history_with_its_warp_and_keys_a(warp):
    """The history is read at ``P + f * mv`` with the configured warp and Keys ``a``
    (thesis sec. 5.5.1; a=-0.5 is the thesis's Bicubic5 before its change), the
    jitter-aligned input where that falls outside: against ``sampling.sample`` (checked
    against PyTorch's grid_sample). Catches: ``warp_a`` dropped on the way to the plan or
    the read (PyTorch's -0.75 then)."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, max_motion=2.0))
    frame = _at(frames, 1)
    history = jnp.asarray(np.random.default_rng(8).uniform(size=(2, 32, 32, 4)), jnp.float32)
    config = dlctus.Config(factor=4, warp=warp, warp_a=-0.5)
    got = _dlctus_hist(config, frame, history)
    xy = sampling.reproject_coords(frame.motion, 4)
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
    frame = _at(frames, 1)
    pre = dlctus.prepare_frame(frame, config)
    out, state = dlctus.advance(params, model.init_state(_first(frames)), pre, config)
    leaves = [x for x in jax.tree_util.tree_leaves((pre, out, state))
              if jnp.issubdtype(x.dtype, jnp.floating)]
    assert len(leaves) >= 6 and {x.dtype for x in leaves} == {jnp.dtype(jnp.float64)}
    f32 = dlctus.prepare_frame(frame, dlctus.Config(factor=4))  # control: float32 there
    assert f32.jau.dtype == jnp.float32


@pytest.mark.parametrize("name", ["dlctus", "nsrr", "nsrr-fast", "kpn", "mlp"])
def test_every_layer_draws_its_own_initialization(name):
    """No two parameter arrays of a fresh model come from one random key. Under JAX's
    partitionable threefry (its default), two draws from one key agree over their common
    leading elements whatever their shapes, so a layer initialized with a key another
    layer used correlates with it (r = 1.0 over that prefix; NSRR's two feature
    extractors then start identical), which no forward or gradient test sees. Every
    pair of arrays of at least 64 values must correlate below 0.9 over their common
    prefix (independent draws: |r| of order 1/sqrt(n); measured largest 0.36, NSRR, over
    a 64-value prefix; 1.0 for a shared key)."""
    from jtus import models

    params = models.build(name, 4).init(jax.random.PRNGKey(0))
    leaves = [(jax.tree_util.keystr(k), np.asarray(v, np.float64).ravel())
              for k, v in jax.tree_util.tree_leaves_with_path(params) if v.size >= 64]
    assert len(leaves) >= 3, name
    worst = (0.0, None)
    for i, (ka, a) in enumerate(leaves):
        for kb, b in leaves[i + 1:]:
            n = min(a.size, b.size)
            r = abs(np.corrcoef(a[:n], b[:n])[0, 1])
            worst = max(worst, (r, f"{ka} and {kb}"))
    assert worst[0] < 0.9, f"{name}: {worst[1]} share their draws (r = {worst[0]:.3f})"


def test_kpn_batch_elements_are_independent():
    """A batch of KPN frames gives each element's output and state as that element run
    alone, each with its own jitter's weight set, also with more elements than the HR
    image has rows (5 against 4). Catches the per-sample convolution looping over
    another axis than the batch's."""
    from jtus.models import kpn

    frames, _ = seqdata.to_jax(seqdata.sequence(T=1, B=5, h=1, w=2, seed=3))
    frame = _at(frames, 0)
    assert len(set(map(tuple, np.asarray(frame.jitter).tolist()))) > 1  # several phases
    model = kpn.make(kpn.Config(factor=4))
    params = model.init(jax.random.PRNGKey(1))
    out, state = model.step(params, model.init_state(frame), frame)
    for b in range(5):
        one = jax.tree_util.tree_map(lambda x: x[b:b + 1], frame)
        o, st = model.step(params, model.init_state(one), one)
        np.testing.assert_allclose(out[b:b + 1], o, rtol=0, atol=1e-6)
        np.testing.assert_allclose(state.history[b:b + 1], st.history, rtol=0, atol=1e-6)


def test_kpn_input_preparation():
    """Herveau et al.'s network input at HR: the jitter-aligned bilinear colour,
    linear depth and motion in HR pixels (both bilinearly up-sampled), then the
    Catmull-Rom-reprojected history (colour and 5 hidden channels); a reset frame's
    history is the fresh colour with zero hidden channels. Each part against numpy
    (``seqdata.jau_reference``; jitter 0.5 is plain bilinear). Catches: channels out of
    order, motion not scaled to HR pixels, depth not linearized, the reset ignored."""
    from jtus.data.conventions import linearize_depth
    from jtus.models import kpn

    f = 4
    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, reset_at=(1, 0), max_motion=0.0))
    frame = _at(frames, 1)
    config = kpn.Config(factor=f)
    hist = jnp.asarray(np.random.default_rng(8).uniform(size=(2, 32, 32, 3 + kpn.HIDDEN)),
                       jnp.float32)
    x, _, _ = kpn.prepare(kpn.State(hist), frame, config)
    x = np.asarray(x)
    half = np.full((2, 2), 0.5)
    jau = seqdata.jau_reference(np.asarray(frame.color), np.asarray(frame.jitter), f)
    lin = linearize_depth(np.asarray(frame.depth, np.float64), config.near, config.far)
    np.testing.assert_allclose(x[..., 0:3], jau, rtol=0, atol=1e-6)
    np.testing.assert_allclose(x[..., 3:4], seqdata.jau_reference(lin, half, f), rtol=0,
                               atol=1e-6)
    np.testing.assert_allclose(x[..., 4:6], f * seqdata.jau_reference(
        np.asarray(frame.motion, np.float64), half, f), rtol=0, atol=1e-6)
    # zero motion: the Catmull-Rom read at pixel centres is the history itself (element 1);
    # element 0 is a reset: fresh colour, hidden channels zero
    np.testing.assert_allclose(x[1, ..., 6:], np.asarray(hist[1]), rtol=0, atol=1e-6)
    np.testing.assert_allclose(x[0, ..., 6:9], jau[0], rtol=0, atol=1e-6)
    np.testing.assert_array_equal(x[0, ..., 9:], 0.0)
    # and with motion, the motion channels follow it (f x the up-sampled LR vectors)
    moving, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, max_motion=2.0))
    frame = _at(moving, 1)
    x, _, _ = kpn.prepare(kpn.State(hist), frame, config)
    np.testing.assert_allclose(np.asarray(x)[..., 4:6], f * seqdata.jau_reference(
        np.asarray(frame.motion, np.float64), half, f), rtol=0, atol=1e-5)


def _dejitter_numpy(img, jx, jy):
    """``img [h,w,C]`` read at the pixel centres of a frame sampled at ``(j + jx, i +
    jy)``: bilinear at index-space position ``(j + 0.5 - jx, i + 0.5 - jy)``, indices
    clamped to the edge."""
    h, w = img.shape[:2]
    out = np.zeros(img.shape, np.float64)
    c = lambda a, n: min(max(a, 0), n - 1)  # noqa: E731
    for i in range(h):
        for j in range(w):
            u, v = j + 0.5 - jx, i + 0.5 - jy
            j0, i0 = int(np.floor(u)), int(np.floor(v))
            tx, ty = u - j0, v - i0
            row = lambda r: ((1 - tx) * img[c(r, h), c(j0, w)]  # noqa: E731
                             + tx * img[c(r, h), c(j0 + 1, w)])
            out[i, j] = (1 - ty) * row(i0) + ty * row(i0 + 1)
    return out


def _mlp_numpy(params, color, depth, f, gamma, slope, near, far, jitter=None, mode="ignore"):
    """Spencer's MLP upscaler written out per LR pixel in numpy (float64): the 5x5
    colour patch of each channel and the 5x5 linear-depth patch, both minus their
    means, boosted by sign(r)|r|^(1/gamma); two leaky-ReLU layers; f*f outputs plus the
    colour mean, placed at sub-pixel (dy, dx) = divmod(k, f) (jtus's choices: raster
    patch order, colour before depth, edge-replicated borders). ``mode="input"``: the
    offset of ``jitter [B,2]`` from the pixel centre (x, y) follows as two more inputs;
    ``"dejitter"``: colour and linear depth are first read at the pixel centres."""
    from jtus.data.conventions import linearize_depth

    B, h, w, _ = color.shape
    lin = linearize_depth(depth[..., 0].astype(np.float64), near, far)
    color = color.astype(np.float64)
    if mode == "dejitter":
        color = np.stack([_dejitter_numpy(color[b], *jitter[b]) for b in range(B)])
        lin = np.stack([_dejitter_numpy(lin[b, ..., None], *jitter[b])[..., 0]
                        for b in range(B)])
    pc = np.pad(color, ((0, 0), (2, 2), (2, 2), (0, 0)), mode="edge")
    pd = np.pad(lin, ((0, 0), (2, 2), (2, 2)), mode="edge")
    Ws = [(np.asarray(lyr["kernel"], np.float64), np.asarray(lyr["bias"], np.float64))
          for lyr in params["layers"]]
    boost = lambda r: np.sign(r) * np.abs(r) ** (1.0 / gamma)  # noqa: E731
    out = np.zeros((B, h * f, w * f, 3))
    for b in range(B):
        for i in range(h):
            for j in range(w):
                dpatch = pd[b, i:i + 5, j:j + 5].reshape(-1)
                for c in range(3):
                    cpatch = pc[b, i:i + 5, j:j + 5, c].reshape(-1)
                    v = np.concatenate([boost(cpatch - cpatch.mean()),
                                        boost(dpatch - dpatch.mean())]
                                       + ([np.asarray(jitter[b], np.float64) - 0.5]
                                          if mode == "input" else []))
                    for k, (W, bias) in enumerate(Ws):
                        v = v @ W + bias
                        if k < len(Ws) - 1:
                            v = np.where(v > 0, v, slope * v)
                    v = v + cpatch.mean()
                    for s in range(f * f):
                        dy, dx = divmod(s, f)
                        out[b, i * f + dy, j * f + dx, c] = v[s]
    return out


def test_mlp_forward_and_gamma_against_numpy():
    """Catches: gamma ignored (or only 2.0 boosted) or applied as r^gamma, the leaky
    ReLU's slope left at its default, the mean not added back, sub-pixels shuffled in
    another order, the jitter input dropped, swapped or not centred, the
    de-jittering read on the wrong side or left out for depth."""
    from jtus.models import mlp

    frames, _ = seqdata.to_jax(seqdata.sequence(T=1, B=2, h=6, w=5))
    frame = _at(frames, 0)
    frame = frame._replace(jitter=jnp.asarray([[0.125, 0.875], [0.625, 0.25]], jnp.float32))
    for gamma, jit, slope in ((1.0, "dejitter", 0.01), (2.2, "dejitter", 0.01),
                              (2.0, "input", 0.2), (1.0, "ignore", 0.01)):
        config = mlp.Config(factor=4, gamma=gamma, jitter=jit, slope=slope)
        params = mlp.init(jax.random.PRNGKey(1), config)
        got = np.asarray(mlp.step(params, (), frame, config)[0])
        want = _mlp_numpy(params, np.asarray(frame.color), np.asarray(frame.depth), 4, gamma,
                          config.slope, config.near, config.far, np.asarray(frame.jitter), jit)
        np.testing.assert_allclose(got, want, rtol=0, atol=5e-7)  # float32: 2.1e-7 measured
    with pytest.raises(ValueError, match="jitter"):
        mlp.Config(jitter="centre")


@pytest.mark.parametrize("jit", ["ignore", "input", "dejitter"])
def test_mlp_computes_in_float32_whatever_the_frame_type(jit):
    """The MLP computes in float32, like its parameters: a half-precision frame and a
    float64 frame (64-bit types on) give exactly the output of the same values in
    float32, as float32. Catches: colour, depth or jitter left in the frame's own type
    (``astype(None)`` is float32 only while 64-bit types are off)."""
    from jtus.models import mlp

    frames, _ = seqdata.to_jax(seqdata.sequence(T=1, B=2, h=6, w=5))
    frame = _at(frames, 0)._replace(jitter=jnp.asarray([[0.0078125, 0.875], [0.625, 0.25]]))
    config = mlp.Config(factor=4, jitter=jit)
    params = mlp.init(jax.random.PRNGKey(1), config)
    for dtype in (jnp.float16, jnp.float64):
        with jax.enable_x64(dtype == jnp.float64):
            typed = _cast_frame(frame, dtype)
            assert typed.color.dtype == dtype
            want = mlp.step(params, (), _cast_frame(typed, jnp.float32), config)[0]
            got = mlp.step(params, (), typed, config)[0]
            assert got.dtype == jnp.float32, dtype
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_nsrr_ycbcr_option_converts_at_both_ends():
    """``ycbcr=True``: the network sees BT.601 full-range YCbCr colour (written here
    from the standard: Y = 0.299 R + 0.587 G + 0.114 B, Cb = 1/2 + (B - Y)/1.772,
    Cr = 1/2 + (R - Y)/1.402) and its output is converted back to RGB: the same as the
    RGB model fed YCbCr frames, its output converted back. Catches: the option
    ignored at either end."""
    from jtus.frame import Frame

    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=1, reset_at=(1, 0)))
    frame = _at(frames, 1)
    rgb = np.asarray(frame.color, np.float64)
    y = 0.299 * rgb[..., 0] + 0.587 * rgb[..., 1] + 0.114 * rgb[..., 2]
    ycc = np.stack([y, 0.5 + (rgb[..., 2] - y) / 1.772, 0.5 + (rgb[..., 0] - y) / 1.402], -1)
    yuv = nsrr.make(nsrr.Config(factor=4, fast=True, ycbcr=True))
    plain = nsrr.make(nsrr.Config(factor=4, fast=True))
    params = yuv.init(jax.random.PRNGKey(3))
    got, _ = yuv.step(params, yuv.init_state(frame), frame)
    alt = Frame(jnp.asarray(ycc, jnp.float32), *frame[1:])
    out_ycc, _ = plain.step(params, plain.init_state(alt), alt)
    o = np.asarray(out_ycc, np.float64)  # back to RGB, inverting the matrix above
    r = o[..., 0] + 1.402 * (o[..., 2] - 0.5)
    b = o[..., 0] + 1.772 * (o[..., 1] - 0.5)
    g = (o[..., 0] - 0.299 * r - 0.114 * b) / 0.587
    np.testing.assert_allclose(np.asarray(got), np.stack([r, g, b], -1), rtol=0, atol=1e-5)
    assert float(jnp.abs(got - plain.step(params, plain.init_state(frame), frame)[0]).max()) > 1e-3


def test_tus_dilation_reprojects_with_the_dilated_motion():
    """TUS with ``dilation=True`` equals TUS fed the dilated motion (replaces a test
    that asserted the field it had just set). Catches: the option ignored."""
    from jtus.models import tus

    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, max_motion=2.0))
    frame = _at(frames, 1)
    base = tus.thesis(4)
    state = tus.init_state(_at(frames, 0), base)
    state = tus.State(state.history + jnp.asarray(
        np.random.default_rng(9).uniform(-0.2, 0.2, size=state.history.shape), jnp.float32))
    got, _ = tus.step({}, state, frame, dataclasses.replace(base, dilation=True))
    dilated = frame._replace(motion=sampling.dilate_motion(frame.motion, frame.depth))
    want, _ = tus.step({}, state, dilated, base)
    plain, _ = tus.step({}, state, frame, base)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-6)
    assert float(jnp.abs(plain - want).max()) > 1e-3  # control


@pytest.mark.parametrize("name", ["jau", "tus", "tus-mean", "kpn", "nsrr-fast", "dlctus"])
def test_models_compute_in_float32_whatever_the_frame_type(name):
    """Every model computes in float32, like its parameters: a float64 frame sequence
    with 64-bit types on gives exactly the outputs and the state that the same values in
    float32 give with them off (the default), as float32. Catches: a frame field cast
    with ``astype(None)``, which is float32 only while 64-bit types are off: the state's
    type then changes inside the scan, the outputs come out in float64, or a position
    is computed in float64 (TUS's and NSRR's reprojection read with float64 motion:
    about 1e-6 of a value, where a run under 64-bit types with float32 frames would be
    cast the same way and match; its input read at a float64 jitter-aligned position).
    Half-precision frames: the MLP's test above, and ``test_losses.py`` for the losses."""
    from jtus import models

    # three frames, the second a reset: the third reads a history (NSRR's starts at zero,
    # so with two frames its warp read only zeros and a float64 position passed)
    frames, _ = seqdata.sequence(T=3, B=1, h=6, w=5, reset_at=(1, 0))
    # jitters that are not short binary fractions (the thesis's are), so that a position
    # computed from them in float64 differs from the float32 one
    jitter = np.random.default_rng(5).uniform(0.05, 0.95, frames.jitter.shape)
    frames = seqdata.to_jax(frames._replace(jitter=jitter.astype(np.float32)))
    model = models.build(name, 4)
    params = model.init(jax.random.PRNGKey(0))
    want, want_state = rollout.outputs(model.step, params, model.init_state(_first(frames)),
                                       frames)
    with jax.enable_x64(True):
        fr = _cast_frame(frames, jnp.float64)
        assert fr.color.dtype == jnp.float64
        got, got_state = rollout.outputs(model.step, params, model.init_state(_first(fr)), fr)
        for g, w in zip(jax.tree_util.tree_leaves((got, got_state)),
                        jax.tree_util.tree_leaves((want, want_state))):
            assert g.dtype == w.dtype, (g.dtype, w.dtype)
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
        assert got.dtype == jnp.float32


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
    frame = _at(frames, 1)
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
    frame = _at(frames, 0)._replace(reset=jnp.zeros((1,), bool))
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
    frame = _at(frames, 0)._replace(reset=jnp.zeros((1,), bool))
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
