"""The rollout helper with DLCTUS: scan against a Python loop, BPTT/TBPTT, remat,
formulations, resets, float64 gradients, and one trace across TBPTT windows."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.test_util import check_grads

from jtus import losses, models, rollout, sampling, train
from jtus.models import dlctus
from jtus.models.base import DTYPES, param_count
from tests import seqdata


# The float64 identities of the scan, the loss windows and the step's parts (below) hold
# for any depth of the trunk; their DLCTUS has one residual block, a smaller program to
# compile (the six took 99 s against 119 s with four, one process). The four-block
# network is checked against PyTorch in test_dlctus_torch.py and through the float32
# rollouts here.
IDENTITY_BLOCKS = 1


def _lift_last_bias(params, blocks):
    """The last convolution's bias raised by 0.5, so the network's outputs o sit inside
    (0, 1) rather than on the clamp at 0."""
    last = params[f"block{blocks}"]["conv2"]
    last["bias"] = last["bias"] + 0.5


def _setup(T=6, factor=4, seed=0, config=None, dtype=np.float32, **kw):
    config = config or dlctus.Config(factor=factor,
                                     dtype="float64" if dtype == np.float64 else "float32")
    frames, targets = seqdata.sequence(T=T, B=2, h=8 * 4 // factor, w=8 * 4 // factor,
                                       factor=factor, seed=seed, dtype=dtype, **kw)
    model = dlctus.make(config)
    params = model.init(jax.random.PRNGKey(seed))
    _lift_last_bias(params, config.blocks)
    if dtype == np.float64:
        params = jax.tree_util.tree_map(lambda x: x.astype(jnp.float64), params)
    frames, targets = seqdata.to_jax((frames, targets))
    return model, params, frames, targets


def test_param_count_matches_thesis_network():
    # down 4x4x8x32 + 32; four blocks of two 3x3x32x32 + 32 convolutions.
    params = dlctus.init(jax.random.PRNGKey(0))
    assert param_count(params) == (4 * 4 * 8 * 32 + 32) + 4 * 2 * (3 * 3 * 32 * 32 + 32) == 78112


def _interior_params(params, config):
    """Weights small enough that the network's outputs o stay strictly inside (0, 1):
    no clamp is on its boundary, where the subgradient is decided by the last ulp."""
    params = jax.tree_util.tree_map(lambda x: 0.2 * x, params)
    _lift_last_bias(params, config.blocks)
    return params


def test_scan_equals_python_loop_values_and_vjp(x64):
    config = dlctus.Config(factor=4, dtype="float64", blocks=IDENTITY_BLOCKS)
    model, params, frames, _ = _setup(T=5, config=config, dtype=np.float64)
    params = _interior_params(params, config)
    frames = frames._replace(reset=None)
    rng = np.random.default_rng(0)
    state0 = dlctus.State(jnp.asarray(rng.uniform(0.1, 0.9, size=(2, 32, 32, 4))))

    def scanned(p, s):
        return rollout.outputs(model.step, p, s, frames)

    step = jax.jit(model.step)  # one compiled step, called from a Python loop

    def looped(p, s):
        outs = []
        for t in range(5):
            out, s = step(p, s, jax.tree_util.tree_map(lambda x: x[t], frames))
            outs.append(out)
        return jnp.stack(outs), s

    pre = dlctus.prepare_frame(seqdata.first(frames), model.config)
    net_in, _, _ = dlctus.reproject(state0, pre, model.config)
    o = dlctus.network(params, net_in, model.config)
    assert 0.05 < float(o.min()) and float(o.max()) < 0.95
    (o1, s1), vjp1 = jax.vjp(scanned, params, state0)
    (o2, s2), vjp2 = jax.vjp(looped, params, state0)
    np.testing.assert_allclose(o1, o2, rtol=0, atol=1e-13)
    np.testing.assert_allclose(s1.history, s2.history, rtol=0, atol=1e-13)
    ct = (jnp.asarray(rng.normal(size=o1.shape)),
          dlctus.State(jnp.asarray(rng.normal(size=s1.history.shape))))
    g1, g2 = vjp1(ct), vjp2(ct)
    for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g2)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)


def test_video_runs_from_the_first_state_float64(x64):
    """rollout.video (evaluation, figures, the upsample CLI): the step looped in Python
    from ``init_state`` of the first frame, and a clear error on non-finite input."""
    model, params, frames, _ = _setup(T=4, dtype=np.float64)
    got = rollout.video(model, params, frames)
    s, want = model.init_state(seqdata.first(frames)), []
    for t in range(4):
        out, s = model.step(params, s, jax.tree_util.tree_map(lambda x: x[t], frames))
        want.append(out)
    np.testing.assert_allclose(got, jnp.stack(want), rtol=0, atol=1e-13)
    bad = frames._replace(color=frames.color.at[2, 0, 1, 1, 0].set(jnp.nan))
    with pytest.raises(ValueError, match="color"):
        rollout.video(model, params, bad)


def test_check_grads_float64_three_frames(x64):
    config = dlctus.Config(factor=4, warp="bilinear", dtype="float64")
    model, params, frames, targets = _setup(T=3, config=config, dtype=np.float64)
    frames = frames._replace(reset=None)
    state0 = model.init_state(seqdata.first(frames))
    sub = {"down": params["down"], "block4": params["block4"]}

    def loss(p):
        full = dict(params, **p)
        outs, s = rollout.outputs(model.step, full, state0, frames)
        return jnp.mean((outs - targets) ** 2) + jnp.mean(s.history[..., 3])

    check_grads(loss, (sub,), order=1, modes=("rev",), eps=1e-6, atol=1e-6, rtol=1e-5)


def _loss_value_and_grad(model, params, frames, targets, K, **kw):
    carry = rollout.start(model.init_state(seqdata.first(frames)), targets[0])

    def f(p):
        return rollout.window_loss(model.step, losses.make("st-linear", 4, theta=0.5), p,
                                   carry, frames, targets, loss_frames=K, **kw)

    return jax.jit(jax.value_and_grad(f, has_aux=True))(params)


# Left out of the default run (82 s compiling in CI of 28b6886): rollout's remat and
# unroll bookkeeping is checked in float64 on a toy model by test_rollout_toy.py in
# seconds; this keeps DLCTUS's own step (its custom convolution backward) under
# jax.checkpoint, which no default training uses (Config.remat is False).
@pytest.mark.long
def test_remat_and_unroll_equal_plain():
    model, params, frames, targets = _setup(T=6)
    (l0, _), g0 = _loss_value_and_grad(model, params, frames, targets, 3)
    for kw in ({"remat": True}, {"remat": "dots"}, {"unroll": True}):
        (l1, _), g1 = _loss_value_and_grad(model, params, frames, targets, 3, **kw)
        np.testing.assert_allclose(l1, l0, rtol=1e-6)
        for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g0)):
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-7)


# separable; from coordinates (bicubic5 in the long run: the same hoisting, 30 s)
@pytest.mark.parametrize("warp", ["bicubic", pytest.param("bicubic5", marks=pytest.mark.long)])
def test_hoisted_preparation_equals_the_plain_step_float64(x64, warp):
    """``Model.prepare`` run for the whole window before the scan, then ``advance``
    inside it, gives the plain scan's loss and gradients (float64, 1e-12), with a reset
    in the middle of one batch element, HDR colour with an exposure per frame, and a
    TBPTT cut (``keep_at``); and ``step`` is ``advance`` after ``prepare``."""
    config = dlctus.Config(factor=4, warp=warp, hdr=True, dtype="float64", blocks=IDENTITY_BLOCKS)
    model, params, frames, targets = _setup(T=6, config=config, dtype=np.float64)
    frames = frames._replace(color=frames.color * 4.0,
                             exposure=jnp.linspace(0.2, 0.5, 12).reshape(6, 2),
                             reset=jnp.zeros((6, 2), bool).at[0].set(True).at[3, 1].set(True))
    carry = rollout.start(model.init_state(seqdata.first(frames)), targets[0])
    loss_fn = losses.make("st-linear", 4, theta=0.5)
    advance, prepare = rollout.parts(model)
    assert prepare is not None

    def f(p, hoist):
        return rollout.window_loss(advance if hoist else model.step, loss_fn, p, carry, frames,
                                   targets, loss_frames=3, keep_at=2,
                                   prepare=prepare if hoist else None)

    # compiled whole: op-by-op dispatch of this float64 gradient took 169 s against
    # 122 s compiled (both plain and hoisted, one loaded core)
    vg = jax.jit(jax.value_and_grad(f, has_aux=True), static_argnums=1)
    (l0, (c0, k0)), g0 = vg(params, False)
    (l1, (c1, k1)), g1 = vg(params, True)
    np.testing.assert_allclose(l1, l0, rtol=1e-12)
    leaves = jax.tree_util.tree_leaves
    for a, b in zip(leaves((g1, c1, k1)), leaves((g0, c0, k0))):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    frame = seqdata.first(frames)
    out0, s0 = model.step(params, carry.state, frame)
    out1, s1 = advance(params, carry.state, prepare(frame))
    np.testing.assert_array_equal(out1, out0)
    np.testing.assert_array_equal(s1.history, s0.history)


def test_remat_rejects_an_unknown_policy():
    model, params, frames, targets = _setup(T=2)
    with pytest.raises(ValueError, match="remat: expected"):
        _loss_value_and_grad(model, params, frames, targets, 1, remat="everything")
    with pytest.raises(ValueError, match="unroll: remat='reverse'"):  # it would be ignored
        _loss_value_and_grad(model, params, frames, targets, 1, remat="reverse", unroll=2)


def test_tbptt_with_full_window_equals_bptt():
    config = dlctus.Config(factor=4, blocks=IDENTITY_BLOCKS)
    model, params, frames, targets = _setup(T=6, config=config)
    (l0, _), g0 = _loss_value_and_grad(model, params, frames, targets, 2)
    carry = rollout.start(model.init_state(seqdata.first(frames)), targets[0])
    results, _ = seqdata.tbptt_grads(model.step, losses.make("st-linear", 4, theta=0.5), params,
                                     carry, frames, targets, k1=2, k2=6)
    assert len(results) == 1
    l1, g1 = results[0]
    np.testing.assert_allclose(l1, l0, rtol=1e-6)
    for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g0)):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-8)


def test_tbptt_windows_plan():
    assert rollout.tbptt_windows(8, 2, 4) == [(0, 4), (2, 6), (4, 8)]
    assert rollout.tbptt_windows(6, 3, 3) == [(0, 3), (3, 6)]
    with pytest.raises(ValueError, match="multiple of"):
        rollout.tbptt_windows(7, 2, 4)
    with pytest.raises(ValueError, match="k1 <= k2"):
        rollout.tbptt_windows(8, 4, 2)


def test_tbptt_windows_chain_states():
    """Each window starts from the state after k1 frames of the previous one: the
    carried history equals the plain rollout's at that time."""
    model, params, frames, targets = _setup(T=8)
    carry = rollout.start(model.init_state(seqdata.first(frames)), targets[0])
    _, last = seqdata.tbptt_grads(model.step, losses.make("l1", 4), params, carry, frames,
                                  targets, k1=2, k2=4)
    outs, _ = rollout.outputs(model.step, params, model.init_state(seqdata.first(frames)), frames)
    # The last window is [4, 8); the carry kept after its first k1=2 frames is time 6.
    np.testing.assert_allclose(last.prev_out, outs[5], atol=1e-6)


