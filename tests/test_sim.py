"""The simulator: motion vectors, jitter, effect gating (cost and pixels), determinism."""

import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pytest

from jtus import sampling, sim
from jtus.files import UnknownKeyWarning
from jtus.sim import paths, render
from jtus.sim.video import ROTATED_GRID, VideoRenderer


def _moving_frames(video, factor, min_motion=0.3, min_fraction=0.03):
    """Frames where at least ``min_fraction`` of the pixels move ``min_motion`` LR px."""
    mv = video[f"x{factor}"]["motion"]
    ts = [t for t in range(1, len(mv))
          if np.mean(np.abs(mv[t]).max(-1) > min_motion) > min_fraction and not video["reset"][t]]
    assert ts, "the test path should move"
    return ts


def _coherent(mv, tol=0.05):
    """LR pixels whose 3x3 neighbourhood moves alike (to ``tol`` LR px): away from
    motion discontinuities, hence from disocclusions and bilinear-up-sampling errors."""
    h, w, _ = mv.shape
    pad = np.pad(mv, ((1, 1), (1, 1), (0, 0)), mode="edge")
    nb = np.stack([pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] for dy in (-1, 0, 1)
                   for dx in (-1, 0, 1)])
    return (nb.max(0) - nb.min(0)).max(-1) < tol


@pytest.mark.parametrize("layout,motion", [("camera_orbit", "camera_motion"),
                                           ("objects", "object_motion")])
def test_motion_vectors_reproject_the_target(layout, motion):
    """Camera-only and object-only motion, on textured (filtered) surfaces so that
    frames differ where things move."""
    base = sim.get_scene(layout)
    scene = dataclasses.replace(base, effects=(motion, "texture_detail"),
                                path=dataclasses.replace(base.path, speed=0.05, holds=0))
    f, size = 2, 96
    v = VideoRenderer(scene, (size, size), (f,), spp=4).video("test", 0, 8)
    up = lambda m: np.repeat(np.repeat(m, f, 0), f, 1)  # noqa: E731
    checked = 0

    def warp_error(prev, cur, mv):
        xy = sampling.pixel_grid(1, size, size) + f * sampling.upsample(jnp.asarray(mv[None]), f)
        warped, inside = sampling.sample(jnp.asarray(prev[None]), xy, "catmull_rom",
                                         return_mask=True)
        return np.abs(np.asarray(warped)[0] - cur).max(-1), np.asarray(inside)[0, ..., 0]

    for t in _moving_frames(v, f):
        prev, cur = v["target"][t - 1], v["target"][t]
        mv = v[f"x{f}"]["motion"][t]
        err_warp, inside = warp_error(prev, cur, mv)
        keep = inside & up(_coherent(mv))
        moving = keep & up(np.abs(mv).max(-1) > 0.3)
        err_none = np.abs(prev - cur).max(-1)
        # Outside disocclusions the warp reproduces the current target closely (what is
        # left is resampling a supersampled, textured target) ...
        assert np.percentile(err_warp[keep], 99) < 0.05, t
        # Where the moving content has detail (not flat sky or walls):
        if err_none[moving].mean() > 0.01:
            # far better than no warp ...
            assert err_warp[moving].mean() < 0.35 * err_none[moving].mean(), t
            # ... to sub-pixel accuracy: vectors off by a quarter LR pixel do worse.
            for off in ([0.25, 0.0], [0.0, 0.25]):
                err_off, _ = warp_error(prev, cur, mv + np.array(off, np.float32))
                assert err_warp[moving].mean() < 0.8 * err_off[moving].mean(), (t, off)
            checked += 1
    assert checked >= 2


def test_input_pixel_is_a_single_sample_at_its_jittered_position():
    r = VideoRenderer(sim.get_scene("everything"), (64, 64), (4,), spp=1)
    state = paths.timeline(r.scene, "train", 0, 3, 1.0)[2]
    jitter = np.array([0.3125, 0.8125], np.float32)
    color, depth, motion = r.input(state, 4, jitter)
    rng = np.random.default_rng(0)
    ij = rng.integers(0, 16, size=(20, 2))
    xy = np.stack([(ij[:, 1] + jitter[0]) / 16, (ij[:, 0] + jitter[1]) / 16], -1)
    single = r.points(state, xy)
    np.testing.assert_allclose(np.asarray(single["color"]), color[ij[:, 0], ij[:, 1]], atol=1e-6)
    np.testing.assert_allclose(np.asarray(single["depth"]), depth[ij[:, 0], ij[:, 1]], atol=1e-6)
    # ... and not the pixel centre's value everywhere (the jitter is real).
    centre = r.points(state, (ij[:, ::-1] + 0.5) / 16)
    assert np.abs(np.asarray(centre["color"]) - color[ij[:, 0], ij[:, 1]]).max() > 1e-3


