"""DLCTUS's ``resample_input`` variant: one more network input saying how far each
pixel's history read lies from a pixel centre. Its feature, its equality with the
thesis's model while the new kernel rows are zero, its formulations, and the tools
that must refuse it (the PyTorch reference and the native ONNX graph have 8 inputs)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jtus import loading, sampling
from jtus.config import Config
from jtus.models import dlctus, dlctus_onnx
from tests import seqdata


@pytest.mark.parametrize("factor", [2, 4])
def test_resample_offset_is_the_read_positions_distance_from_a_pixel_centre(factor):
    """A constant motion field up-samples to itself, so the offset is ``|d - round(d)|``
    summed over both axes of ``d = f * mv``: 0 for no motion and for whole-pixel
    displacements, 0.5 per axis at half a pixel (numpy reference, float32 exact)."""
    mvs = np.array([[0.0, 0.0], [1.0 / factor, -2.0 / factor], [0.5 / factor, 0.0],
                    [0.3, -0.7], [-1.26, 0.49]], np.float32)
    motion = jnp.asarray(np.broadcast_to(mvs[:, None, None, :], (5, 4, 6, 2)))
    got = np.asarray(dlctus.resample_offset(motion, factor))
    d = factor * mvs.astype(np.float64)
    want = np.abs(d - np.round(d)).sum(-1)
    assert got.shape == (5, 4 * factor, 6 * factor, 1)
    np.testing.assert_allclose(got[..., 0], np.broadcast_to(want[:, None, None], got.shape[:3]),
                               rtol=0, atol=2e-6)
    assert got[0].max() == 0.0 and got[1].max() == 0.0 and np.allclose(got[2], 0.5)


def test_a_zero_offset_marks_an_exact_history_read():
    """Where the offset is 0 the bicubic read returns the history's own pixels (a whole
    pixel shift), which is what the feature tells the network; at a half-pixel shift
    it does not, and the offset there is 0.5."""
    rng = np.random.default_rng(0)
    hist = jnp.asarray(rng.uniform(size=(1, 16, 16, 4)), jnp.float32)
    for mv, exact in ((0.5, True), (0.25, False)):  # factor 2: d = 1 and 0.5 HR pixels
        motion = jnp.full((1, 8, 8, 2), mv, jnp.float32)
        plan = sampling.reproject_plan(motion, 2, method="bicubic", a=-0.75)
        read = sampling.warp_read(hist, plan, "bicubic", -0.75)
        inner = np.asarray(read)[0, 2:-2, 2:-2]
        shifted = np.asarray(hist)[0, 3:-1, 3:-1]  # the read at P + (1, 1)
        offset = float(dlctus.resample_offset(motion, 2).max())
        assert (offset == 0.0) == exact
        assert np.allclose(inner, shifted, atol=1e-6) == exact


def _frames(seed=0, T=3):
    frames, _ = seqdata.to_jax(seqdata.sequence(T=T, B=2, h=8, w=8, factor=2, seed=seed))
    return frames


@functools.partial(jax.jit, static_argnums=1)
def _run(params, config, frames):
    model = dlctus.make(config)
    state, outs = model.init_state(seqdata.first(frames)), []
    for t in range(frames.color.shape[0]):
        out, state = model.step(params, state, seqdata.at(frames, t))
        outs.append(out)
    return jnp.stack(outs)


def test_grown_thesis_weights_compute_the_thesis_model_until_trained():
    """The shipped weights grown by ``adapt_params`` (zero rows for the new channel)
    give the 8-input model's outputs exactly, on moving frames whose offsets are not
    zero; with non-zero rows they do not (control), and the loss's gradient reaches
    those rows, so training can use the channel."""
    base = loading.load("shipped", 2).params
    c8, c9 = dlctus.Config(factor=2), dlctus.Config(factor=2, resample_input=True)
    grown = dlctus.adapt_params(base, c9)
    assert grown["down"]["kernel"].shape == (4, 4, 9, 32)
    frames = _frames()
    assert float(dlctus.resample_offset(frames.motion[1], 2).max()) > 0.1
    np.testing.assert_array_equal(np.asarray(_run(grown, c9, frames)),
                                  np.asarray(_run(base, c8, frames)))
    k = grown["down"]["kernel"].at[:, :, 8].set(0.05)
    moved = {**grown, "down": {**grown["down"], "kernel": k}}
    assert float(jnp.abs(_run(moved, c9, frames) - _run(base, c8, frames)).max()) > 1e-3
    grad = jax.grad(lambda p: jnp.mean(_run(p, c9, frames) ** 2))(grown)
    assert float(jnp.abs(grad["down"]["kernel"][:, :, 8]).max()) > 0


def test_resample_input_formulations_agree():
    """standard (a 9-channel strided convolution), opt1 and opt2 (the offset joins the
    history's space-to-depth matmul) give the same frames with random weights, to 1e-5
    in float32."""
    frames = _frames(seed=3, T=2)
    params = dlctus.init(jax.random.PRNGKey(2), dlctus.Config(factor=2, resample_input=True))
    outs = [np.asarray(_run(params, dlctus.Config(factor=2, resample_input=True,
                                                  formulation=f), frames))
            for f in dlctus.FORMULATIONS]
    for o in outs[1:]:
        np.testing.assert_allclose(o, outs[0], rtol=0, atol=1e-5)


def test_a_run_grows_its_init_weights_and_tools_refuse_the_variant():
    """``--model-override resample_input=true`` with the thesis's design's weights as
    ``init_from``: the run starts from them grown; a kernel that is neither size is
    refused naming it; the PyTorch conversion and the native ONNX graph say why they
    cannot hold the variant."""
    cfg = Config(model="dlctus", factor=2, init_from="jtus/weights/dlctus-x2.msgpack",
                 model_overrides=(("resample_input", True),))
    assert loading.init_params(cfg)["down"]["kernel"].shape == (4, 4, 9, 32)
    c9 = dlctus.Config(factor=2, resample_input=True)
    bad = dlctus.init(jax.random.PRNGKey(0), dlctus.Config(factor=2))
    bad = {**bad, "down": {**bad["down"], "kernel": bad["down"]["kernel"][:, :, :7]}}
    with pytest.raises(ValueError, match="params: down kernel with 7 input channels"):
        dlctus.adapt_params(bad, c9)
    with pytest.raises(ValueError, match="resample_input"):
        dlctus.params_to_torch(dlctus.init(jax.random.PRNGKey(0), c9), c9)
    assert "resample_input" in dlctus_onnx.unsupported(c9)
    assert dlctus_onnx.unsupported(dlctus.Config(factor=2)) is None
