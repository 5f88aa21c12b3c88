"""The randomized scene family, the texture library, jitter variety, the ``diverse``
presets and ``python -m jtus.sim render``."""

import dataclasses
import json
import os

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

from jtus import sim
from jtus.data import __main__ as data_cli
from jtus.data import dataset
from jtus.sampling import jitter_sequence
from jtus.sampling.jitter import VARIETY
from jtus.sim import __main__ as sim_cli
from jtus.sim import generate, randomized, render, textures
from jtus.sim.scene import EFFECTS, KINDS, LDR_EFFECTS, PATHS, TEXTURES
from jtus.sim.video import VideoRenderer


def test_random_scene_is_deterministic_and_round_trips_json():
    for seed in range(12):
        a, b = sim.random_scene(seed), sim.random_scene(seed)
        assert a == b
        assert sim.from_json(sim.to_json(a)) == a
        assert a.name == f"random_{seed}" and sim.get_scene(a.name) == a
    assert sim.random_scene(1) != sim.random_scene(2)
    forced = sim.random_scene(5, effects=("shadows",))
    assert forced.effects == ("shadows",)
    # drawn effects do not change the geometry drawn for the seed beyond thin geometry
    assert sim.random_scene(5, effects=EFFECTS).path == sim.random_scene(5).path


def test_random_family_spans_every_kind_texture_path_and_effect():
    """Over the diverse preset's 200 training seeds: 8-40 visible objects per scene,
    every object kind, texture, path kind and effect; speeds from holds to fast."""
    kinds, texs, path_kinds, effects, speeds = set(), set(), set(), set(), []
    for seed in randomized.split_seeds("train", 200):
        sc = sim.random_scene(seed)
        n = sum(1 for o in sc.visible_objects()[1:] if o.size[0] < 4)  # not floor or walls
        assert 8 <= n <= 40, (seed, n)
        kinds |= {o.kind for o in sc.visible_objects()}
        if "texture_detail" in sc.effects:
            texs |= {o.material.texture for o in sc.objects}
        path_kinds.add(sc.path.kind)
        effects |= set(sc.effects)
        speeds.append(abs(sc.path.speed))
    assert kinds == set(KINDS)
    assert texs == set(TEXTURES)
    assert path_kinds == set(PATHS)
    assert effects == set(LDR_EFFECTS)  # every effect but hdr, which is asked for (hdr preset)
    assert min(speeds) < 0.001 and max(speeds) > 0.1


def test_random_scenes_reach_fast_motion():
    """The fast pan of seed 20 moves the image by more than 16 output pixels per
    frame (at 256x256; measured 52 px at the 99th percentile)."""
    sc = sim.random_scene(20)
    assert sc.path.kind == "pan"
    v = VideoRenderer(sc, (64, 64), (4,), 1).video("train", 0, 4)
    speed = np.linalg.norm(v["x4"]["motion"][1:], axis=-1) * 4 * (256 / 64)
    assert np.percentile(speed, 99) > 16


def test_split_seed_ranges_are_disjoint():
    p = generate.preset("diverse")
    names = {sp: set(p.splits[sp][0]) for sp in dataset.SPLITS}
    assert len(names["train"]) == 200
    assert not names["train"] & names["val"] and not names["train"] & names["test"]
    assert not names["val"] & names["test"]
    assert set(sim.SCENES) <= names["test"]  # the hand-made family tests too


def _flops(scene):
    return render.flops_per_point(scene, 256)


@pytest.mark.parametrize("texture", ["fbm", "glyphs"])
def test_a_texture_costs_only_where_declared(texture):
    sc = sim.random_scene(3, effects=("texture_detail",))
    objs = tuple(dataclasses.replace(o, material=dataclasses.replace(o.material, texture=texture))
                 for o in sc.objects)
    sc = dataclasses.replace(sc, objects=objs)
    plain = dataclasses.replace(sc, effects=())
    assert _flops(plain) < _flops(sc)
    # a scene using one texture pays for that one, not for the whole library
    mixed = dataclasses.replace(sc, objects=sim.random_scene(3, effects=EFFECTS).objects)
    assert _flops(sc) < _flops(mixed)


def test_extra_lights_cost_only_with_their_scene():
    sc = sim.random_scene(0)
    assert sc.extra_lights and "shadows" in sc.effects
    alone = dataclasses.replace(sc, extra_lights=())
    assert _flops(alone) < _flops(sc)


def _render(scene, size=32, frames=2):
    v = VideoRenderer(scene, (size, size), (4,), spp=1).video("train", 0, frames)
    return np.concatenate([v["target"].ravel(), v["x4"]["color"].ravel(),
                           v["x4"]["motion"].ravel()])