def test_targets_cast_colour_alone_and_match_the_full_renderer():
    """Targets are cast without depth and motion (``make_split_renderer``'s ``shade``),
    inputs with them (``geometry``); on a scene with every effect (object motion
    included) both must give ``make_renderer``'s values, called on the same chunks
    (XLA may round one fusion differently: 1e-6, a few float32 ulps of a value <= 1).
    The colour alone must count fewer FLOPs per point than the whole."""
    scene = sim.get_scene("everything")
    r = VideoRenderer(scene, (32, 32), (4,), spp=4)
    state = paths.timeline(r.scene, "train", 0, 3, 1.0)[2]
    pix = np.arange(32 * 32)
    jy, jx = np.divmod(pix.astype(np.float32), np.float32(32))
    xy = np.concatenate([np.stack([(jx + ox) / 32, (jy + oy) / 32], -1) for ox, oy in r.offsets])
    arr, angle = render.state_arrays(state), r.pixel_angle(state)
    full = render.make_renderer(scene)
    c = r.chunk
    whole = [full(arr, jnp.asarray(xy[i:i + c]), angle) for i in range(0, len(xy), c)]
    ref = np.concatenate([np.asarray(w["color"]) for w in whole])
    ref = ref.reshape(4, -1, 3).mean(0, dtype=np.float64).astype(np.float32)
    np.testing.assert_allclose(r.target(state), ref.reshape(32, 32, 3), rtol=0, atol=1e-6)
    points = r.points(state, xy[:c])
    assert set(points) == {"color", "depth", "motion"}
    for k in points:
        np.testing.assert_allclose(points[k], np.asarray(whole[0][k]), rtol=0, atol=1e-6)
    xy0 = jnp.zeros((256, 2), jnp.float32)  # counted unrolled: XLA counts a loop body once
    shade, _ = render.make_split_renderer(scene, intersect="unrolled")
    assert (render.compiled_cost(shade, arr, xy0, 0.01)["flops"]
            < render.compiled_cost(render.make_renderer(scene, intersect="unrolled"), arr,
                                   xy0, 0.01)["flops"])


def _flops(scene):
    return render.flops_per_point(scene, 1024)


def _without(scene, effect):
    return dataclasses.replace(scene, effects=tuple(e for e in scene.effects if e != effect))


@pytest.mark.parametrize("effect", ["shadows", "texture_detail", "specular", "object_motion",
                                    "thin_geometry", "emissive_flicker"])
def test_declared_effects_decide_the_cost(effect):
    full = sim.get_scene("everything")
    assert _flops(_without(full, effect)) < _flops(full)


def _render(scene, frames=3, size=32):
    v = VideoRenderer(scene, (size, size), (4,), spp=1).video("train", 0, frames)
    return np.concatenate([v["target"].ravel(), v["x4"]["color"].ravel(),
                           v["x4"]["depth"].ravel(), v["x4"]["motion"].ravel()])


def _perturb(scene, effect):
    """The scene with the parameters of ``effect`` changed (they must be ignored when
    the effect is undeclared)."""
    objs = scene.objects
    if effect == "texture_detail":
        objs = tuple(dataclasses.replace(o, material=dataclasses.replace(
            o.material, texture="zoneplate", texture_scale=7.0)) for o in objs)
    elif effect == "thin_geometry":
        objs = objs + (sim.Object("rod", (0.0, 1.0, 0.0), (0.05, 1.0, 0)),)
    elif effect == "specular":
        objs = tuple(dataclasses.replace(o, material=dataclasses.replace(o.material, specular=2.0))
                     for o in objs)
    elif effect == "emissive_flicker":
        objs = tuple(dataclasses.replace(o, material=dataclasses.replace(o.material, emission=3.0))
                     for o in objs)
    elif effect == "object_motion":
        objs = tuple(dataclasses.replace(o, velocity=(0.3, 0.0, 0.1), spin=0.2) for o in objs)
    scene = dataclasses.replace(scene, objects=objs)
    if effect == "moving_light":
        scene = dataclasses.replace(scene, light=dataclasses.replace(scene.light, orbit_speed=0.5))
    if effect == "camera_motion":
        scene = dataclasses.replace(scene, path=dataclasses.replace(scene.path, speed=0.3))
    if effect == "camera_cut":
        scene = dataclasses.replace(scene, path=dataclasses.replace(scene.path, cut_every=1))
    return scene


