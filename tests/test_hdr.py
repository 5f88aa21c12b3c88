"""HDR colour and exposure (docs/conventions.md, "HDR and exposure"): the tone map,
every model's exposure edge, losses on displayed colour, the simulator's ``hdr``
effect, datasets that carry exposure, and a moving highlight's ghost trail."""

import dataclasses
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from jtus import loading, losses, models, recipe, rollout, sampling, upsample
from jtus.config import PRESETS
from jtus.data import dataset
from jtus.data.exr import linear_to_srgb, read_exr
from jtus.frame import Frame, validate
from jtus.sampling import display, jitter_sequence
from jtus.sim import generate
from tests import seqdata


def test_tonemap_round_trip_and_range():
    rng = np.random.default_rng(0)
    # radiance over 6 decades, as an HDR frame holds (sky, highlights, emitters)
    x = jnp.asarray(10.0 ** rng.uniform(-3, 3, size=(4096, 3)), jnp.float32)
    t = sampling.tonemap(x)
    assert float(t.min()) >= 0 and float(t.max()) < 1
    back = sampling.inverse_tonemap(t)
    # float32: 1 - max(t) keeps few digits as max(t) -> 1, so the relative error
    # grows with 1 + max(x); measured worst 1.45 eps (1 + max), 7.4e-5 near 1000
    xn, bn = np.asarray(x, np.float64), np.asarray(back, np.float64)
    rel = np.abs(bn - xn) / xn
    assert np.all(rel <= 4 * np.finfo(np.float32).eps * (1 + xn.max(-1, keepdims=True)))
    with jax.enable_x64(True):
        x64 = jnp.asarray(np.asarray(x), jnp.float64)
        np.testing.assert_allclose(np.asarray(sampling.inverse_tonemap(sampling.tonemap(x64))),
                                   np.asarray(x64), rtol=1e-12)  # measured 1.5e-13
    # hue kept: one scale per pixel; an output at or above 1 maps to a finite value
    ratio = np.asarray(t) / np.asarray(x)
    np.testing.assert_allclose(ratio, ratio[:, :1].repeat(3, 1), rtol=1e-6)
    assert np.isfinite(np.asarray(sampling.inverse_tonemap(jnp.ones((1, 3))))).all()


def test_tonemap_and_display_against_their_formulas():
    """Hand-computed values on [B,H,W,3] images (the max is over the channels, never
    over a spatial axis); ``display`` multiplies by the exposure of each batch element
    before the tone map, leaves LDR frames (no exposure) as they are, and keeps the
    image's dtype (a float64 exposure with 64-bit types on would promote float32)."""
    rgb = np.array([[[[1.0, 3.0, 0.5], [0.0, 0.0, 0.0]],
                     [[0.2, 0.1, 0.4], [7.0, 1.0, 2.0]]],
                    [[[0.5, 0.5, 0.5], [4.0, 0.0, 1.0]],
                     [[1.0, 2.0, 3.0], [0.0, 9.0, 1.0]]]])  # [2,2,2,3]
    want = rgb / (1 + rgb.max(-1, keepdims=True))
    np.testing.assert_allclose(sampling.tonemap(jnp.asarray(rgb)), want, rtol=1e-6)
    np.testing.assert_allclose(sampling.inverse_tonemap(jnp.asarray(want)), rgb, rtol=1e-5)
    e = np.array([0.5, 4.0])
    pre = rgb * e[:, None, None, None]
    np.testing.assert_allclose(sampling.display(jnp.asarray(rgb), jnp.asarray(e)),
                               pre / (1 + pre.max(-1, keepdims=True)), rtol=1e-6)
    x = jnp.asarray(rgb, jnp.float32)
    assert sampling.display(x, None) is x
    assert sampling.display(x.astype(jnp.bfloat16), jnp.asarray(e, jnp.float32)).dtype == \
        jnp.bfloat16
    with jax.enable_x64(True):
        assert sampling.display(x, np.asarray(e)).dtype == jnp.float32
        assert sampling.exposure_scale(np.asarray(e), x).shape == (2, 1, 1, 1)


