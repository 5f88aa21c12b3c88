"""NSRR, kernel-prediction TAA and the MLP upscaler: structure, PyTorch parity, training."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from PIL import Image

from jtus import checkpoint, evaluate, loading, losses, models, recipe, rollout, sampling, train
from jtus.config import PRESETS, Config, to_json
from jtus.data import dataset
from jtus.models import kpn, mlp, nsrr
from jtus.models.base import param_count
from tests import seqdata, torch_models


def _frames(T=3, B=2, h=8, factor=4, seed=0):
    return seqdata.to_jax(seqdata.sequence(T=T, B=B, h=h, w=h, factor=factor, seed=seed))


def test_parameter_counts():
    def conv(k, i, o):
        return k * k * i * o + o
    ext = conv(3, 4, 32) + conv(3, 32, 32) + conv(3, 32, 8)
    rew = conv(3, 20, 32) + conv(3, 32, 32) + conv(3, 32, 4)
    unet = (conv(3, 60, 64) + conv(3, 64, 32) + conv(3, 32, 64) + conv(3, 64, 64)
            + conv(3, 64, 128) + conv(3, 128, 128) + conv(3, 192, 64) + conv(3, 64, 64)
            + conv(3, 96, 32) + conv(3, 32, 3))
    def count(init, *args):  # shapes only: no weights are drawn
        return param_count(jax.eval_shape(lambda: init(jax.random.PRNGKey(0), *args)))

    assert count(nsrr.init) == 2 * ext + rew + unet == 547767
    phases = 16  # the thesis's 4x pattern
    k = (conv(3, 14, 12) + conv(1, 12, 5)
         + phases * (conv(3, 12, 12) + conv(5, 12, 12) + conv(5, 12, 50)))
    assert count(kpn.init) == k
    assert count(mlp.init) == (50 * 50 + 50) * 2 + 50 * 16 + 16
    assert count(mlp.init, mlp.Config(jitter="input")) == ((52 * 50 + 50) + (50 * 50 + 50)
                                                           + 50 * 16 + 16)
    fast = count(nsrr.init, nsrr.Config(fast=True))
    assert fast < 0.4 * 547767


def test_nsrr_unet_widths_chain_and_fast_halves_them():
    """Each U-Net layer's input width follows from the widths before it, with distinct
    widths (the defaults repeat 64 and 128, so a layer sized from a neighbour of the
    same width passed every other test), the network runs with them, and ``fast``
    halves every width, keeping at least one channel."""
    widths = (5, 6, 7, 9, 11, 13, 10, 8, 4)
    cfg = nsrr.Config(unet=widths)
    params = nsrr.init(jax.random.PRNGKey(0), cfg)
    ins = [12 * 5, 5, 6, 7, 9, 11, 13 + 9, 10, 8 + 6, 4]  # skips: u[5]+u[3], u[7]+u[1]
    assert [p["kernel"].shape[2:] for p in params["unet"]] == list(zip(ins, widths + (3,)))
    frames, _ = _frames(T=2, B=1)
    m = nsrr.make(cfg)
    outs, _ = rollout.outputs(m.step, params, m.init_state(seqdata.first(frames)), frames)
    assert outs.shape == (2, 1, 32, 32, 3) and np.all(np.isfinite(np.asarray(outs)))
    assert nsrr.Config(fast=True).unet_widths() == (32, 16, 32, 32, 64, 64, 32, 32, 16)
    assert nsrr.Config(fast=True, unet=tuple(range(1, 10))).unet_widths() == \
        (1, 1, 1, 2, 2, 3, 3, 4, 4)
    assert nsrr.Config(unet=widths).unet_widths() == widths


@pytest.mark.parametrize("changes,message", [
    ({"extract": (32, 32, 7)}, r"^extract: the last width must be 8, got \(32, 32, 7\)$"),
    ({"unet": (64,) * 8}, r"^unet: expected 9 widths \(the 10th layer outputs 3\), got "
                          r"\(64, 64, 64, 64, 64, 64, 64, 64\)$"),
    ({"frames": 0}, r"^frames: expected >= 1, got 0$"),
    ({"exposure": "auto"}, r"^exposure: expected one of \('absolute', 'normalized'\), "
                           r"got 'auto'$")])
def test_nsrr_config_names_the_bad_field(changes, message):
    """A bad NSRR setting is refused with an error that starts with its field's name and
    says what was expected and what it got; the boundaries are accepted."""
    with pytest.raises(ValueError, match=message):
        nsrr.Config(**changes)
    assert nsrr.Config(frames=1, extract=(8,)).frames == 1


def test_nsrr_differentiates_by_winograd_only_where_it_measured_faster(monkeypatch):
    """``conv_backward="auto"`` (the default): Winograd's F(4x4) forward and input gradient
    on a CPU for the full-width model's 3x3 layers from at least 32 channels to at least
    16 on maps of at most ``WINOGRAD_PIXELS`` per device, the custom backward for the
    others, on larger maps, on a GPU and for NSRR-fast; ``"winograd"`` named takes the
    same layers anywhere, ``"custom"`` none. In NSRR's step that is both
    extractors' and the reweighting's middle layers and the U-Net's first nine (12), and
    only those on the smallest maps when the bound leaves the others out (the layer's
    values: ``tests/test_convolutions.py``)."""
    from jtus.models import layers

    auto, most = nsrr.Config(), nsrr.WINOGRAD_PIXELS
    assert auto.conv_backward == "auto"
    assert auto.conv_form("cpu", most, (32, 16)) == "winograd"
    assert auto.conv_form("cpu", most + 1, (32, 16)) == "custom"
    assert auto.conv_form("cpu", 64, (20, 32)) == "custom"
    assert auto.conv_form("cpu", 64, (32, 3)) == "custom"
    assert auto.conv_form("gpu", 64, (64, 64)) == "custom"
    assert auto.train_conv_form(2, 128, "cpu") == "winograd"
    assert auto.train_conv_form(2, 256, "cpu") == "custom"
    assert nsrr.Config(conv_backward="custom").conv_form("cpu", 64, (64, 64)) == "custom"
    assert nsrr.Config(conv_backward="winograd").conv_form("gpu") == "winograd"
    assert nsrr.Config(conv_backward="winograd").conv_form("gpu", 10 ** 9, (32, 16)) == \
        "winograd"
    assert nsrr.Config(conv_backward="winograd").conv_form("cpu", 64, (20, 32)) == "custom"
    assert nsrr.Config(fast=True).conv_form("cpu", 64, (64, 64)) == "custom"
    assert nsrr.Config(fast=True, conv_backward="winograd").conv_form("cpu", 64, (64, 64)) \
        == "winograd"
    with pytest.raises(ValueError, match=r"^conv_backward: expected one of \('auto', "):
        nsrr.Config(conv_backward="fast")

    frames, targets = _frames(T=1, B=1, h=4)
    frame, target = seqdata.first(frames), seqdata.first(targets)
    params = nsrr.init(jax.random.PRNGKey(0), nsrr.Config())

    def loss(p, config):
        out, _ = nsrr.step(p, nsrr.init_state(frame, config), frame, config)
        return jnp.mean((out - target) ** 2)

    calls = []
    real = layers.conv_same_winograd
    monkeypatch.setattr(layers, "conv_same_winograd", lambda *a: calls.append(1) or real(*a))
    auto_loss = lambda p: loss(p, nsrr.Config())  # noqa: E731
    jax.eval_shape(jax.grad(auto_loss), params)  # traced only: the choice
    assert len(calls) == 12
    calls.clear()
    monkeypatch.setattr(nsrr, "WINOGRAD_PIXELS", 4 * 4)  # the 4x4 maps alone
    jax.eval_shape(jax.grad(auto_loss), params)
    assert len(calls) == 4  # the LR extractors' middle layers, the U-Net's lowest level


@pytest.mark.parametrize("shape", [(1,), (7,), (64,), (3, 3, 12, 50), (50, 16)])
def test_init_draws_are_jax_uniform_draws(shape):
    """layers.uniform (the models' inits) draws from a power-of-two length and keeps the
    first values: exactly jax.random.uniform of the shape, and the bound is reached."""
    from jtus.models import layers

    key = jax.random.PRNGKey(3)
    got = layers.uniform(key, shape, 0.25)
    np.testing.assert_array_equal(got, jax.random.uniform(key, shape, jnp.float32, -0.25, 0.25))
    assert got.shape == shape and float(jnp.abs(got).max()) <= 0.25


def test_nsrr_reweighting_lies_in_0_10():
    frames, _ = _frames()
    config = nsrr.Config()
    params = nsrr.init(jax.random.PRNGKey(1), config)
    params["reweight"][-1] = jax.tree_util.tree_map(lambda x: 50 * x, params["reweight"][-1])
    cur, _ = nsrr.features(params, seqdata.first(frames), config)
    warped = jnp.asarray(np.random.default_rng(0).normal(size=cur.shape[:3] + (48,)) * 5,
                         jnp.float32)
    w = np.asarray(nsrr.reweight_maps(params, cur, warped, config))
    assert w.shape[-1] == 4 and w.min() >= 0.0 and w.max() <= 10.0
    assert w.min() < 1.0 and w.max() > 9.0  # the range is used, not a constant


def test_nsrr_forward_matches_torch():
    frames, _ = _frames(T=3, B=1, h=4)
    config = nsrr.Config()
    params = nsrr.init(jax.random.PRNGKey(2), config)
    model = nsrr.make(config)
    state = model.init_state(seqdata.first(frames))
    prev_t = torch_models.nchw(np.asarray(state.previous))
    for t in range(3):  # the state carries real features from the second frame on
        fr = jax.tree_util.tree_map(lambda x: x[t], frames)
        out, state = model.step(params, state, fr)
        ref, prev_t, _ = torch_models.nsrr_step(
            params, prev_t, torch_models.nchw(fr.color), torch_models.nchw(fr.depth),
            torch_models.nchw(fr.motion), np.asarray(fr.jitter), 4)
        np.testing.assert_allclose(np.asarray(out), ref.numpy().transpose(0, 2, 3, 1),
                                   rtol=0, atol=1e-5)
        np.testing.assert_allclose(np.asarray(state.previous),
                                   prev_t.numpy().transpose(0, 2, 3, 1), rtol=0, atol=1e-5)
    assert float(np.abs(np.asarray(state.previous)).max()) > 0


def test_kpn_forward_matches_torch_and_kernels_sum_to_one():
    frames, _ = _frames(T=2, B=2)
    config = kpn.Config()
    params = kpn.init(jax.random.PRNGKey(3), config)
    model = kpn.make(config)
    fr = seqdata.first(frames)
    state = model.init_state(fr)
    x, jau, rep = kpn.prepare(state, fr, config)
    phase = np.asarray(kpn.phase_index(fr.jitter, config))
    wts, hidden = kpn.kernels(params, x, jnp.asarray(phase))
    np.testing.assert_allclose(np.asarray(wts).sum(-1), 1.0, atol=1e-5)
    out, new = model.step(params, state, fr)
    for b in range(2):
        ref, ref_hidden, _ = torch_models.kpn_forward(
            params, torch_models.nchw(x[b:b + 1]), torch_models.nchw(jau[b:b + 1]),
            torch_models.nchw(rep[b:b + 1]), int(phase[b]))
        np.testing.assert_allclose(np.asarray(out[b]), ref[0].numpy().transpose(1, 2, 0),
                                   rtol=0, atol=1e-5)
        np.testing.assert_allclose(np.asarray(new.history[b, ..., 3:]),
                                   ref_hidden[0].numpy().transpose(1, 2, 0), rtol=0, atol=1e-5)


@pytest.mark.parametrize("factor", [2, 4])
def test_kpn_sample_mask_marks_the_hr_pixel_under_each_sample(factor):
    """With ``sample_mask`` the last input channel is 1 on exactly one HR pixel of each
    f x f cell, the one under the jittered sample (x, y = floor(jitter * f)), and the
    other inputs are those of the KPN without it."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=1, B=2, h=4, w=3, factor=factor))
    fr = seqdata.at(frames, 0)._replace(jitter=jnp.asarray([[0.1, 0.6], [0.9, 0.3]]))
    plain, masked = kpn.Config(factor=factor), kpn.Config(factor=factor, sample_mask=True)
    state = kpn.init_state(fr, plain)
    x0, _, _ = kpn.prepare(state, fr, plain)
    x1, _, _ = kpn.prepare(state, fr, masked)
    np.testing.assert_array_equal(np.asarray(x1[..., :-1]), np.asarray(x0))
    mask = np.asarray(x1[..., -1])
    for b, (jx, jy) in enumerate(np.asarray(fr.jitter)):
        want = np.zeros((factor, factor))
        want[int(jy * factor), int(jx * factor)] = 1.0
        np.testing.assert_array_equal(mask[b], np.tile(want, (4, 3)))


def test_kpn_given_the_sample_mask_starts_as_the_kpn_it_was_made_from(tmp_path):
    """``kpn.adapt_params`` gives the first convolution a zero weight for the new
    channel: the grown network's outputs and state equal the original's, both built by
    ``loading.init_params`` from a checkpoint without the mask (what ``--init-from``
    with ``--model-override sample_mask=true`` trains from); parameters that already
    fit are kept, other input layouts refused by name."""
    frames, _ = _frames(T=2, B=2)
    plain, masked = kpn.Config(), kpn.Config(sample_mask=True)
    params = kpn.init(jax.random.PRNGKey(3), plain)
    src = checkpoint.write_params(str(tmp_path / "kpn"), params,
                                  to_json(Config(model="kpn", factor=4)))
    wide = loading.init_params(Config(model="kpn", factor=4, init_from=src,
                                      model_overrides=(("sample_mask", True),)))
    assert wide["conv1"]["kernel"].shape[2] == masked.in_channels()
    np.testing.assert_array_equal(wide["conv1"]["kernel"][:, :, -1], 0)
    fr = seqdata.first(frames)
    s0 = s1 = kpn.init_state(fr, plain)
    for t in range(2):
        fr = seqdata.at(frames, t)
        o0, s0 = kpn.step(params, s0, fr, plain)
        o1, s1 = kpn.step(wide, s1, fr, masked)
        np.testing.assert_allclose(np.asarray(o1), np.asarray(o0), rtol=0, atol=1e-6)
    assert kpn.adapt_params(wide, masked) is wide
    with pytest.raises(ValueError, match="conv1 takes 15 input channels, this config takes 14"):
        kpn.adapt_params(wide, plain)
    with pytest.raises(ValueError, match="only the sample-mask channel"):
        kpn.adapt_params(params, kpn.Config(current="samples"))


@pytest.mark.parametrize("factor", [2, 4])
def test_kpn_samples_mix_weighs_only_the_taps_that_hold_a_sample(factor):
    """``current="samples"``: every 5x5 window off the border holds at least one sample
    (at the border the history taps alone may carry the softmax); the current
    kernel's weight is exactly 0 on taps without one; the 50 weights sum to one; the
    output is the weighted sum of the placed samples and the history; the gradient
    through the masked softmax is finite."""
    frames, _ = _frames(T=1, B=2, h=8 * 4 // factor, factor=factor)
    config = kpn.Config(factor=factor, current="samples")
    params = kpn.init(jax.random.PRNGKey(5), config)
    fr = seqdata.first(frames)
    state = kpn.init_state(fr, config)
    x, cur, rep = kpn.prepare(state, fr, config)
    assert x.shape[-1] == config.in_channels() == kpn.IN_CHANNELS + 4
    valid = np.asarray(kpn.valid_taps(x, config))
    n = kpn.K * kpn.K
    assert valid[:, 2:-2, 2:-2, :n].sum(-1).min() >= 1 and valid[..., n:].all()
    # at 4x a border window may hold none (the jitter cell past its three columns)
    assert (valid[..., :n].sum(-1).min() == 0) == (factor == 4)
    wts, _ = kpn.kernels(params, x, kpn.phase_index(fr.jitter, config), jnp.asarray(valid))
    wts = np.asarray(wts)
    assert np.all(wts[..., :n][~valid[..., :n]] == 0.0)
    np.testing.assert_allclose(wts.sum(-1), 1.0, rtol=0, atol=1e-6)
    near = lambda img: np.asarray(sampling.neighbourhood(img, kpn.K, mode="constant"))  # noqa: E731
    want = ((near(cur) * wts[:, :, :, None, :n]).sum(-1)
            + (near(rep[..., :3]) * wts[:, :, :, None, n:]).sum(-1))
    out, _ = kpn.step(params, state, fr, config)
    np.testing.assert_allclose(np.asarray(out), want, rtol=0, atol=1e-6)
    grad = jax.grad(lambda p: kpn.step(p, state, fr, config)[0].sum())(params)
    assert all(np.isfinite(np.asarray(g)).all() for g in jax.tree_util.tree_leaves(grad))


def test_kpn_samples_mix_starts_as_jitter_aware_accumulation():
    """With the kernel layer's weights at zero only its starting bias
    (``SAMPLES_PRIOR``) speaks: where a sample lies on the pixel itself it gets weight
    1 / (1 + 9 + the other taps' e^-5 each) and the history's centre 9 times that;
    elsewhere the history's centre takes over 80%."""
    frames, _ = _frames(T=1, B=1, h=8)
    config = kpn.Config(current="samples")
    params = kpn.init(jax.random.PRNGKey(6), config)
    params["kernel"]["kernel"] = jnp.zeros_like(params["kernel"]["kernel"])
    fr = seqdata.first(frames)
    x, _, _ = kpn.prepare(kpn.init_state(fr, config), fr, config)
    valid = kpn.valid_taps(x, config)
    wts, _ = kpn.kernels(params, x, kpn.phase_index(fr.jitter, config), valid)
    wts, valid = np.asarray(wts), np.asarray(valid)
    n, c = kpn.K * kpn.K, kpn.K * kpn.K // 2
    on = valid[..., c]
    others = valid.sum(-1) - 2
    want = 1.0 / (1.0 + 9.0 + others * np.exp(-5.0))
    np.testing.assert_allclose(wts[..., c][on], want[on], rtol=1e-5)
    np.testing.assert_allclose(wts[..., n + c][on], 9.0 * want[on], rtol=1e-5)
    assert wts[..., n + c][~on].min() > 0.8
    assert 0 < on.mean() < 1


def test_kpn_config_names_a_bad_current_colour():
    with pytest.raises(ValueError, match=r"^current: expected one of \('jau', 'samples'\), "
                                         r"got 'sparse'$"):
        kpn.Config(current="sparse")
    with pytest.raises(ValueError, match=r"^history: expected one of \('raw', 'clamped'\), "
                                         r"got 'clipped'$"):
        kpn.Config(history="clipped")
    with pytest.raises(ValueError, match=r"^exposure: expected one of \('absolute', "
                                         r"'normalized'\), got 'auto'$"):
        kpn.Config(exposure="auto")


def test_kpn_normalized_exposure_scales_outputs_with_the_colour(factor=2):
    """``exposure="normalized"``: over 5 frames with motion and a camera cut, the
    video's colour times 8 or times 1/4 gives the outputs times 8 or 1/4 (powers of
    two, so the network reads the same numbers; measured exact), and the hidden
    channels do not change. The KPN fed absolute colour does not have this property,
    which is what the test would catch if the normalization were dropped."""
    frames, _ = seqdata.sequence(T=5, B=2, h=24 // factor, w=32 // factor, factor=factor,
                                 seed=5, max_motion=1.5, reset_at=(3, 1))
    jf = seqdata.to_jax(frames)

    def run(scale, exposure):
        m = models.build("kpn", factor, current="samples", history="clamped",
                         exposure=exposure)
        fr = jf._replace(color=jf.color * scale)
        return rollout.outputs(m.step, m.init(jax.random.PRNGKey(1)),
                               rollout.first_state(m, fr), fr)

    outs, final = run(1.0, "normalized")
    for scale in (8.0, 0.25):
        o, f = run(scale, "normalized")
        np.testing.assert_allclose(np.asarray(o), scale * np.asarray(outs), rtol=1e-6,
                                   atol=1e-7)
        np.testing.assert_allclose(np.asarray(f.history[..., 3:]),
                                   np.asarray(final.history[..., 3:]), rtol=1e-6, atol=1e-7)
    absolute, _ = run(1.0, "absolute")
    brighter, _ = run(8.0, "absolute")
    assert np.abs(np.asarray(brighter) - 8.0 * np.asarray(absolute)).max() > 1e-3
    # the cost model counts the frame's mean and the scaled colour inputs
    config = kpn.Config(factor=factor, current="samples", exposure="normalized")
    absolute_cost = kpn.cost(dataclasses.replace(config, exposure="absolute"), 64, 64)
    assert (kpn.cost(config, 64, 64).flops - absolute_cost.flops
            == (64 // factor) ** 2 * 3 + 64 * 64 * 9)


def test_kpn_clamped_history_keeps_what_lies_in_the_samples_box():
    """``history="clamped"``: the reprojected RGB is clamped to the 3x3 box of the
    frame's samples (``sampling.neighbourhood_box``); colour already inside it and the
    hidden channels pass unchanged. Catches: the hidden channels clamped, the box
    taken around another position than the jitter-aligned one."""
    frames, _ = _frames(T=1, B=2)
    frame = seqdata.first(frames)
    config = kpn.Config(current="samples", history="clamped")
    b, h, w, _ = frame.color.shape
    xy = sampling.jitter_aligned_coords(frame.jitter, b, h, w, 4)
    lo, hi = (np.asarray(v) for v in sampling.neighbourhood_box(frame.color, xy))
    rep = np.random.default_rng(3).uniform(-0.5, 1.5, size=(b, 4 * h, 4 * w, 8))
    rep[0, :, :, :3] = (lo[0] + hi[0]) / 2  # element 0 inside the box everywhere
    out = np.asarray(kpn.clamp_history(jnp.asarray(rep, jnp.float32), frame, config))
    np.testing.assert_array_equal(out[..., 3:], rep[..., 3:].astype(np.float32))
    np.testing.assert_allclose(out[0, ..., :3], rep[0, ..., :3], rtol=0, atol=1e-7)
    np.testing.assert_allclose(out[1, ..., :3], np.clip(rep[1, ..., :3], lo[1], hi[1]),
                               rtol=0, atol=1e-7)
    assert (np.abs(out[1, ..., :3] - rep[1, ..., :3]) > 1e-3).mean() > 0.5
    # the cost model counts the clamp: 48 operations per LR pixel and 6 per HR pixel
    raw = kpn.cost(dataclasses.replace(config, history="raw"), 64, 64)
    assert kpn.cost(config, 64, 64).flops - raw.flops == 16 * 16 * 48 + 64 * 64 * 6


def test_kpn_uses_the_weight_set_of_the_jitter_phase():
    frames, _ = _frames(T=1, B=2)
    config = kpn.Config()
    params = kpn.init(jax.random.PRNGKey(4), config)
    fr = seqdata.first(frames)
    phase = np.asarray(kpn.phase_index(fr.jitter, config))
    seq = config.phases()
    np.testing.assert_allclose(seq[phase], np.asarray(fr.jitter), atol=1e-6)
    model = kpn.make(config)
    state = model.init_state(fr)
    base, _ = model.step(params, state, fr)
    for k in range(len(seq)):
        changed = jax.tree_util.tree_map(lambda x: x, params)
        changed["kernel"]["bias"] = changed["kernel"]["bias"].at[k].add(3.0 * jnp.arange(50.0))
        out, _ = model.step(changed, state, fr)
        moved = np.abs(np.asarray(out - base)).max(axis=(1, 2, 3)) > 1e-4
        np.testing.assert_array_equal(moved, phase == k)


def test_mlp_removes_the_dc_term():
    frames, _ = _frames(T=1, B=1)
    fr = seqdata.first(frames)
    model = mlp.make(mlp.Config())
    params = model.init(jax.random.PRNGKey(5))
    out, _ = model.step(params, (), fr)
    shifted, _ = model.step(params, (), fr._replace(color=fr.color + 0.25))
    np.testing.assert_allclose(np.asarray(shifted), np.asarray(out) + 0.25, atol=1e-5)
    assert mlp.acceptance(np.zeros((2, 8, 8, 3))) < mlp.acceptance(
        np.random.default_rng(0).uniform(size=(2, 8, 8, 3)))


@pytest.mark.parametrize("name,loss", [("nsrr-fast", "ssim"), ("kpn", "kpn"), ("mlp", "l1")])
def test_trains_with_decreasing_loss_and_evaluates(tiny_data, tmp_path, name, loss):
    config = dataclasses.replace(PRESETS["tiny"], model=name, loss=loss, dataset=tiny_data,
                                 epochs=1, lr=3e-3)
    model = recipe.model_for(config)
    opt = optax.adam(config.lr)
    step = train.make_train_step(model, recipe.loss_for(config), opt, loss_frames=2)
    ts = train.create_train_state(model.init(jax.random.PRNGKey(0)), opt)
    with dataset.Dataset(tiny_data) as ds:
        batch = ds.crops("train", 4, 2, 4, 16, np.random.default_rng(0))
    frames, targets = jax.tree_util.tree_map(jnp.asarray, batch)
    seen = []
    for _ in range(8):  # a few steps on one batch: the loss must go down
        carry = rollout.start(model.init_state(seqdata.first(frames)), targets[0])
        ts, _, stats = step(ts, carry, frames, targets)
        seen.append(float(stats["loss"]))
    assert seen[-1] < seen[0], seen
    train.train_and_evaluate(config, tmp_path, progress=False)
    out = tmp_path / "eval"
    assert evaluate.main(["--dataset", tiny_data, "--factor", "4", "--models", "jau",
                          f"{name}={tmp_path / 'checkpoint.msgpack'}", "--out", str(out),
                          "--quiet"]) == 0
    grid = np.asarray(Image.open(out / "crops_x4.png").convert("L"))
    # 4 columns (input, jau, the model, reference) enlarged to about 192 px each, under
    # a white header that carries their names in dark text
    assert grid.shape[1] >= 4 * 190 and (grid[:18] < 128).any() and grid[0, 0] == 255
    summary = json.loads((out / "results.json").read_text())
    assert np.isfinite(summary["4"][name]["psnr"])


def test_registry_builds_every_model():
    frames, _ = _frames(T=2, B=1)
    for name in models.NAMES:
        m = models.build(name, 4)
        outs, _ = rollout.outputs(m.step, m.init(jax.random.PRNGKey(0)),
                                  m.init_state(seqdata.first(frames)), frames)
        assert outs.shape == (2, 1, 32, 32, 3) and np.all(np.isfinite(np.asarray(outs))), name


def test_every_registered_model_has_a_cost_and_its_hooks():
    """What the registry promises each tool (jtus.cost, train, evaluate): a positive
    cost at any size, parameters exactly for the trainable names, a known loss."""
    from jtus import cost, losses

    for name, spec in models.REGISTRY.items():
        m = spec.make(spec.config(4))
        c = cost.cost(name, m.config, 64, 64)
        assert c.flops > 0 and c.bytes > 0, name
        n = models.param_count(jax.eval_shape(m.init, jax.random.PRNGKey(0)))
        assert (n > 0) == spec.trainable == (name in models.TRAINABLE), name
        assert spec.loss in losses.NAMES, name
    assert models.spec("mlp").accept is mlp.acceptance
    assert models.spec("kpn").loss == "kpn"


@pytest.mark.parametrize("current,history,exposure", [
    ("jau", "raw", "absolute"), ("samples", "raw", "absolute"),
    ("samples", "clamped", "absolute"), ("samples", "clamped", "normalized")])
@pytest.mark.parametrize("factor", [4, 2])
def test_kpn_matches_an_independent_torch_kpn(factor, current, history, exposure):
    """jtus's KPN against jtus/reference/torch_kpn.py (its own parameter layout, Catmull-Rom,
    input preparation and colour mix, from Herveau et al. and docs/comparison.md) over
    6 frames with motion, a camera cut in one element and the weight set of each
    frame's jitter phase; with either colour for the current kernel (``samples``: the
    placed samples, the softmax over the taps that hold one) and the history raw or
    clamped to the samples' neighbourhood box (its own gathers of the 9 samples), and
    the network's colour absolute or over the frame's mean."""
    import torch

    from jtus import models, rollout
    from jtus.reference import torch_kpn

    frames, _ = seqdata.sequence(T=6, B=2, h=24 // factor, w=32 // factor, factor=factor,
                                 seed=11, max_motion=1.5, reset_at=(3, 1))
    frames.reset[0] = True
    model = models.build("kpn", factor, current=current, history=history, exposure=exposure)
    phases = np.asarray(model.config.phases(), np.float32)
    torch.manual_seed(0)
    net = torch_kpn.KPN(len(phases), samples=current == "samples")
    params = jax.tree_util.tree_map(jnp.asarray, torch_kpn.to_jtus(net))
    jf = seqdata.to_jax(frames)
    outs, final = jax.jit(lambda p, s, f: rollout.outputs(model.step, p, s, f))(
        params, rollout.first_state(model, jf), jf)
    nchw = lambda x: torch.from_numpy(np.ascontiguousarray(np.moveaxis(x, -1, 1)))  # noqa: E731
    fb, ref = None, []
    with torch.no_grad():
        for t in range(6):
            out, fb = torch_kpn.step(net, fb, nchw(frames.color[t]), nchw(frames.depth[t]),
                                     nchw(frames.motion[t]), torch.from_numpy(frames.jitter[t]),
                                     torch.from_numpy(frames.reset[t]), torch.from_numpy(phases),
                                     factor, samples=current == "samples",
                                     clamp=history == "clamped",
                                     normalize=exposure == "normalized")
            ref.append(out.numpy().transpose(0, 2, 3, 1))
    # float32; measured max 3.0e-7 (both factors, every variant)
    np.testing.assert_allclose(np.asarray(outs), np.stack(ref), rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(final.history), fb.numpy().transpose(0, 2, 3, 1),
                               rtol=0, atol=1e-6)
    assert np.abs(np.asarray(outs)).max() > 0.1  # not a comparison of zeros
    if history == "clamped":  # the clamp bites: the raw history gives other outputs
        raw = models.build("kpn", factor, current=current)
        outs_raw, _ = rollout.outputs(raw.step, params, rollout.first_state(raw, jf), jf)
        assert np.abs(np.asarray(outs_raw) - np.asarray(outs)).max() > 1e-3


@pytest.mark.parametrize("factor,exposure", [(4, "absolute"), (2, "absolute"),
                                             (4, "normalized")])
def test_nsrr_matches_an_independent_torch_nsrr(factor, exposure):
    """jtus's NSRR against jtus/reference/torch_nsrr.py (its own nn.Sequential layout converted
    by a function, zero-up-sampling, iterated warping and reweighting from the paper's
    text) over 7 frames (the 4-frame window rolls) with motion and a camera cut; with
    ``exposure="normalized"`` on colour darkened 20x, where the normalization changes
    every output."""
    import torch

    from jtus import models, rollout
    from jtus.reference import torch_nsrr

    frames, _ = seqdata.sequence(T=7, B=2, h=32 // factor, w=32 // factor, factor=factor,
                                 seed=12, max_motion=1.5, reset_at=(4, 1))
    frames.reset[0] = True
    if exposure == "normalized":
        frames = frames._replace(color=frames.color / 20)
    model = models.build("nsrr", factor, exposure=exposure)
    torch.manual_seed(1)
    net = torch_nsrr.NSRR()
    params = jax.tree_util.tree_map(jnp.asarray, torch_nsrr.to_jtus(net))
    jf = seqdata.to_jax(frames)
    outs, _ = jax.jit(lambda p, s, f: rollout.outputs(model.step, p, s, f))(
        params, rollout.first_state(model, jf), jf)
    nchw = lambda x: torch.from_numpy(np.ascontiguousarray(np.moveaxis(x, -1, 1)))  # noqa: E731
    prev, ref = [], []
    with torch.no_grad():
        for t in range(7):
            out, prev = torch_nsrr.step(net, prev, nchw(frames.color[t]), nchw(frames.depth[t]),
                                        nchw(frames.motion[t]), torch.from_numpy(frames.jitter[t]),
                                        torch.from_numpy(frames.reset[t]), factor,
                                        normalize=exposure == "normalized")
            ref.append(out.numpy().transpose(0, 2, 3, 1))
    ref = np.stack(ref)
    # float32 through a 10-layer U-Net; measured max 2.6e-8 on outputs up to 0.07 (and,
    # normalized, 1.6e-9 on outputs up to 0.002: the error scales with the output)
    out_scale = 1 / 20 if exposure == "normalized" else 1.0
    np.testing.assert_allclose(np.asarray(outs), ref, rtol=0, atol=2e-7 * out_scale)
    assert np.abs(ref).max() > 1e-2 * out_scale  # not a comparison of zeros


def _torch_window(frames, targets):
    """``seqdata`` frames and targets as the references' window: a list of NCHW
    ``(color, depth, motion, jitter, reset)`` tensors and NCHW targets."""
    import torch

    nchw = lambda x: torch.from_numpy(np.ascontiguousarray(np.moveaxis(x, -1, 1)))  # noqa: E731
    window = [(nchw(frames.color[t]), nchw(frames.depth[t]), nchw(frames.motion[t]),
               torch.from_numpy(frames.jitter[t]), torch.from_numpy(frames.reset[t]))
              for t in range(len(frames.color))]
    return window, [nchw(y) for y in targets]


def _reference_training_matches(name, ref, net, factor, loss_frames=3, **step_args):
    """The reference's ``window_loss`` and its gradients (torch autograd) against jtus's
    ``rollout.window_loss`` with the model's own loss, from the same weights, over a
    5-frame window with motion and a camera cut: what the bench times beside jtus's
    training step is the same computation."""
    import torch

    frames, targets = seqdata.sequence(T=5, B=2, h=32 // factor, w=32 // factor,
                                       factor=factor, seed=4, max_motion=1.5, reset_at=(3, 1))
    frames.reset[0] = True
    model = models.build(name, factor)
    params = jax.tree_util.tree_map(jnp.asarray, ref.to_jtus(net))
    jf, jt = seqdata.to_jax((frames, targets))
    loss_fn = losses.make(models.spec(name).loss, factor)

    def jtus_loss(p):
        carry = rollout.start(rollout.first_state(model, jf), jt[0])
        return rollout.window_loss(model.step, loss_fn, p, carry, jf, jt,
                                   loss_frames=loss_frames)[0]

    want, want_grads = jax.jit(jax.value_and_grad(jtus_loss))(params)
    window, ys = _torch_window(frames, targets)
    got = ref.window_loss(net, window, ys, factor, loss_frames, **step_args)
    got.backward()
    with torch.no_grad():  # the gradients in jtus's layout, through the same converter
        for p in net.parameters():  # None: a weight set no frame's jitter phase chose
            p.copy_(torch.zeros_like(p) if p.grad is None else p.grad)
    got_grads = ref.to_jtus(net)
    np.testing.assert_allclose(float(got.detach()), float(want), rtol=1e-5)
    scale = max(float(jnp.abs(g).max()) for g in jax.tree_util.tree_leaves(want_grads))
    # float32 through five frames of each network: measured 1.1e-5 (NSRR) and 7e-7 (KPN) of
    # the largest gradient; one frame fewer in NSRR's loss moves them by 8e-3 of it
    for a, b in zip(jax.tree_util.tree_leaves(want_grads), jax.tree_util.tree_leaves(got_grads)):
        np.testing.assert_allclose(b, a, rtol=0, atol=5e-5 * scale)
    assert scale > 1e-4  # not a comparison of zeros


def test_nsrr_reference_training_step_computes_jtus_loss_and_gradients():
    import torch

    from jtus.reference import torch_nsrr

    torch.manual_seed(3)
    _reference_training_matches("nsrr", torch_nsrr, torch_nsrr.NSRR(), 2)


def test_kpn_reference_training_step_computes_jtus_loss_and_gradients():
    """KPN's reference with its alias-masked reference, gradient and temporal loss."""
    import torch

    from jtus.reference import torch_kpn

    phases = torch.from_numpy(np.asarray(kpn.Config(factor=4).phases(), np.float32))
    torch.manual_seed(5)
    _reference_training_matches("kpn", torch_kpn, torch_kpn.KPN(len(phases)), 4,
                                phases=phases)


def test_nsrr_normalized_exposure_scales_outputs_with_the_colour(factor=2):
    """NSRR-fast with ``exposure="normalized"``: over 6 frames with motion and a camera
    cut (the previous-frame window fills and rolls), the video's colour times 8 or times
    1/4 gives the outputs times 8 or 1/4 (powers of two, so the networks read the same
    numbers; asserted to 1e-6 relative). NSRR fed absolute colour does not, which is
    what the test catches if the normalization is dropped at either end."""
    frames, _ = seqdata.sequence(T=6, B=2, h=16 // factor, w=16 // factor, factor=factor,
                                 seed=7, max_motion=1.5, reset_at=(4, 1))
    jf = seqdata.to_jax(frames)

    def run(scale, exposure):
        m = models.build("nsrr-fast", factor, exposure=exposure)
        fr = jf._replace(color=jf.color * scale)
        return rollout.outputs(m.step, m.init(jax.random.PRNGKey(1)),
                               rollout.first_state(m, fr), fr)[0]

    outs = np.asarray(run(1.0, "normalized"))
    assert np.abs(outs).max() > 1e-2
    for scale in (8.0, 0.25):
        np.testing.assert_allclose(np.asarray(run(scale, "normalized")), scale * outs,
                                   rtol=1e-6, atol=1e-7)
    absolute = np.asarray(run(1.0, "absolute"))
    assert np.abs(np.asarray(run(8.0, "absolute")) - 8.0 * absolute).max() > 1e-3
    # the cost model counts the frame's mean, the scaled LR colour and the scaled output
    config = nsrr.Config(factor=factor, fast=True, exposure="normalized")
    absolute_cost = nsrr.cost(dataclasses.replace(config, exposure="absolute"), 64, 64)
    assert (nsrr.cost(config, 64, 64).flops - absolute_cost.flops
            == (64 // factor) ** 2 * 6 + 64 * 64 * 3)


def test_nsrr_reset_forgets_the_previous_features():
    """NSRR on a reset frame runs as if its previous-frame features were zero (its
    state at a sequence start). Catches: the reset flag ignored (garbage features
    reweighted into the output)."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=2, B=2, reset_at=(1, 0)))
    model = nsrr.make(nsrr.Config(factor=4, fast=True))
    params = model.init(jax.random.PRNGKey(0))
    frame = seqdata.at(frames, 1)
    zero = model.init_state(frame)
    garbage = nsrr.State(jnp.asarray(np.random.default_rng(2).uniform(
        size=zero.previous.shape), jnp.float32))
    out_zero, _ = model.step(params, zero, frame)
    out_garbage, _ = model.step(params, garbage, frame)
    np.testing.assert_allclose(out_garbage[0], out_zero[0], rtol=0, atol=1e-6)
    assert float(jnp.abs(out_garbage[1] - out_zero[1]).max()) > 1e-4  # control


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
    frame = seqdata.at(frames, 0)
    assert len(set(map(tuple, np.asarray(frame.jitter).tolist()))) > 1  # several phases
    model = kpn.make(kpn.Config(factor=4))
    params = model.init(jax.random.PRNGKey(1))
    step = jax.jit(model.step)  # one compiled step per batch size, not one per operation
    out, state = step(params, model.init_state(frame), frame)
    for b in range(5):
        one = jax.tree_util.tree_map(lambda x: x[b:b + 1], frame)
        o, st = step(params, model.init_state(one), one)
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
    frame = seqdata.at(frames, 1)
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
    frame = seqdata.at(moving, 1)
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


def _mlp_numpy(params, color, depth, f, gamma, slope, near, far, jitter=None, mode="ignore",
               base="mean", contrast=False):
    """Spencer's MLP upscaler written out per LR pixel in numpy (float64): the 5x5
    colour patch of each channel and the 5x5 linear-depth patch, both minus their
    means, boosted by sign(r)|r|^(1/gamma); two leaky-ReLU layers; f*f outputs plus the
    colour mean, placed at sub-pixel (dy, dx) = divmod(k, f) (jtus's choices: raster
    patch order, colour before depth, edge-replicated borders). ``mode="input"``: the
    offset of ``jitter [B,2]`` from the pixel centre (x, y) follows as two more inputs;
    ``"dejitter"``: colour and linear depth are first read at the pixel centres.
    ``contrast``: each mean-removed patch divided by its mean absolute deviation plus
    1e-4, the outputs multiplied by the colour patch's; ``base="jau"``: the outputs
    added to jitter-aligned bilinear up-sampling instead of the colour mean."""
    from jtus.data.conventions import linearize_depth

    B, h, w, _ = color.shape
    color_in = color
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
                dr = dpatch - dpatch.mean()
                for c in range(3):
                    cpatch = pc[b, i:i + 5, j:j + 5, c].reshape(-1)
                    cr, scale = cpatch - cpatch.mean(), 1.0
                    if contrast:
                        scale = np.abs(cr).mean()
                        cr, dr_ = cr / (scale + 1e-4), dr / (np.abs(dr).mean() + 1e-4)
                    else:
                        dr_ = dr
                    v = np.concatenate([boost(cr), boost(dr_)]
                                       + ([np.asarray(jitter[b], np.float64) - 0.5]
                                          if mode == "input" else []))
                    for k, (W, bias) in enumerate(Ws):
                        v = v @ W + bias
                        if k < len(Ws) - 1:
                            v = np.where(v > 0, v, slope * v)
                    v = v * scale + (cpatch.mean() if base == "mean" else 0.0)
                    for s in range(f * f):
                        dy, dx = divmod(s, f)
                        out[b, i * f + dy, j * f + dx, c] = v[s]
    if base == "jau":
        out += seqdata.jau_reference(np.asarray(color_in, np.float64), jitter, f)
    return out


def test_mlp_forward_and_gamma_against_numpy():
    """Catches: gamma ignored (or only 2.0 boosted) or applied as r^gamma, the leaky
    ReLU's slope left at its default, the mean not added back, sub-pixels shuffled in
    another order, the jitter input dropped, swapped or not centred, the
    de-jittering read on the wrong side or left out for depth."""
    from jtus.models import mlp

    frames, _ = seqdata.to_jax(seqdata.sequence(T=1, B=2, h=6, w=5))
    frame = seqdata.at(frames, 0)
    frame = frame._replace(jitter=jnp.asarray([[0.125, 0.875], [0.625, 0.25]], jnp.float32))
    for gamma, jit, slope, base, contrast in (
            (1.0, "dejitter", 0.01, "mean", False), (2.2, "dejitter", 0.01, "mean", False),
            (2.0, "input", 0.2, "mean", False), (1.0, "ignore", 0.01, "mean", False),
            (1.0, "input", 0.01, "jau", True), (2.0, "dejitter", 0.01, "jau", False),
            (1.0, "ignore", 0.01, "mean", True)):
        config = mlp.Config(factor=4, gamma=gamma, jitter=jit, slope=slope, base=base,
                            contrast=contrast)
        params = mlp.init(jax.random.PRNGKey(1), config)
        # a trained output layer (the JAU base starts it at zero)
        params["layers"][-1] = mlp.init(jax.random.PRNGKey(2))["layers"][-1]
        got = np.asarray(mlp.step(params, (), frame, config)[0])
        want = _mlp_numpy(params, np.asarray(frame.color), np.asarray(frame.depth), 4, gamma,
                          config.slope, config.near, config.far, np.asarray(frame.jitter), jit,
                          base, contrast)
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-6,  # float32: 2.1e-7 measured
                                   err_msg=f"{gamma} {jit} {base} {contrast}")
    with pytest.raises(ValueError, match="jitter"):
        mlp.Config(jitter="centre")
    with pytest.raises(ValueError, match="base"):
        mlp.Config(base="bicubic")


@pytest.mark.parametrize("jit", ["ignore", "input", "dejitter"])
def test_untrained_mlp_on_the_jau_base_is_jau(jit):
    """With ``base="jau"`` the output layer starts at zero, so the untrained upscaler is
    jitter-aligned bilinear up-sampling exactly, bit for bit."""
    from jtus.models import jau

    frames, _ = seqdata.to_jax(seqdata.sequence(T=1, B=2, h=6, w=5))
    frame = seqdata.at(frames, 0)._replace(jitter=jnp.asarray([[0.125, 0.875], [0.625, 0.25]]))
    config = mlp.Config(factor=4, jitter=jit, base="jau", contrast=True)
    got = mlp.step(mlp.init(jax.random.PRNGKey(1), config), (), frame, config)[0]
    want = jau.step({}, (), frame, jau.Config(factor=4))[0]
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))


def test_contrast_normalized_mlp_scales_its_correction_with_the_contrast(monkeypatch):
    """With ``contrast``, colour a * c + d upscales to a * (the upscale of c) + d (exactly
    but for rounding once the ``EPS`` added to the deviation is 0), and a flat frame
    comes out flat at any brightness, whatever the weights."""
    frames, _ = seqdata.to_jax(seqdata.sequence(T=1, B=2, h=6, w=5))
    frame = seqdata.at(frames, 0)._replace(jitter=jnp.asarray([[0.125, 0.875], [0.625, 0.25]]))
    config = mlp.Config(factor=4, jitter="input", base="jau", contrast=True)
    params = mlp.init(jax.random.PRNGKey(1), config)
    params["layers"][-1] = mlp.init(jax.random.PRNGKey(2))["layers"][-1]
    with monkeypatch.context() as m:
        m.setattr(mlp, "EPS", 0.0)
        out = np.asarray(mlp.step(params, (), frame, config)[0])
        for a, d in ((0.01, 0.002), (3.0, -0.5)):
            moved = np.asarray(mlp.step(params, (), frame._replace(color=a * frame.color + d),
                                        config)[0])
            np.testing.assert_allclose(moved, a * out + d, rtol=0, atol=1e-6 * max(a, 1))
    flat = frame._replace(color=jnp.full_like(frame.color, 0.003))
    np.testing.assert_allclose(np.asarray(mlp.step(params, (), flat, config)[0]), 0.003,
                               rtol=0, atol=1e-9)


@pytest.mark.parametrize("jit", ["ignore", "input", "dejitter"])
def test_mlp_computes_in_float32_whatever_the_frame_type(jit):
    """The MLP computes in float32, like its parameters: a half-precision frame and a
    float64 frame (64-bit types on) give exactly the output of the same values in
    float32, as float32. Catches: colour, depth or jitter left in the frame's own type
    (``astype(None)`` is float32 only while 64-bit types are off)."""
    from jtus.models import mlp

    frames, _ = seqdata.to_jax(seqdata.sequence(T=1, B=2, h=6, w=5))
    frame = seqdata.at(frames, 0)._replace(jitter=jnp.asarray([[0.0078125, 0.875], [0.625, 0.25]]))
    config = mlp.Config(factor=4, jitter=jit)
    params = mlp.init(jax.random.PRNGKey(1), config)
    for dtype in (jnp.float16, jnp.float64):
        with jax.enable_x64(dtype == jnp.float64):
            typed = seqdata.cast_frame(frame, dtype)
            assert typed.color.dtype == dtype
            want = mlp.step(params, (), seqdata.cast_frame(typed, jnp.float32), config)[0]
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
    frame = seqdata.at(frames, 1)
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
    want, want_state = rollout.outputs(model.step, params, model.init_state(seqdata.first(frames)),
                                       frames)
    with jax.enable_x64(True):
        fr = seqdata.cast_frame(frames, jnp.float64)
        assert fr.color.dtype == jnp.float64
        state0 = model.init_state(seqdata.first(fr))
        got, got_state = rollout.outputs(model.step, params, state0, fr)
        for g, w in zip(jax.tree_util.tree_leaves((got, got_state)),
                        jax.tree_util.tree_leaves((want, want_state))):
            assert g.dtype == w.dtype, (g.dtype, w.dtype)
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
        assert got.dtype == jnp.float32