@pytest.mark.parametrize("effect", [e for e in sim.EFFECTS if e != "shadows"])
def test_undeclared_effect_changes_no_pixel(effect):
    base = sim.Scene("probe", (), sim.get_scene("everything").objects, sim.Light(),
                     sim.Path("orbit"))
    reference = _render(base)
    np.testing.assert_array_equal(_render(_perturb(base, effect)), reference)
    # Declared, the same change is visible: the comparison above can fail.
    declared = dataclasses.replace(base, effects=(effect,))
    assert not np.array_equal(_render(_perturb(declared, effect)), reference)


def test_shadows_only_when_declared():
    base = sim.Scene("probe", (), sim.get_scene("plaza_day").objects, sim.Light(), sim.Path())
    with_shadows = dataclasses.replace(base, effects=("shadows",))
    a, b = _render(base), _render(with_shadows)
    assert not np.array_equal(a, b)
    assert (b <= a + 1e-7)[: 3 * 32 * 32 * 3].all()  # shadows only darken the target


def test_same_seed_same_bytes():
    a = sim.render_video(sim.get_scene("everything"), "val", 1, 3, size=(32, 32), factors=(4,))
    b = sim.render_video(sim.get_scene("everything"), "val", 1, 3, size=(32, 32), factors=(4,))
    assert a["target"].tobytes() == b["target"].tobytes()
    for k in ("color", "depth", "motion", "jitter"):
        assert a["x4"][k].tobytes() == b["x4"][k].tobytes()
    c = sim.render_video(sim.get_scene("everything"), "val", 2, 3, size=(32, 32), factors=(4,))
    assert c["target"].tobytes() != a["target"].tobytes()


def test_splits_use_different_paths():
    scene = sim.get_scene("camera_orbit")
    eyes = {s: paths.timeline(scene, s, 0, 1, 1.0)[0].camera.eye for s in paths.SPLITS}
    assert not np.allclose(eyes["train"], eyes["test"])
    assert not np.allclose(eyes["val"], eyes["test"])


def test_camera_cut_sets_reset():
    v = sim.render_video(sim.get_scene("cuts"), "train", 0, 22, size=(16, 16), factors=(4,),
                         spp=1)
    assert v["reset"][0] and v["reset"][20] and v["reset"].sum() == 2


def test_scene_json_round_trip_and_errors(tmp_path):
    scene = sim.get_scene("plaza_day")
    path = tmp_path / "scene.json"
    path.write_text(sim.to_json(scene))
    assert sim.from_json(path) == scene
    assert sim.from_json(sim.to_json(scene)) == scene
    with pytest.raises(ValueError, match="effects"):
        sim.from_json('{"name": "x", "effects": ["bloom"], "objects": []}')
    with pytest.raises(ValueError, match=r"objects\[0\].kind"):
        sim.from_json('{"name": "x", "effects": [], "objects": [{"kind": "torus"}]}')
    one = '{"name": "x", "effects": [], "objects": [{"kind": "plane"}]'
    with pytest.warns(UnknownKeyWarning, match="scene: unknown key 'colour' ignored"):
        got = sim.from_json(one + ', "colour": 1}')
    assert got == sim.from_json(one + "}")


def test_scene_file_with_unknown_keys_renders_and_warns_once_per_key(tmp_path, capsys):
    """A key the scene format does not define is ignored with one ``warning:`` line
    naming the file, the object, the key and a close known key when there is one; the
    scene then loads as if the key were absent."""
    from jtus import cli
    from jtus.sim import __main__ as sim_cli
    tree = json.loads(sim.to_json(sim.get_scene("plaza_day")))
    path = tmp_path / "s.json"
    path.write_text(json.dumps({**tree, "extra": 1, "objects": [
        {**tree["objects"][0], "materal": {}}] + tree["objects"][1:]}))
    with pytest.warns(UnknownKeyWarning) as got:
        scene = sim.from_json(path)
    assert scene == sim.get_scene("plaza_day")
    msgs = sorted(str(w.message) for w in got)
    assert len(msgs) == 2
    assert msgs[0].startswith(f"{path}: scene.objects[0]: unknown key 'materal' ignored "
                              "(did you mean 'material'?)")
    assert msgs[1].startswith(f"{path}: scene: unknown key 'extra' ignored;")
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        cli.run(lambda: sim_cli.main(["show", "--scene", str(path)]))
    assert e.value.code == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(line.startswith(f"warning: {path}: scene") for line in err)