@pytest.mark.parametrize("factor", [2, 4])
@pytest.mark.parametrize("formulation", ["opt1", "opt2"])
def test_formulations_equal_standard(formulation, factor):
    _, params, frames, _ = _setup(T=4, factor=factor)
    model = dlctus.make(dlctus.Config(factor=factor, formulation="standard"))
    other = dlctus.make(dlctus.Config(factor=factor, formulation=formulation))
    s0 = model.init_state(seqdata.first(frames))
    o1, s1 = rollout.outputs(model.step, params, s0, frames)
    o2, s2 = rollout.outputs(other.step, params, s0, frames)
    np.testing.assert_allclose(o2, o1, rtol=0, atol=1e-6)
    np.testing.assert_allclose(s2.history, s1.history, rtol=0, atol=1e-6)


# 2x is in the long run (30 s of compiling on 2 cores): the same kernel-row selection
@pytest.mark.parametrize("factor", [pytest.param(2, marks=pytest.mark.long), 4])
def test_opt2_gradients_equal_standard_float64(x64, factor):
    # opt2 never builds the zero-up-sampled input: its kernel rows are picked per frame
    # from the jitter; the parameter gradients must still be the standard network's.
    _, params, frames, targets = _setup(T=3, factor=factor, dtype=np.float64)

    def loss(p, formulation):
        m = dlctus.make(dlctus.Config(factor=factor, dtype="float64", formulation=formulation))
        outs, _ = rollout.outputs(m.step, p, m.init_state(seqdata.first(frames)), frames)
        return jnp.mean(jnp.abs(outs - targets))

    g1 = jax.grad(loss)(params, "standard")
    g2 = jax.grad(loss)(params, "opt2")
    for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g2)):
        np.testing.assert_allclose(b, a, rtol=1e-10, atol=1e-13)
    assert float(jnp.abs(g1["down"]["kernel"]).max()) > 1e-4  # the test sees a gradient