def test_random_scene_undeclared_effects_change_no_pixel():
    """A random scene with no effects declared renders the same bytes whatever its
    textures, lights' motion, emission and object velocities say."""
    sc = dataclasses.replace(sim.random_scene(3), effects=())
    ref = _render(sc)
    objs = tuple(dataclasses.replace(
        o, velocity=(0.5, 0, 0), spin=0.3, material=dataclasses.replace(
            o.material, texture="glyphs", emission=3.0, specular=1.0)) for o in sc.objects)
    changed = dataclasses.replace(sc, objects=objs, light=dataclasses.replace(sc.light,
                                                                               orbit_speed=1.0))
    np.testing.assert_array_equal(_render(changed), ref)
    declared = dataclasses.replace(changed, effects=("texture_detail",))
    assert not np.array_equal(_render(declared), ref)


# ---------------------------------------------------------------- textures


def _box_average(fn, u, width, n=20001):
    """The independent reference: the unfiltered pattern averaged over the footprint."""
    s = np.linspace(-0.5, 0.5, n) * width
    return np.mean(fn(u[:, None] + s[None]), axis=1)


def test_pulse_and_bar_filters_are_exact_box_filters():
    rng = np.random.default_rng(0)
    u = rng.uniform(-3, 3, 64)
    for m in (0.04, 0.3):
        for w in (0.01, 0.2, 1.7):
            got = np.asarray(textures.pulse_box(jnp.asarray(u), m, w))
            ref = _box_average(lambda x: (x - np.floor(x) < m).astype(float), u, w)
            np.testing.assert_allclose(got, ref, atol=2e-4)
    for a, b in ((0.1, 0.2), (0.45, 0.55)):
        for w in (0.02, 0.3):
            got = np.asarray(textures._bar_box(jnp.asarray(u), a, b, w))
            ref = _box_average(lambda x: ((x >= a) & (x < b)).astype(float), u, w)
            np.testing.assert_allclose(got, ref, atol=2e-4)


@pytest.mark.parametrize("name", sorted(textures.SEEDED_FNS))
def test_seeded_textures_are_bounded_and_prefiltered(name):
    """Values in [0, 1]; a footprint of several periods leaves little contrast (the
    pattern is filtered, not aliased); a tiny footprint keeps the detail; the seed
    changes the pattern."""
    fn = textures.SEEDED_FNS[name]
    rng = np.random.default_rng(1)
    u = jnp.asarray(rng.uniform(-20, 20, 4000), jnp.float32)
    v = jnp.asarray(rng.uniform(-20, 20, 4000), jnp.float32)
    seed = jnp.full(u.shape, 7, jnp.int32)
    sharp = np.asarray(fn(u, v, jnp.full(u.shape, 1e-3), seed))
    blurred = np.asarray(fn(u, v, jnp.full(u.shape, 8.0), seed))
    assert sharp.min() >= 0 and sharp.max() <= 1 and blurred.min() >= 0 and blurred.max() <= 1
    assert sharp.std() > 0.05
    assert blurred.std() < 0.25 * sharp.std()
    other = np.asarray(fn(u, v, jnp.full(u.shape, 1e-3), seed + 1))
    if name not in ("dots",):  # dots have no seeded part
        assert np.abs(other - sharp).max() > 0.05


# ---------------------------------------------------------------- jitter variety


@pytest.mark.parametrize("name", VARIETY)
def test_every_jitter_sequence_is_stored_and_read_back(name, tmp_path):
    p = generate.Preset((16, 16), (2, 4), 1, 1, {"train": ((), 1, 1), "val": ((), 1, 1),
                                                "test": (("objects",), 1, 5)}, (name,))
    out = tmp_path / "j.h5"
    generate.generate(p, out, progress=False)
    with dataset.Dataset(out) as ds:
        g = ds.file["test/objects_00"]
        assert g.attrs["jitter_sequence"] == name and g.attrs["jitter_phase"] == 0
        for f in (2, 4):
            frame, _ = ds.video("test", "objects_00", f)
            want = jitter_sequence(name, f)[:5]
            np.testing.assert_array_equal(frame.jitter[:, 0], want.astype(np.float32))


def test_variety_draws_per_video_and_records_it(tmp_path):
    draws = {generate.video_jitter(VARIETY, f"random_{s}", "train", 0) for s in range(40)}
    assert {d[0] for d in draws} == set(VARIETY)
    assert len({d[1] for d in draws}) > 10  # phases vary too
    assert generate.video_jitter(("thesis",), "random_1", "train", 0) == ("thesis", 0)
    out = tmp_path / "d.h5"
    generate.generate("diverse-tiny", out, progress=False)
    with dataset.Dataset(out) as ds:
        for split in dataset.SPLITS:
            for name in ds.videos(split):
                g = ds.file[f"{split}/{name}"]
                seq = jitter_sequence(g.attrs["jitter_sequence"], 4)
                ph = int(g.attrs["jitter_phase"])
                want = seq[(np.arange(g["target"].shape[0]) + ph) % len(seq)]
                np.testing.assert_array_equal(g["x4/jitter"][:], want.astype(np.float32))
        assert ds.videos("train") == [f"random_{s}_00" for s in range(3)]