def test_suite_covers_every_effect_alone():
    alone = {sim.get_scene(n).effects[0] for n in sim.SCENES if len(sim.get_scene(n).effects) == 1}
    assert len(sim.SCENES) >= 8
    # moving light is shown with shadows; hdr is added to scenes by the hdr preset
    assert set(sim.EFFECTS) - alone <= {"moving_light", "hdr"}


def _box_mean(renderer, state, offsets):
    """The box filter of one sample at each of ``offsets`` in every pixel, by hand."""
    h, w = renderer.H, renderer.W
    jy, jx = np.divmod(np.arange(h * w, dtype=np.float64), w)
    acc = sum(renderer.points(state, np.stack([(jx + ox) / w, (jy + oy) / h], -1)
                              .astype(np.float32))["color"].astype(np.float64)
              for ox, oy in offsets)
    return (acc / len(offsets)).reshape(h, w, 3)


def test_adaptive_target_is_4_16_or_64_samples_where_they_disagree():
    """``adaptive_target``: the rotated grid's 4 samples where nothing disagrees, the
    whole 4x4 grid (the uniform 16-sample target) and then the 8x8 grid as the
    thresholds fall; with the default thresholds each pixel is exactly one of the
    three, and the 4-sample pixels lie away from where the samples disagree."""
    scene = sim.get_scene("fence_pan")
    st = paths.timeline(scene, "test", 0, 1, 1.0)[0]
    r = VideoRenderer(scene, (24, 32), (4,), spp=16)
    four, c4 = r.adaptive_target(st, (2.0, 2.0))
    sixteen, c16 = r.adaptive_target(st, (-1.0, 2.0))
    many, c64 = r.adaptive_target(st, (-1.0, -1.0))
    assert (c4 == 4).all() and (c16 == 16).all() and (c64 == 64).all()
    np.testing.assert_allclose(four, _box_mean(r, st, ROTATED_GRID), atol=1e-6)
    np.testing.assert_allclose(sixteen, r.target(st), atol=1e-6)
    np.testing.assert_allclose(many, VideoRenderer(scene, (24, 32), (4,), spp=64).target(st),
                               atol=1e-6)
    got, count = r.adaptive_target(st)
    assert {4, 16, 64} == set(np.unique(count).tolist())
    for n, full in ((4, four), (16, sixteen), (64, many)):
        np.testing.assert_allclose(got[count == n], full[count == n], atol=1e-6)
    # where the 4 samples span an edge (the 4- and 16-sample values differ clearly), the
    # pixel was refined
    assert (count[np.abs(four - sixteen).max(-1) > 0.1] > 4).all()


@pytest.mark.parametrize("name", ["fence_pan", "everything", "random_3"])
def test_adaptive_target_is_closer_to_a_64_sample_reference_than_16_uniform(name):
    """The bound the adaptive targets are measured by (experiments/adaptive_targets.py):
    against a 64-sample jittered reference of the frame, sharing no sample position
    with either, the adaptive target is at least as close (PSNR) as the uniform
    16-sample target. (Its rays depend on the content: more than 16 per pixel on these
    busy 64x64 frames, 4-8 on game levels; docs/simulator.md.)"""
    scene = sim.random_scene(3) if name == "random_3" else sim.get_scene(name)
    st = paths.timeline(scene, "test", 0, 1, 1.0)[0]
    r = VideoRenderer(scene, (64, 64), (4,), spp=16)
    ref = r.jittered_reference(st, 8, seed=1)
    target, _ = r.adaptive_target(st)
    assert _psnr(target, ref) >= _psnr(r.target(st), ref)


def _psnr(a, b):
    return -10 * np.log10(np.mean((np.asarray(a, np.float64) - b) ** 2))


def test_jittered_reference_converges_to_the_grid_target():
    """``jittered_reference`` is a box filter of the pixel: with 16x16 cells it agrees
    with the 256-sample grid target of the same frame to 5e-3 RMS, closer than with
    8x8 cells; a new seed draws new points."""
    scene = sim.get_scene("fence_pan")
    st = paths.timeline(scene, "test", 0, 1, 1.0)[0]
    r = VideoRenderer(scene, (16, 16), (4,), spp=256)
    grid = r.target(st)
    rms = [np.sqrt(np.mean((r.jittered_reference(st, c, seed=0) - grid) ** 2)) for c in (8, 16)]
    assert rms[1] < min(rms[0], 5e-3)
    assert not np.array_equal(r.jittered_reference(st, 4, seed=0),
                              r.jittered_reference(st, 4, seed=1))