@pytest.mark.parametrize("field,value,says", [
    ("factor", 3, "factor: expected 2 or 4, got 3"),
    ("near", 0.0, "near/far: expected 0 < near < far, got 0.0, 100.0"),
    ("far", 0.05, "near/far: expected 0 < near < far, got 0.1, 0.05"),
    ("far", 0.1, "near/far: expected 0 < near < far, got 0.1, 0.1"),
    ("warp", "cubic", f"warp: expected one of {sampling.METHODS}, got 'cubic'"),
    ("formulation", "opt3", "formulation: expected one of ('standard', 'opt1', 'opt2'), "
                            "got 'opt3'"),
    ("channels", 16, "channels: the pixel shuffle to 2 outputs needs 32, got 16"),
    ("conv_backward", "manual", "conv_backward: expected one of ('auto', 'autodiff', "
                                "'custom', 'winograd'), "
                                "got 'manual'"),
    ("dtype", "int8", f"dtype: expected one of {tuple(DTYPES)}, got 'int8'"),
])
def test_config_names_the_bad_field(field, value, says):
    """A bad DLCTUS setting is refused with a message naming the field, what was
    expected and what came (compared whole)."""
    with pytest.raises(ValueError) as err:
        dlctus.Config(**{field: value})
    assert str(err.value) == says
    dlctus.Config(factor=2, near=0.05, far=50.0)  # control: valid fields pass