# ---------------------------------------------------------------- CLI


def test_sim_render_cli_writes_a_dataset_and_refuses_bad_input(tmp_path, capsys):
    spec = tmp_path / "mine.json"
    spec.write_text(sim.to_json(dataclasses.replace(sim.random_scene(2), name="mine")))
    out = tmp_path / "mine.h5"
    assert sim_cli.main(["render", "--scene", str(spec), "--random", "9", "--effects",
                         "camera_motion,texture_detail", "--size", "16", "--frames", "3",
                         "--spp", "1", "--jitter", "halton8", "--out", str(out), "--quiet"]) == 0
    with dataset.Dataset(out) as ds:
        assert ds.videos("test") == ["mine_00", "random_9_00"]
        g = ds.file["test/mine_00"]
        assert json.loads(g.attrs["effects"]) == ["camera_motion", "texture_detail"]
        assert g.attrs["jitter_sequence"] == "halton8"
        frame, target = ds.video("test", "random_9_00", 4)
        assert frame.color.shape == (3, 1, 4, 4, 3) and target.shape == (3, 1, 16, 16, 3)
    before = out.read_bytes()
    bad = [(["--random", "1", "--out", str(out)], "exists"),
           (["--random", "1", "--effects", "bloom", "--out", str(tmp_path / "b.h5")], "bloom"),
           (["--random", "1", "--size", "30", "--out", str(tmp_path / "b.h5")], "--size"),
           (["--random", "1", "--jitter", "sobol", "--out", str(tmp_path / "b.h5")], "sobol"),
           (["--scene", str(tmp_path / "none.json"), "--out", str(tmp_path / "b.h5")],
            "does not exist"),
           (["--random", "1", "--out", str(tmp_path)], "folder"),
           (["--out", str(tmp_path / "b.h5")], "give --scene")]
    for args, msg in bad:
        capsys.readouterr()
        assert sim_cli.main(["render"] + args) == 2, args
        assert msg in capsys.readouterr().err, args
    assert out.read_bytes() == before
    assert not (tmp_path / "b.h5").exists()
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{not json")
    assert sim_cli.main(["render", "--scene", str(bad_json), "--out", str(tmp_path / "c.h5")]) == 2
    assert "bad.json" in capsys.readouterr().err


def test_sim_render_writes_adaptive_targets_and_info_names_them(tmp_path, capsys):
    """``--targets adaptive``: the videos' targets are ``VideoRenderer.adaptive_target``'s
    and the file says so (``targets`` attr, ``spp`` 0); ``--spp`` beside it is refused
    before anything is written."""
    out = tmp_path / "a.h5"
    assert sim_cli.main(["render", "--random", "3", "--size", "16", "--frames", "2",
                         "--targets", "adaptive", "--out", str(out), "--quiet"]) == 0
    scene = sim.random_scene(3)
    r = VideoRenderer(scene, (16, 16), (2, 4), targets="adaptive")
    st = r.timeline("test", 0, 2)[1]
    with dataset.Dataset(out) as ds:
        assert (ds.file.attrs["targets"], ds.file.attrs["spp"]) == ("adaptive", 0)
        _, target = ds.video("test", "random_3_00", 4)
        np.testing.assert_allclose(target[1, 0], r.adaptive_target(st)[0], atol=1e-3)
    capsys.readouterr()
    assert data_cli.main(["info", str(out)]) == 0
    assert "adaptive targets" in capsys.readouterr().out
    assert sim_cli.main(["render", "--random", "3", "--targets", "adaptive", "--spp", "8",
                         "--out", str(tmp_path / "b.h5")]) == 2
    assert "--spp" in capsys.readouterr().err and not (tmp_path / "b.h5").exists()
    with pytest.raises(SystemExit):  # argparse's choices
        sim_cli.main(["render", "--random", "3", "--targets", "sparse",
                      "--out", str(tmp_path / "b.h5")])
    assert not (tmp_path / "b.h5").exists()


def test_sim_show_and_preview_take_the_same_scenes(tmp_path, capsys):
    assert sim_cli.main(["show", "--random", "11"]) == 0
    assert sim.from_json(capsys.readouterr().out) == sim.random_scene(11)
    out = tmp_path / "p.png"
    assert sim_cli.main(["preview", "--random", "11", "--scene", "thin", "--size", "16",
                         "--frame", "1", "--spp", "1", "--out", str(out)]) == 0
    from PIL import Image
    assert Image.open(out).size == (4 * 16, 2 * 16)


def test_parallel_generation_writes_the_same_file(tmp_path):
    """``workers=2`` (two processes, scenes dealt between them, then copied into one
    file in the preset's order) writes the videos ``workers=1`` writes, attributes and
    arrays equal; a worker that fails leaves no file and names the failure."""
    p = generate.Preset((16, 16), (4,), 1, 1, {"train": (("objects", "camera_orbit"), 1, 2),
                                               "val": (("objects",), 1, 2),
                                               "test": ((), 1, 1)})
    one, two = tmp_path / "one.h5", tmp_path / "two.h5"
    generate.generate(p, one, progress=False, workers=1)
    generate.generate(p, two, progress=False, workers=2)

    def contents(path):
        out = {}
        with h5py.File(path, "r") as fh:
            fh.visititems(lambda name, obj: out.__setitem__(name, (
                {k: np.asarray(v).tolist() for k, v in obj.attrs.items()},
                obj[()] if isinstance(obj, h5py.Dataset) else None)))
        return out

    a, b = contents(one), contents(two)
    assert list(a) == list(b) and len(a) > 10
    for k in a:
        assert a[k][0] == b[k][0], k
        if a[k][1] is not None:
            np.testing.assert_array_equal(a[k][1], b[k][1], err_msg=k)
    bad = dataclasses.replace(p, size=(18, 18))  # not a multiple of the factor
    with pytest.raises(RuntimeError, match="worker processes failed"):
        generate.generate(bad, tmp_path / "bad.h5", progress=False, workers=2)
    with pytest.raises(ValueError, match="divisible"):
        generate.generate(bad, tmp_path / "bad.h5", progress=False, workers=1)
    assert sorted(os.listdir(tmp_path)) == ["one.h5", "two.h5"]


def test_cost_table_has_a_header_and_both_ratios():
    """``python -m jtus.sim cost``'s table: XLA's FLOPs per point and the wall time,
    each beside its ratio to the scene with no effect."""
    rows = [("none", (), 1000.0, 0.4), ("shadows", ("shadows",), 2500.0, 0.9)]
    lines = sim_cli.cost_table(rows).splitlines()
    assert lines[0] == ("| effects | FLOP per point (XLA) | x no effect | ms per frame | "
                        "x no effect |") and lines[1].startswith("| --- |")
    assert lines[2:] == ["| none | 1,000 | 1.00 | 400 | 1.00 |",
                         "| shadows | 2,500 | 2.50 | 900 | 2.25 |"]


@pytest.mark.parametrize("edit,message", [
    (lambda d: d["path"].update(fov_y=0), "path.fov_y: expected radians"),
    (lambda d: d["path"].update(fov_y=float("nan")), "path.fov_y: expected a finite number"),
    (lambda d: d["path"].update(radius="6"), "path.radius: expected a finite number, got '6'"),
    (lambda d: d["path"].update(center=[float("inf"), 0, 0]), "path.center: expected a list of 3"),
    (lambda d: d.update(objects=None), "objects: expected a list, got None"),
    (lambda d: d.update(objects=[]), "objects: expected at least one object"),
    (lambda d: d["objects"][0]["material"].update(color=[1, 2]), "material.color: expected a list"),
    (lambda d: d["objects"][0].update(position=[float("nan"), 0, 0]), "position: expected"),
    (lambda d: d["light"].update(vector=[0, 0, 0]), "light.vector: a directional light"),
    (lambda d: d["objects"][-1].update(size=[0, 0, 0]), "size: a "),
])
def test_scene_json_that_makes_no_picture_is_refused(tmp_path, capsys, edit, message):
    """Each field of a user's scene JSON is checked on load (types, finiteness, lengths,
    values that make a picture): one error line naming the file and field, exit 2,
    nothing written."""
    d = json.loads(sim.to_json(sim.random_scene(7)))
    edit(d)
    path = tmp_path / "s.json"
    path.write_text(json.dumps(d))
    out = tmp_path / "s.h5"
    assert sim_cli.main(["render", "--scene", str(path), "--out", str(out), "--size", "32",
                         "--frames", "2"]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and message in err, err
    assert sorted(os.listdir(tmp_path)) == ["s.json"]


def test_every_built_in_and_randomized_scene_passes_its_own_schema():
    for name in sim.SCENES:
        assert sim.from_json(sim.to_json(sim.get_scene(name))) == sim.get_scene(name)
    for seed in range(50):
        sc = sim.random_scene(seed, effects=EFFECTS)
        assert sim.from_json(sim.to_json(sc)) == sc
