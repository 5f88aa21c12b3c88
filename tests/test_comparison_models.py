"""NSRR, kernel-prediction TAA and the MLP upscaler: structure, PyTorch parity, training."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jtus import evaluate, models, recipe, rollout, train
from jtus.config import PRESETS
from jtus.data import dataset
from jtus.models import kpn, mlp, nsrr
from jtus.models.base import param_count
from tests import seqdata, torch_models


def _frames(T=3, B=2, h=8, factor=4, seed=0):
    return seqdata.to_jax(seqdata.sequence(T=T, B=B, h=h, w=h, factor=factor, seed=seed))


def _first(tree):
    return jax.tree_util.tree_map(lambda x: x[0], tree)


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
    outs, _ = rollout.outputs(m.step, params, m.init_state(_first(frames)), frames)
    assert outs.shape == (2, 1, 32, 32, 3) and np.all(np.isfinite(np.asarray(outs)))
    assert nsrr.Config(fast=True).unet_widths() == (32, 16, 32, 32, 64, 64, 32, 32, 16)
    assert nsrr.Config(fast=True, unet=tuple(range(1, 10))).unet_widths() == \
        (1, 1, 1, 2, 2, 3, 3, 4, 4)
    assert nsrr.Config(unet=widths).unet_widths() == widths


@pytest.mark.parametrize("changes,message", [
    ({"extract": (32, 32, 7)}, r"^extract: the last width must be 8, got \(32, 32, 7\)$"),
    ({"unet": (64,) * 8}, r"^unet: expected 9 widths \(the 10th layer outputs 3\), got "
                          r"\(64, 64, 64, 64, 64, 64, 64, 64\)$"),
    ({"frames": 0}, r"^frames: expected >= 1, got 0$")])
def test_nsrr_config_names_the_bad_field(changes, message):
    """A bad NSRR setting is refused with an error that starts with its field's name and
    says what was expected and what it got; the boundaries are accepted."""
    with pytest.raises(ValueError, match=message):
        nsrr.Config(**changes)
    assert nsrr.Config(frames=1, extract=(8,)).frames == 1


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
    cur, _ = nsrr.features(params, _first(frames), config)
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
    state = model.init_state(_first(frames))
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
    fr = _first(frames)
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


def test_kpn_uses_the_weight_set_of_the_jitter_phase():
    frames, _ = _frames(T=1, B=2)
    config = kpn.Config()
    params = kpn.init(jax.random.PRNGKey(4), config)
    fr = _first(frames)
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
    fr = _first(frames)
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
        carry = rollout.start(model.init_state(_first(frames)), targets[0])
        ts, _, stats = step(ts, carry, frames, targets)
        seen.append(float(stats["loss"]))
    assert seen[-1] < seen[0], seen
    train.train_and_evaluate(config, tmp_path, progress=False)
    out = tmp_path / "eval"
    assert evaluate.main(["--dataset", tiny_data, "--factor", "4", "--models", "jau",
                          f"{name}={tmp_path / 'checkpoint.msgpack'}", "--out", str(out),
                          "--quiet"]) == 0
    assert (out / "crops_x4.png").exists()
    summary = json.loads((out / "results.json").read_text())
    assert np.isfinite(summary["4"][name]["psnr"])


def test_registry_builds_every_model():
    frames, _ = _frames(T=2, B=1)
    for name in models.NAMES:
        m = models.build(name, 4)
        outs, _ = rollout.outputs(m.step, m.init(jax.random.PRNGKey(0)),
                                  m.init_state(_first(frames)), frames)
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


@pytest.mark.parametrize("factor", [4, 2])
def test_kpn_matches_an_independent_torch_kpn(factor):
    """jtus's KPN against tests/torch_kpn.py (its own parameter layout, Catmull-Rom,
    input preparation and colour mix, from Herveau et al. and docs/comparison.md) over
    6 frames with motion, a camera cut in one element and the weight set of each
    frame's jitter phase."""
    import torch

    from jtus import models, rollout
    from tests import torch_kpn

    frames, _ = seqdata.sequence(T=6, B=2, h=24 // factor, w=32 // factor, factor=factor,
                                 seed=11, max_motion=1.5, reset_at=(3, 1))
    frames.reset[0] = True
    model = models.build("kpn", factor)
    phases = np.asarray(model.config.phases(), np.float32)
    torch.manual_seed(0)
    net = torch_kpn.KPN(len(phases))
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
                                     factor)
            ref.append(out.numpy().transpose(0, 2, 3, 1))
    # float32; measured max 3.0e-7 (both factors)
    np.testing.assert_allclose(np.asarray(outs), np.stack(ref), rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(final.history), fb.numpy().transpose(0, 2, 3, 1),
                               rtol=0, atol=1e-6)
    assert np.abs(np.asarray(outs)).max() > 0.1  # not a comparison of zeros


@pytest.mark.parametrize("factor", [4, 2])
def test_nsrr_matches_an_independent_torch_nsrr(factor):
    """jtus's NSRR against tests/torch_nsrr.py (its own nn.Sequential layout converted
    by a function, zero-up-sampling, iterated warping and reweighting from the paper's
    text) over 7 frames (the 4-frame window rolls) with motion and a camera cut."""
    import torch

    from jtus import models, rollout
    from tests import torch_nsrr

    frames, _ = seqdata.sequence(T=7, B=2, h=32 // factor, w=32 // factor, factor=factor,
                                 seed=12, max_motion=1.5, reset_at=(4, 1))
    frames.reset[0] = True
    model = models.build("nsrr", factor)
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
                                        torch.from_numpy(frames.reset[t]), factor)
            ref.append(out.numpy().transpose(0, 2, 3, 1))
    ref = np.stack(ref)
    # float32 through a 10-layer U-Net; measured max 2.6e-8 on outputs up to 0.07
    np.testing.assert_allclose(np.asarray(outs), ref, rtol=0, atol=2e-7)
    assert np.abs(ref).max() > 1e-2  # not a comparison of zeros