def test_step_is_advance_of_the_prepared_frame():
    """``dlctus.step`` (the module's plain step, which engines and references call) is
    the model's ``step`` (``advance`` of ``prepare_frame``), to the bit, on a frame that
    reads a history, with a config other than the default. Catches: a mutated argument
    in ``step`` (the config dropped: the default's then), which no model path runs."""
    # a config unlike the default in every field the step reads
    config = dlctus.Config(factor=2, warp="bilinear", formulation="standard")
    model, params, frames, _ = _setup(T=2, config=config, factor=2)
    state = model.init_state(seqdata.first(frames))
    frame = jax.tree_util.tree_map(lambda x: x[1], frames)
    got = dlctus.step(params, state, frame, model.config)
    want = model.step(params, state, frame)
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))


@pytest.mark.parametrize("formulation", ["standard", "opt1", "opt2"])
def test_network_computes_in_its_dtype(formulation):
    """With ``dtype="bfloat16"`` the network (down-sampling convolution and trunk) runs
    in bfloat16 and returns it; its values stay within bfloat16 rounding of the float32
    network's (0.0101 at most measured on activations up to 1.26; bound 0.02). Catches:
    the parameters or the input cast to ``None`` (float32), which would run it in float32."""
    model, params, frames, _ = _setup(T=2)
    state = model.init_state(seqdata.first(frames))
    frame = jax.tree_util.tree_map(lambda x: x[1], frames)
    c32 = dlctus.Config(factor=4, formulation=formulation)
    c16 = dlctus.Config(factor=4, formulation=formulation, dtype="bfloat16")
    x, _, _ = dlctus.reproject(state, dlctus.prepare_frame(frame, c32), c32)
    a, b = dlctus.network(params, x, c32), dlctus.network(params, x, c16)
    assert a.dtype == jnp.float32 and b.dtype == jnp.bfloat16
    np.testing.assert_allclose(np.asarray(b, np.float32), a, rtol=0, atol=0.02)