def _model(name):
    """A registered model at 4x with parameters (trained where jtus ships them). Built
    in the test, not at collection: every xdist worker collects every module, and
    building all of them there took 30-70 s per worker."""
    m = models.build(name, 4)
    params = loading.load("shipped", 4).params if name == "dlctus" else m.init(
        jax.random.PRNGKey(0))
    return m, params


@pytest.mark.parametrize("name", models.NAMES)
def test_ldr_frame_with_exposure_one_is_unchanged(name):
    model, params = _model(name)
    frames, _ = seqdata.sequence(T=4, B=2, h=8, w=8, factor=4, seed=1, max_motion=0.5)
    frames = frames._replace(reset=np.eye(4, 2, dtype=bool))
    base = rollout.outputs(model.step, params, rollout.first_state(model, frames), frames)[0]
    ones = frames._replace(exposure=np.ones((4, 2), np.float32))
    got = rollout.outputs(model.step, params, rollout.first_state(model, ones), ones)[0]
    np.testing.assert_array_equal(np.asarray(got), np.asarray(base))


def test_hdr_model_sees_pre_exposed_tonemapped_colour():
    """``step(c, exposure e) == step(e c, exposure 1) / e`` and the body's input is
    ``tonemap(e c)``: checked through a model whose body returns its input."""
    model = models.build("jau", 4, hdr=True)
    frames, _ = seqdata.sequence(T=1, B=2, h=4, w=4, factor=4, seed=2)
    fr = jax.tree_util.tree_map(lambda x: jnp.asarray(x[0]), frames)
    hdr = fr._replace(color=fr.color * 40.0, exposure=jnp.asarray([0.5, 2.0]))
    got, _ = model.step({}, (), hdr)
    ldr = models.build("jau", 4)
    body_in = sampling.tonemap(hdr.color * hdr.exposure[:, None, None, None])
    want = sampling.inverse_tonemap(ldr.step({}, (), fr._replace(color=body_in))[0])
    want = want / hdr.exposure[:, None, None, None]
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-6)
    # and linear in exposure: the output is radiance, whatever the exposure
    again, _ = model.step({}, (), hdr._replace(color=hdr.color * 2, exposure=hdr.exposure / 2))
    np.testing.assert_allclose(np.asarray(again), 2 * np.asarray(got), rtol=2e-5)


def test_losses_and_metrics_compare_displayed_colour():
    frames, targets = seqdata.sequence(T=2, B=2, h=4, w=4, factor=4, seed=3)
    fr = jax.tree_util.tree_map(lambda x: jnp.asarray(x[1]), frames)
    out, tgt = jnp.asarray(targets[1]) * 30.0, jnp.asarray(targets[0]) * 30.0
    e = jnp.asarray([0.25, 1.5])
    for name in ("l1", "st-linear", "kpn"):
        fn = losses.make(name, 4)
        got = fn(out, tgt, out, tgt, jnp.asarray(True), fr._replace(exposure=e))
        d = lambda x: sampling.display(x, e)  # noqa: E731
        want = fn(d(out), d(tgt), d(out), d(tgt), jnp.asarray(True),
                  fr._replace(color=d(fr.color)))
        np.testing.assert_allclose(float(got), float(want), rtol=1e-6)
    # LDR frames (no exposure): the images themselves
    assert float(losses.make("l1", 4)(out, tgt, out, tgt, True, fr)) == pytest.approx(
        float(jnp.mean(jnp.abs(out - tgt))), rel=1e-6)


def test_validate_refuses_bad_exposure():
    frames, _ = seqdata.sequence(T=1, B=2, h=4, w=4, factor=4)
    fr = jax.tree_util.tree_map(lambda x: x[0], frames)
    with pytest.raises(ValueError, match="exposure: expected shape"):
        validate(fr._replace(exposure=np.ones((2, 1), np.float32)))
    for bad in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="exposure: expected finite values > 0"):
            validate(fr._replace(exposure=np.array([1.0, bad], np.float32)))