def _ray_meets_sphere(o, d, centre, radius, t_max=np.inf):
    """float64: does any ray ``o + t d`` (0 < t < t_max) pass within ``radius`` of
    ``centre``? ``o``, ``d`` [N,3]; ``t_max`` scalar or [N]."""
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    t = np.clip(((centre - o) * d).sum(-1), 0.0, t_max)
    return bool((np.linalg.norm(o + t[:, None] * d - centre, axis=-1) <= radius).any())


def test_culling_keeps_every_sphere_a_ray_of_the_bundle_meets():
    """``cone_keep`` (camera rays through a screen tile) and ``capsule_keep`` (shadow
    rays from a tile's hit points to a point light or along a directional light) are
    conservative: every sphere some ray passes within its radius of is kept (checked
    ray by ray in float64), and spheres well away from the bundle are dropped."""
    rng = np.random.default_rng(0)
    dropped = 0
    for case in range(60):
        centres = rng.uniform(-20, 20, (40, 3))
        radius = rng.uniform(0.05, 3.0, 40)
        eye = rng.uniform(-5, 5, 3)
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        spread = rng.uniform(0.001, 0.6)
        d = axis + spread * rng.uniform(-1, 1, (256, 3))
        keep = np.asarray(render.cone_keep(jnp.asarray(radius, jnp.float32),
                                           jnp.asarray(centres, jnp.float32),
                                           jnp.asarray(eye, jnp.float32),
                                           jnp.asarray(d, jnp.float32)))
        o = np.broadcast_to(eye, d.shape)
        met = np.array([_ray_meets_sphere(o, d, c, r) for c, r in zip(centres, radius)])
        assert not (met & ~keep).any(), (case, np.flatnonzero(met & ~keep))
        dropped += (~keep).sum()
        # shadow rays from scattered origins
        x = rng.uniform(-2, 2, 3) + rng.uniform(0.01, 3.0) * rng.uniform(-1, 1, (256, 3))
        hit = rng.random(256) < 0.8
        directional = case % 2 == 0
        to = axis if directional else rng.uniform(-20, 20, 3)
        keep = np.asarray(render.capsule_keep(
            jnp.asarray(radius, jnp.float32), jnp.asarray(centres, jnp.float32),
            jnp.asarray(x, jnp.float32), jnp.asarray(hit), jnp.asarray(to, jnp.float32),
            directional))
        xs = x[hit]
        dirs = np.broadcast_to(to, xs.shape) if directional else to - xs
        t_max = np.inf if directional else np.linalg.norm(to - xs, axis=-1)
        met = np.array([_ray_meets_sphere(xs, dirs, c, r, t_max)
                        for c, r in zip(centres, radius)])
        assert not (met & ~keep).any(), (case, np.flatnonzero(met & ~keep))
        dropped += (~keep).sum()
    assert dropped > 0.3 * 60 * 2 * 40  # culling is not everything kept
    none = render.capsule_keep(jnp.ones(3), jnp.zeros((3, 3)), jnp.zeros((4, 3)),
                               jnp.zeros(4, bool), jnp.ones(3) / 3 ** 0.5, True)
    assert not np.asarray(none).any()  # no hit point: no shadow ray to block


@pytest.mark.parametrize("name", ["random_3", "everything"])
def test_culled_rendering_equals_testing_every_object(name):
    """The tile-by-tile culling skips work, not values: targets and inputs of the
    culled renderer equal, bit for bit, those of the same loop with every object
    tested, on a randomized scene (24 objects, shadows of three lights) and the scene
    with every effect."""
    scene = sim.random_scene(3) if name == "random_3" else sim.get_scene(name)
    culled = VideoRenderer(scene, (64, 64), (4,), 16)
    every = VideoRenderer(scene, (64, 64), (4,), 16, intersect="every")
    a, b = culled.video("train", 1, 2), every.video("train", 1, 2)
    np.testing.assert_array_equal(a["target"], b["target"])
    for k in ("color", "depth", "motion"):
        np.testing.assert_array_equal(a["x4"][k], b["x4"][k])