def test_step_labels_its_stages_for_the_profile():
    """The step's operations (its lowered HLO) carry the stage scopes ``python -m jtus.profile``
    splits the time by (``Spec.stages``: input up-sampling, reprojection, network,
    output). Catches: a renamed scope, whose time the profile would file under "other"."""
    from jtus import profile

    model, params, frames, _ = _setup(T=2)
    state = model.init_state(seqdata.first(frames))
    frame = jax.tree_util.tree_map(lambda x: x[1], frames)
    # the lowered HLO, not the compiled one: a compiled program can come from the
    # persistent compilation cache, whose key leaves op names out (a renamed scope then
    # reads back the original's names; found by mutation testing)
    hlo = jax.jit(model.step).lower(params, state, frame).as_text(dialect="hlo",
                                                                  debug_info=True)
    assert models.spec("dlctus").stages == (
        "input_upsampling", "reprojection", "network", "output")
    for stage in models.spec("dlctus").stages:
        assert f"/{stage}/" in hlo, stage
    assert "/loss/" not in hlo  # control: a stage the step does not run is absent
    # every operation is in a stage but the slice that takes the RGB out of the new
    # history (the other op names are the arguments': params[...], state.history)
    ops = re.findall(r'op_name="(jit\([^"]*)"', hlo)
    outside = {op.rsplit("/", 1)[1] for op in ops
               if profile.classify("", "", op)[0] == "other"}
    assert len(ops) > 100 and outside == {"slice"}, outside


def test_reset_equals_fresh_init_state():
    model, params, frames, _ = _setup(T=4, reset_at=(2, 1))
    s0 = model.init_state(seqdata.first(frames))
    outs, _ = rollout.outputs(model.step, params, s0, frames)
    # Sample 1 restarted at frame 2: same as a fresh rollout from frame 2 on.
    tail = jax.tree_util.tree_map(lambda x: x[2:], frames)
    fresh, _ = rollout.outputs(model.step, params, model.init_state(seqdata.first(tail)), tail)
    np.testing.assert_allclose(outs[2:, 1], fresh[:, 1], rtol=0, atol=1e-6)
    assert np.abs(np.asarray(outs[2:, 0] - fresh[:, 0])).max() > 1e-3  # sample 0 did not reset


def test_train_step_traces_once_across_tbptt_windows():
    model, params, frames, targets = _setup(T=8)
    frames = frames._replace(reset=frames.reset.at[0].set(True))
    traces = []
    base = losses.make("l1", 4)

    def counted(*args):
        traces.append(1)
        return base(*args)

    opt = optax.adam(1e-3)
    step = train.make_train_step(model, counted, opt, loss_frames=2, keep_at=2)
    ts = train.create_train_state(params, opt)
    carry = rollout.start(model.init_state(seqdata.first(frames)), targets[0])
    seen = []
    for w in rollout.tbptt_windows(8, 2, 4):
        sl = jax.tree_util.tree_map(lambda x: x[w.start:w.stop], (frames, targets))
        ts, carry, stats = step(ts, carry, *sl)
        seen.append(float(stats["loss"]))
    assert int(ts.step) == 3 and all(np.isfinite(seen))
    assert step._cache_size() == 1  # three windows, one compiled train step
    assert len(traces) == 1  # the loss is traced once, in the one loss segment