def test_hdr_effect_renders_radiance_above_one_and_an_exposure_curve():
    from jtus.sim import VideoRenderer, get_scene, with_effects

    base = get_scene("random_3")
    hdr = with_effects(base, generate.preset("hdr").effects)
    assert "hdr" in hdr.effects and "hdr" not in base.effects
    assert sum(o.material.emission > 0 for o in hdr.objects) >= 2  # emitters drawn
    v = VideoRenderer(hdr, (48, 48), (4,), 4).video("train", 0, 6)
    assert v["target"].max() > 4.0 and v["x4"]["color"].max() > 4.0
    e = v["exposure"]
    assert e.shape == (6,) and np.all(e > 0) and np.ptp(e) > 0
    ldr = VideoRenderer(dataclasses.replace(hdr, effects=tuple(
        x for x in hdr.effects if x != "hdr")), (48, 48), (4,), 4).video("train", 0, 6)
    assert "exposure" not in ldr and ldr["target"].max() <= 1.0
    # same scene, same geometry: where the LDR render is below its clamp, only the
    # highlight gain differs, so depth and motion agree exactly
    np.testing.assert_array_equal(ldr["x4"]["depth"], v["x4"]["depth"])
    np.testing.assert_array_equal(ldr["x4"]["motion"], v["x4"]["motion"])


def test_adding_hdr_to_the_effect_list_left_every_randomized_scene_as_it_was():
    """The drawn effects and every draw after them depend on one uniform per drawn
    effect; hdr is never drawn, so existing seeds (data/diverse.h5) are unchanged.
    Golden: sha256 of the JSON of seeds 0-19 before hdr existed (its two new fields
    at their defaults removed)."""
    import hashlib
    import json

    from jtus.sim import random_scene, to_json

    def before(seed):
        d = json.loads(to_json(random_scene(seed)))
        assert d.pop("highlight_gain") == 12.0 and d.pop("exposure_stops") == 1.0
        return json.dumps(d, indent=1)

    digest = hashlib.sha256("".join(before(s) for s in range(20)).encode()).hexdigest()
    assert digest == "050dce763c1950fbce3ff16660b37243c441f42282be13f22a67424ab1db2023"


@pytest.fixture(scope="module")
def hdr_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("hdr") / "hdr-tiny.h5"
    return generate.generate("hdr-tiny", str(out), progress=False)


def test_hdr_dataset_carries_exposure_into_videos_and_crops(hdr_data):
    with dataset.Dataset(hdr_data) as ds:
        assert ds.hdr
        name = ds.videos("test")[0]
        frames, targets = ds.video("test", name, 4)
        assert frames.exposure.shape == frames.reset.shape
        np.testing.assert_array_equal(frames.exposure[:, 0],
                                      ds.group("test", name)["exposure"][:])
        fr, tg = ds.crops("train", 4, 2, 4, 16, np.random.default_rng(0))
        assert fr.exposure.shape == (4, 2) and np.all(fr.exposure > 0)
        assert tg.max() > 1.0
        validate(fr, 4, time_major=True)


def test_training_refuses_hdr_data_for_an_ldr_model(hdr_data, tmp_path):
    hdr = dataclasses.replace(PRESETS["hdr-tiny"], dataset=hdr_data)
    recipe.check_data(hdr)
    with pytest.raises(ValueError, match="HDR colour with an exposure"):
        recipe.check_data(dataclasses.replace(hdr, model_overrides=()))


def test_upsample_writes_hdr_data_as_png_mp4_and_exr(hdr_data, tmp_path):
    """HDR input through every output of ``python -m jtus.upsample``: EXR frames keep
    the radiance (above 1), PNG frames and the MP4 show ``display`` of it (the
    tone-mapped pre-exposed colour), frame by frame."""
    with dataset.Dataset(hdr_data) as ds:
        name = ds.videos("test")[0]
        frames, _ = ds.video("test", name, 4)
    base = ["--input", hdr_data, "--video", name, "--factor", "4", "--model", "jau"]
    assert upsample.main(base + ["--format", "exr", "--out", str(tmp_path / "exr")]) == 0
    assert upsample.main(base + ["--format", "png", "--out", str(tmp_path / "png"),
                                 "--mp4", str(tmp_path / "v.mp4")]) == 0
    exrs = sorted((tmp_path / "exr").glob("*.exr"))
    pngs = sorted((tmp_path / "png").glob("*.png"))
    assert len(exrs) == len(pngs) == frames.color.shape[0]
    assert (tmp_path / "v.mp4").stat().st_size > 0
    radiance = np.stack([np.stack([read_exr(str(f))[0][c] for c in "RGB"], -1) for f in exrs])
    assert radiance.max() > 1.0
    shown = np.asarray(display(jnp.asarray(radiance),
                               jnp.asarray(frames.exposure[:, 0])))
    png = np.stack([np.asarray(Image.open(f), np.float64) / 255 for f in pngs])
    np.testing.assert_allclose(png, linear_to_srgb(shown), atol=0.5 / 255 + 1e-3)


