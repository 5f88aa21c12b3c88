"""DLCTUS in JAX against the independent PyTorch forward (jtus/reference/torch_dlctus.py)."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch

from jtus import losses, rollout
from jtus.models import dlctus
from jtus.reference import torch_dlctus
from tests import seqdata


def _torch_net(seed=0):
    torch.manual_seed(seed)
    net = torch_dlctus.Net().double()
    with torch.no_grad():  # keep o away from the clamps so every path carries gradient
        net.cnn4[2].bias.add_(0.5)
    return net.float()


def _nchw(x):
    return torch.from_numpy(np.ascontiguousarray(np.moveaxis(np.asarray(x), -1, -3)))


def _torch_rollout(net, frames, factor, grad=False):
    T = frames.color.shape[0]
    hist = torch_dlctus.init_history(_nchw(frames.color[0]), torch.from_numpy(frames.jitter[0]),
                                     factor)
    outs, hists = [], []
    for t in range(T):
        reset = None if frames.reset is None else torch.from_numpy(frames.reset[t])
        out, hist = torch_dlctus.step(net, hist, _nchw(frames.color[t]), _nchw(frames.depth[t]),
                                      _nchw(frames.motion[t]), torch.from_numpy(frames.jitter[t]),
                                      factor, reset=reset)
        outs.append(out)
        hists.append(hist)
    return outs, hists


@pytest.mark.parametrize("factor", [4, 2])
def test_rollout_matches_torch(factor):
    frames, _ = seqdata.sequence(T=10, B=2, h=32 // factor, w=48 // factor, factor=factor)
    net = _torch_net()
    config = dlctus.Config(factor=factor)
    params = dlctus.params_from_torch(net.state_dict(), config)
    model = dlctus.make(config)
    jf = seqdata.to_jax(frames._replace(reset=None))
    state = model.init_state(jax.tree_util.tree_map(lambda x: x[0], jf))
    outs, final = jax.jit(lambda p, s, f: rollout.outputs(model.step, p, s, f))(params, state, jf)
    with torch.no_grad():
        touts, thists = _torch_rollout(net, frames, factor)
    ref = np.stack([o.numpy() for o in touts]).transpose(0, 1, 3, 4, 2)
    np.testing.assert_allclose(np.asarray(outs), ref, rtol=0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(final.history),
                               thists[-1].numpy().transpose(0, 2, 3, 1), rtol=0, atol=1e-5)
    # The accumulation channel moved: the test exercises eq. 45, not a constant.
    assert np.ptp(np.asarray(final.history)[..., 3]) > 0.05


@pytest.mark.parametrize("factor", [4, 2])
def test_reset_frames_match_torch(factor):
    """First frame and a camera cut in the middle, with non-zero motion on both: a
    reset frame's history is its fresh input, unwarped, in jtus as in the reference
    (30 frames; measured max error 5e-6 at 4x)."""
    frames, _ = seqdata.sequence(T=30, B=2, h=32 // factor, w=32 // factor, factor=factor,
                                 seed=3, reset_at=(13, 1))
    frames = frames._replace(reset=frames.reset.copy())
    frames.reset[0] = True
    assert np.abs(frames.motion[0]).max() > 0.3 and np.abs(frames.motion[13]).max() > 0.3
    net = _torch_net(2)
    config = dlctus.Config(factor=factor)
    params = dlctus.params_from_torch(net.state_dict(), config)
    model = dlctus.make(config)
    jf = seqdata.to_jax(frames)
    # any history: the reset on frame 0 must replace it
    state = dlctus.State(jnp.full((2, 32, 32, 4), 0.3, jnp.float32))
    outs, _ = jax.jit(lambda p, s, f: rollout.outputs(model.step, p, s, f))(params, state, jf)
    with torch.no_grad():
        touts, _ = _torch_rollout(net, frames, factor)
    ref = np.stack([o.numpy() for o in touts]).transpose(0, 1, 3, 4, 2)
    np.testing.assert_allclose(np.asarray(outs), ref, rtol=0, atol=1e-5)
    # the reference's first history is reprojected only without the reset flag: the
    # difference that the test above would catch
    with torch.no_grad():
        warped, _ = _torch_rollout(net, frames._replace(reset=None), factor)
    assert np.abs(np.stack([o.numpy() for o in warped])[0] - np.stack(
        [o.numpy() for o in touts])[0]).max() > 1e-3


def test_bptt_gradients_match_torch():
    factor = 4
    frames, targets = seqdata.sequence(T=5, B=2, h=8, w=8, factor=factor, seed=1)
    net = _torch_net(1)
    config = dlctus.Config(factor=factor)
    params = dlctus.params_from_torch(net.state_dict(), config)
    model = dlctus.make(config)
    jf = seqdata.to_jax(frames._replace(reset=None))
    jt = jnp.asarray(targets)

    def loss(p):
        state = model.init_state(jax.tree_util.tree_map(lambda x: x[0], jf))
        carry = rollout.start(state, jt[0])
        value, _ = rollout.window_loss(model.step, losses.make("l1", factor), p, carry, jf, jt,
                                       loss_frames=5)
        return value

    value, grads = jax.jit(jax.value_and_grad(loss))(params)
    touts, _ = _torch_rollout(net, frames, factor)
    tl = sum((o - _nchw(targets[t])).abs().mean() for t, o in enumerate(touts)) / 5
    tl.backward()
    np.testing.assert_allclose(float(value), tl.item(), rtol=1e-6)
    tgrads = dlctus.params_from_torch({k: p.grad for k, p in net.named_parameters()}, config)
    flat, _ = jax.tree_util.tree_flatten_with_path(grads)
    tflat = jax.tree_util.tree_leaves(tgrads)
    for (path, g), tg in zip(flat, tflat):
        g, tg = np.asarray(g), np.asarray(tg)
        scale = np.abs(tg).max()
        assert scale > 0, path
        np.testing.assert_allclose(g, tg, rtol=1e-4, atol=1e-4 * scale,
                                   err_msg=jax.tree_util.keystr(path))


def test_params_round_trip_exact():
    config = dlctus.Config()
    params = dlctus.init(jax.random.PRNGKey(3), config)
    back = dlctus.params_from_torch(dlctus.params_to_torch(params, config), config)
    for a, b in zip(jax.tree_util.tree_leaves(params), jax.tree_util.tree_leaves(back)):
        np.testing.assert_array_equal(a, b)
    sd = dlctus.params_to_torch(params, config)
    assert list(sd)[:4] == ["down.0.weight", "down.0.bias", "cnn1.0.weight", "cnn1.0.bias"]
    assert sd["down.0.weight"].shape == (32, 8, 4, 4)
    assert set(sd) == set(torch_dlctus.Net().state_dict())


def _save(obj, tmp_path, name="ckpt.pt"):
    path = tmp_path / name
    torch.save(obj, path)
    return path


def test_load_checkpoint_formats(tmp_path):
    net = _torch_net()
    want = dlctus.params_from_torch(net.state_dict())
    bare = _save(net.state_dict(), tmp_path, "bare.pt")
    # A training checkpoint as people have them: extra entries and numpy scalars.
    full = _save({"epoch": 200, "model_state_dict": net.state_dict(),
                  "loss": np.float64(0.0123), "best_psnr": np.float32(35.5),
                  "step": np.int64(1000)}, tmp_path, "full.pt")
    for path in (bare, full):
        got = dlctus.load_torch_checkpoint(path)
        for a, b in zip(jax.tree_util.tree_leaves(want), jax.tree_util.tree_leaves(got)):
            np.testing.assert_array_equal(a, b)


def test_load_checkpoint_pickled_with_numpy1(tmp_path):
    """The thesis's checkpoints were pickled with numpy 1.x, whose scalars pickle as
    ``numpy.core.multiarray.scalar``; numpy 2 writes ``numpy._core...``. The legacy
    (non-zip) format keeps the global's name as plain text, so the file a numpy 1.x
    torch.save writes is made here by renaming it in the stream."""
    net = _torch_net()
    path = tmp_path / "numpy1.pt"
    torch.save({"epoch": 200, "model_state_dict": net.state_dict(), "loss": np.float64(0.01)},
               path, _use_new_zipfile_serialization=False)
    raw = path.read_bytes()
    assert b"numpy._core.multiarray\nscalar" in raw
    path.write_bytes(raw.replace(b"numpy._core.multiarray\nscalar",
                                 b"numpy.core.multiarray\nscalar"))
    assert b"numpy._core" not in path.read_bytes()
    got = dlctus.load_torch_checkpoint(path)
    want = dlctus.params_from_torch(net.state_dict())
    for a, b in zip(jax.tree_util.tree_leaves(want), jax.tree_util.tree_leaves(got)):
        np.testing.assert_array_equal(a, b)


class _Evil:
    def __reduce__(self):
        return (print, ("this must never run",))


def test_load_checkpoint_refuses_code_and_bad_content(tmp_path, capsys):
    evil = tmp_path / "evil.pt"
    torch.save({"model_state_dict": {}, "x": _Evil()}, evil)
    with pytest.raises(ValueError, match="not a loadable DLCTUS checkpoint"):
        dlctus.load_torch_checkpoint(evil)
    assert "must never run" not in capsys.readouterr().out
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint at all")
    with pytest.raises(ValueError, match="corrupt.pt"):
        dlctus.load_torch_checkpoint(corrupt)
    with pytest.raises(ValueError, match="expected a state_dict"):
        dlctus.load_torch_checkpoint(_save([1, 2, 3], tmp_path, "list.pt"))
    sd = torch_dlctus.Net().state_dict()
    sd.pop("cnn4.2.bias")
    with pytest.raises(ValueError, match=r"missing \['cnn4.2.bias'\]"):
        dlctus.load_torch_checkpoint(_save(sd, tmp_path, "missing.pt"))
    sd = torch_dlctus.Net(channels=32).state_dict()
    sd["down.0.weight"] = torch.zeros(32, 7, 4, 4)
    with pytest.raises(ValueError, match=r"down.0.weight.*\(32, 8, 4, 4\)"):
        dlctus.params_from_torch(sd)
    for key, value, message in (
            ("cnn2.0.weight", torch.full((32, 32, 3, 3), float("nan")), "1 NaN|9216 NaN"),
            ("cnn1.0.bias", torch.tensor([float("inf")] + [0.0] * 31), "1 NaN or infinite"),
            ("cnn3.2.bias", torch.zeros(32, dtype=torch.int64), "floating-point weights")):
        sd = torch_dlctus.Net().state_dict()
        sd[key] = value
        with pytest.raises(ValueError, match=rf"{re.escape(key)}.*({message})"):
            dlctus.load_torch_checkpoint(_save(sd, tmp_path, "bad.pt"))


@pytest.mark.parametrize("factor", [4, 2])
def test_rollout_matches_the_thesis_listing(factor):
    """jtus against the thesis's own code listing (tests/torch_thesis.py: its zero-up-
    sampling by transposed convolution and pad-and-slice, its affine-grid jitter
    alignment, its identity-grid motion arithmetic, its border mask and its first
    frame) over 30 frames with motion of up to 2 LR pixels (samples leave the image)
    and a camera cut in one batch element."""
    from tests import torch_thesis

    frames, _ = seqdata.sequence(T=30, B=2, h=32 // factor, w=48 // factor, factor=factor,
                                 seed=5, max_motion=2.0, reset_at=(17, 1))
    frames = frames._replace(reset=frames.reset.copy())
    frames.reset[0] = True
    net = _torch_net(3)
    config = dlctus.Config(factor=factor)
    params = dlctus.params_from_torch(net.state_dict(), config)
    model = dlctus.make(config)
    jf = seqdata.to_jax(frames)
    outs, final = jax.jit(lambda p, s, f: rollout.outputs(model.step, p, s, f))(
        params, rollout.first_state(model, jf), jf)
    t = {k: torch.from_numpy(np.ascontiguousarray(np.moveaxis(np.asarray(v), -1, 2)))
         for k, v in (("color", frames.color), ("depth", frames.depth),
                      ("motion", frames.motion))}
    with torch.no_grad():
        ref, hist = torch_thesis.rollout(net, t["color"], t["depth"], t["motion"],
                                         torch.from_numpy(frames.jitter),
                                         torch.from_numpy(frames.reset), factor)
    ref = ref.numpy().transpose(0, 1, 3, 4, 2)
    # float32 on both sides; measured max 2.1e-6 (4x), 2.4e-6 (2x)
    np.testing.assert_allclose(np.asarray(outs), ref, rtol=0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(final.history), hist.numpy().transpose(0, 2, 3, 1),
                               rtol=0, atol=1e-5)
    # the border mask and the cut were exercised: some reprojected samples left the
    # image, and continuing through the cut instead would differ
    assert np.abs(frames.motion).max() > 1.5
    no_cut = frames._replace(reset=np.eye(30, 2, dtype=bool)[:, :1].repeat(2, 1))
    with torch.no_grad():
        cont, _ = torch_thesis.rollout(net, t["color"], t["depth"], t["motion"],
                                       torch.from_numpy(frames.jitter),
                                       torch.from_numpy(no_cut.reset), factor)
    assert np.abs(cont.numpy().transpose(0, 1, 3, 4, 2)[17:, 1] - ref[17:, 1]).max() > 1e-3