@pytest.mark.parametrize("k", [1, 3, 5])
def test_conv_same_fast_equals_autodiff_float64(x64, k):
    """``layers.conv_same_fast`` (NSRR's and KPN's SAME convolutions): values and all
    three gradients equal plain autodiff's of ``layers.conv``, in float64, inside a
    rolled scan as in training; and ``check_grads`` of the custom rule itself."""
    from jtus.models import layers
    rng = np.random.default_rng(k)
    x = jnp.asarray(rng.normal(size=(3, 2, 7, 6, 5)))
    kernel = jnp.asarray(rng.normal(size=(k, k, 5, 4)))
    bias = jnp.asarray(rng.normal(size=(4,)))
    w = jnp.asarray(rng.normal(size=(2, 7, 6, 4)))

    def loss(conv_fn, kernel, bias, x):
        def body(h, xt):
            y = conv_fn(xt + 0.1 * h, kernel, bias)
            return jnp.tanh(y[..., :1]) * 0.5, jnp.sum(y * w)
        return jax.lax.scan(body, jnp.zeros((2, 7, 6, 1)), x)[1].sum()

    ref = jax.value_and_grad(lambda *a: loss(layers.conv, *a), argnums=(0, 1, 2))(kernel, bias, x)
    got = jax.value_and_grad(lambda *a: loss(layers.conv_same_fast, *a),
                             argnums=(0, 1, 2))(kernel, bias, x)
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-11)
    check_grads(layers.conv_same_fast, (x[0], kernel, bias), order=1, modes=("rev",),
                eps=1e-6, atol=1e-6, rtol=1e-6)


def test_custom_conv_backward_equals_autodiff(x64):
    """The custom-VJP convolutions give plain autodiff's loss and gradients through a
    rolled scan: ``custom`` to 1e-11, ``winograd`` (whose forward under differentiation
    is Winograd's F(4x4), the direct convolution's values only in exact arithmetic) to
    1e-9."""
    out = {}
    for cb in ("autodiff", "custom", "winograd"):
        config = dlctus.Config(factor=4, dtype="float64", conv_backward=cb, blocks=IDENTITY_BLOCKS)
        model, params, frames, targets = _setup(T=4, config=config, dtype=np.float64)
        out[cb] = _loss_value_and_grad(model, params, frames, targets, 2)
    for cb, tol in (("custom", 1e-11), ("winograd", 1e-9)):
        (la, _), ga = out["autodiff"]
        (lb, _), gb = out[cb]
        np.testing.assert_allclose(lb, la, rtol=tol)
        for a, b in zip(jax.tree_util.tree_leaves(gb), jax.tree_util.tree_leaves(ga)):
            np.testing.assert_allclose(a, b, rtol=tol, atol=tol * 1e-2)


def test_recomputed_edges_give_the_kept_edges_gradients(x64):
    """DLCTUS's down-sampling and output construction recomputed in the backward pass
    (``remat_edges``, the default) give the same loss and gradients through a rolled
    scan as keeping their residuals, in float64."""
    out = []
    for remat in (False, True):
        config = dlctus.Config(factor=4, dtype="float64", remat_edges=remat, blocks=IDENTITY_BLOCKS)
        model, params, frames, targets = _setup(T=3, config=config, dtype=np.float64)
        out.append(_loss_value_and_grad(model, params, frames, targets, 2))
    (la, _), ga = out[0]
    (lb, _), gb = out[1]
    np.testing.assert_allclose(la, lb, rtol=1e-13)
    for a, b in zip(jax.tree_util.tree_leaves(ga), jax.tree_util.tree_leaves(gb)):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-14)


# Left out of the default run (52 s): the reverse-time backward's bookkeeping is
# checked on the toy model (test_rollout_toy.py, with the hoisted preparation too);
# this keeps it on DLCTUS, which no default training runs it on.
@pytest.mark.long
def test_reverse_time_backward_equals_autodiff_float64(x64):
    """``remat="reverse"`` (the hand-written reverse-time backward of a window: the
    forward keeps only each frame's carry, the backward recomputes one step at a time)
    gives the plain scan's loss, gradients and carries in float64 (1e-12), with a
    temporal loss (previous output and target in the carry), a reset in the middle of
    one batch element and a TBPTT cut (``keep_at``: gradients flow through the carry
    from one segment into the next)."""
    config = dlctus.Config(factor=4, dtype="float64")
    model, params, frames, targets = _setup(T=6, config=config, dtype=np.float64)
    frames = frames._replace(reset=jnp.zeros((6, 2), bool).at[0].set(True).at[3, 1].set(True))
    carry = rollout.start(model.init_state(seqdata.first(frames)), targets[0])
    loss_fn = losses.make("st-linear", 4, theta=0.5)

    def f(p, remat):
        return rollout.window_loss(model.step, loss_fn, p, carry, frames, targets,
                                   loss_frames=4, keep_at=3, remat=remat)

    vg = jax.jit(jax.value_and_grad(f, has_aux=True), static_argnums=1)
    (l0, aux0), g0 = vg(params, False)
    (l1, aux1), g1 = vg(params, "reverse")
    np.testing.assert_allclose(l1, l0, rtol=1e-12)
    leaves = jax.tree_util.tree_leaves
    assert len(leaves(g1)) == len(leaves(g0))
    for a, b in zip(leaves((g1, aux1)), leaves((g0, aux0))):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    assert max(float(jnp.abs(x).max()) for x in leaves(g0)) > 1e-3  # a gradient to compare