def test_upsample_failed_mp4_leaves_no_file_and_no_frames(hdr_data, tmp_path, capsys):
    """An ``--mp4`` path that cannot take a file is refused before any work; nothing is
    written."""
    (tmp_path / "file").write_text("x")
    for bad in (str(tmp_path / "file" / "v.mp4"), str(tmp_path), str(tmp_path / "v.avi")):
        assert upsample.main(["--input", hdr_data, "--factor", "4", "--model", "jau",
                              "--out", str(tmp_path / "f"), "--mp4", bad]) == 2
        assert "--mp4" in capsys.readouterr().err
    assert not (tmp_path / "f").exists() and sorted(os.listdir(tmp_path)) == ["file"]


def highlight(T=14, h=16, w=40, f=4, value=30.0, bg=0.02, speed=1.0, exposure=1.0):
    """A 3x3 LR-pixel square of radiance ``value`` moving ``speed`` LR pixels per frame
    to the right over a flat background ``bg``, rendered at each frame's thesis jitter,
    with exact backward motion; the x of its front edge at the last frame (HR)."""
    seq = jitter_sequence("thesis", f)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    cols, deps, mvs, jits = [], [], [], []
    for t in range(T):
        x0 = 4 + speed * t
        j = seq[t % len(seq)].astype(np.float32)
        px, py = xx + j[0], yy + j[1]
        inside = (px >= x0) & (px < x0 + 3) & (py >= 6) & (py < 9)
        cols.append(np.where(inside[..., None], value, bg) * np.ones(3, np.float32))
        deps.append(np.where(inside, 0.3, 0.9)[..., None])
        mvs.append(np.stack([np.where(inside, -speed, 0.0), np.zeros_like(px)], -1))
        jits.append(j)
    stack = lambda a: jnp.asarray(np.stack(a)[:, None], jnp.float32)  # noqa: E731
    reset = jnp.asarray(np.arange(T) == 0)[:, None]
    fr = Frame(stack(cols), stack(deps), stack(mvs), stack(jits), reset,
               jnp.full((T, 1), exposure, jnp.float32))
    return fr, (4 + speed * (T - 1)) * f


def trail_length(model, params, frames, front, f=4, threshold=0.05):
    """HR columns behind the square's last position, in its rows, whose displayed
    colour exceeds the displayed background by ``threshold``."""
    outs, _ = rollout.outputs(model.step, params, rollout.first_state(model, frames), frames)
    e = frames.exposure[-1]
    d = np.asarray(sampling.display(outs[-1], e))[0]
    bg = float(sampling.display(jnp.full((1, 1, 1, 3), 0.02), e).max())
    band = d[6 * f + 2:9 * f - 2, :int(front)].max(-1)
    return int((band > bg + threshold).any(0).sum())


def test_moving_highlight_leaves_no_longer_ghost_than_tus():
    """A highlight 1500x its background (radiance 30 over 0.02) moving 4 HR pixels per
    frame: the shipped DLCTUS run on tone-mapped colour (``hdr``) leaves a trail no
    longer than TUS's. Fed the raw radiance instead (an LDR model on HDR colour), the
    history holds values far outside what the network was trained on."""
    fr, front = highlight()
    tus = models.build("tus", 4, hdr=True)
    dl = models.build("dlctus", 4, hdr=True)
    params = loading.load("shipped", 4).params
    t_tus = trail_length(tus, {}, fr, front)
    t_dl = trail_length(dl, params, fr, front)
    assert t_dl <= t_tus, (t_dl, t_tus)
    assert t_tus > 0  # the measure sees TUS's short trail: not vacuous