def test_a_state_of_another_batch_than_the_frames_is_refused():
    """A B=1 state with B=2 frames would broadcast through the step silently."""
    frames, _ = seqdata.sequence(T=3, B=2, h=8, w=8, factor=4)
    frames = jax.tree_util.tree_map(jnp.asarray, frames)
    model = dlctus.make(dlctus.Config(factor=4))
    params = model.init(jax.random.PRNGKey(0))
    one = jax.tree_util.tree_map(lambda x: x[0, :1], frames)
    with pytest.raises(ValueError, match="state: expected a batch of 2"):
        rollout.outputs(model.step, params, model.init_state(one), frames)
    two = jax.tree_util.tree_map(lambda x: x[0], frames)
    outs, _ = rollout.outputs(model.step, params, model.init_state(two), frames)
    assert outs.shape[:2] == (3, 2)


def test_late_loss_scores_the_window_from_its_index_float64(x64):
    """``window_loss(late=(k, late_fn))`` scores the window's frames from k on with
    ``late_fn`` and the earlier loss frames with ``loss_fn``: its value and gradients
    equal a Python loop's over the frames, with a temporal loss whose weight differs
    between the two (previous output and target carried across the cut). Float64, but
    the carry keeps the previous frame in float32, so the value agrees to 1e-10 and
    the gradients, whose cotangents pass that float32 frame, to 1e-5. A first frame
    before the loss frames scores all of them with ``late_fn``."""
    config = dlctus.Config(factor=4, dtype="float64", blocks=IDENTITY_BLOCKS)
    model, params, frames, targets = _setup(T=6, config=config, dtype=np.float64)
    carry = rollout.start(model.init_state(seqdata.first(frames)), targets[0])
    early, late = losses.make("log-salvi", 4), losses.make("log-salvi", 4, temporal_weight=5.0)

    def scanned(p):
        return rollout.window_loss(model.step, early, p, carry, frames, targets,
                                   loss_frames=5, late=(3, late))[0]

    def looped(p):
        state, prev_out, prev_target, has_prev = carry
        total = 0.0
        for t in range(6):
            frame = jax.tree_util.tree_map(lambda x: x[t], frames)
            out, state = model.step(p, state, frame)
            if t >= 1:
                fn = late if t >= 3 else early
                total = total + fn(out, targets[t], prev_out, prev_target, has_prev, frame)
            # the carry keeps the previous frame in float32, as rollout's scan does
            prev_out, prev_target = out.astype(jnp.float32), targets[t].astype(jnp.float32)
            has_prev = jnp.asarray(True)
        return total / 5

    vg = lambda f: jax.jit(jax.value_and_grad(f))(params)  # noqa: E731
    (v1, g1), (v2, g2) = vg(scanned), vg(looped)
    np.testing.assert_allclose(v1, v2, rtol=1e-10)
    assert abs(float(v1) - float(jax.jit(lambda p: rollout.window_loss(
        model.step, early, p, carry, frames, targets, loss_frames=5)[0])(params))) > 1e-3
    for a, b in zip(jax.tree_util.tree_leaves(g1), jax.tree_util.tree_leaves(g2)):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-9)
    # a late loss from before the loss frames scores all of them
    np.testing.assert_allclose(
        rollout.window_loss(model.step, early, params, carry, frames, targets, loss_frames=5,
                            late=(0, late))[0],
        rollout.window_loss(model.step, late, params, carry, frames, targets,
                            loss_frames=5)[0], rtol=1e-12)
    with pytest.raises(ValueError, match="late: expected a first frame in 0..6, got 7"):
        rollout.window_loss(model.step, early, params, carry, frames, targets, loss_frames=5,
                            late=(7, late))
