"""HDF5 datasets, EXR import/export, atomic writes, and the data/sim CLIs."""

import dataclasses
import os

import h5py
import numpy as np
import pytest

from jtus import sim, upsample
from jtus.data import __main__ as data_cli
from jtus.data import conventions, dataset, exr
from jtus.sim import __main__ as sim_cli
from jtus.sim import generate


def test_layout_and_round_trip(tiny_data):
    with h5py.File(tiny_data, "r") as fh:
        assert fh.attrs["format"] == "jtus-dataset" and fh.attrs["version"] == 1
        assert fh.attrs["spp"] == 4 and "motion" in fh.attrs["conventions"]
        g = fh["train/camera_orbit_00"]
        assert g.attrs["scene"] == "camera_orbit" and "camera_motion" in g.attrs["effects"]
        assert g["target"].shape == (8, 32, 32, 3) and g["x4/color"].shape == (8, 8, 8, 3)
        assert g["x2/motion"].shape == (8, 16, 16, 2) and g["x4/jitter"].shape == (8, 2)
        assert g["x4"].attrs["mip_bias"] == -2.0  # eq. 47 at f=4 matching 1 spp
        stored = {k: g[f"x4/{k}"][:] for k in ("color", "depth", "motion", "jitter")}
        target = g["target"][:]
    ref = sim.render_video(sim.get_scene("camera_orbit"), "train", 0, 8, size=(32, 32),
                           factors=(2, 4), spp=4)
    np.testing.assert_array_equal(target, ref["target"].astype(np.float16))
    np.testing.assert_array_equal(stored["color"], ref["x4"]["color"].astype(np.float16))
    for k in ("depth", "motion", "jitter"):
        np.testing.assert_array_equal(stored[k], ref["x4"][k])


def test_crops_are_aligned(tiny_data):
    with dataset.Dataset(tiny_data) as ds:
        frames, targets, index = ds.crops("train", 4, 3, 5, 16, np.random.default_rng(1),
                                          return_index=True)
        assert frames.color.shape == (5, 3, 4, 4, 3) and targets.shape == (5, 3, 16, 16, 3)
        assert frames.reset[0].all()
        for b, (name, t0, y, x) in enumerate(index):
            full, tgt = ds.video("train", name, 4)
            ts = slice(t0, t0 + 5)
            np.testing.assert_array_equal(frames.color[:, b], full.color[ts, 0, y:y + 4, x:x + 4])
            np.testing.assert_array_equal(frames.motion[:, b], full.motion[ts, 0, y:y + 4, x:x + 4])
            np.testing.assert_array_equal(frames.jitter[:, b], full.jitter[ts, 0])
            np.testing.assert_array_equal(targets[:, b],
                                          tgt[ts, 0, 4 * y:4 * y + 16, 4 * x:4 * x + 16])
        with pytest.raises(ValueError, match="crop"):
            ds.crops("train", 4, 1, 2, 18, np.random.default_rng(0))
        with pytest.raises(ValueError, match="factor"):
            ds.crops("train", 3, 1, 2, 12, np.random.default_rng(0))


def test_generate_is_deterministic(tiny_data, tmp_path):
    again = tmp_path / "again.h5"
    generate.generate("tiny", again, progress=False)

    def contents(path):
        out = {}
        with h5py.File(path, "r") as fh:
            fh.visititems(lambda k, v: out.__setitem__(k, v[()].tobytes())
                          if isinstance(v, h5py.Dataset) else None)
        return out

    assert contents(again) == contents(tiny_data)


def test_generated_holds_move_then_stand_still(tmp_path):
    """A preset with ``hold_from``: each video is the scene's own video up to that
    frame, then the last moving frame's scene with only the jitter moving: the same
    target, zero motion, the input of the same jitter position repeated, no reset."""
    p = dataclasses.replace(generate.preset("tiny"), splits={
        "train": (("camera_orbit",), 1, 24), "val": ((), 1, 1), "test": ((), 1, 1)},
        jitters=("thesis",), hold_from=5)
    generate.generate(p, tmp_path / "holds.h5", progress=False)
    ref = sim.render_video(sim.get_scene("camera_orbit"), "train", 0, 5, size=(32, 32),
                           factors=(2, 4), spp=4)
    with h5py.File(tmp_path / "holds.h5", "r") as fh:
        g = fh["train/camera_orbit_00"]
        assert g.attrs["hold_from"] == 5 and g["target"].shape[0] == 24
        target, reset = g["target"][:], g["reset"][:]
        x4 = {k: g[f"x4/{k}"][:] for k in ("color", "depth", "motion", "jitter")}
    np.testing.assert_array_equal(target[:5], ref["target"].astype(np.float16))
    np.testing.assert_array_equal(x4["motion"][:5], ref["x4"]["motion"])
    assert np.abs(ref["x4"]["motion"][1:5]).max() > 0.01  # the camera moved before
    assert (target[5:] == target[4]).all() and not x4["motion"][5:].any()
    assert reset[0] and not reset[1:].any()
    # frames 16 apart share the thesis's jitter position, and so their input
    np.testing.assert_array_equal(x4["jitter"][5], x4["jitter"][21])
    np.testing.assert_array_equal(x4["color"][5], x4["color"][21])
    assert not np.array_equal(x4["color"][5], x4["color"][6])


def test_continued_hold_equals_a_longer_rendered_hold(tmp_path):
    """``extend_holds``: a held video read past its stored length gives exactly the
    frames of the same hold rendered that long (jitter period 8 here, at both factors;
    the phase differs per video); a video whose hold spans less than one period, or
    one without a hold, is not drawn, and without ``extend_holds`` a sequence longer
    than a video is refused by name."""
    def held(name, length, hold_from=5):
        p = dataclasses.replace(generate.preset("tiny"), splits={
            "train": (("camera_orbit",), 1, length), "val": ((), 1, 1), "test": ((), 1, 1)},
            jitters=("halton8",), hold_from=hold_from)
        generate.generate(p, tmp_path / name, progress=False)
        return dataset.Dataset(tmp_path / name)

    with held("short.h5", 5 + 8) as short, held("long.h5", 5 + 30) as long, \
            held("shorter.h5", 5 + 7) as shorter:
        for f in (4, 2):
            assert short.hold_period("train", "camera_orbit_00", f) == (5, 8)
            a, ta = short.crops("train", f, 1, 35, 32, np.random.default_rng(0),
                                extend_holds=True)
            b, tb = long.crops("train", f, 1, 35, 32, np.random.default_rng(0))
            for x, y in zip(a, b):
                np.testing.assert_array_equal(x, y)
            np.testing.assert_array_equal(ta, tb)
        with pytest.raises(ValueError, match="not even with its hold continued"):
            shorter.crops("train", 4, 1, 35, 32, np.random.default_rng(0), extend_holds=True)
        with pytest.raises(ValueError, match="exceeds the length 13 of video 'camera_orbit_00'"):
            short.crops("train", 4, 1, 35, 32, np.random.default_rng(0))


def test_interrupted_generate_leaves_no_file(tmp_path, monkeypatch):
    from jtus.sim import video

    calls = []
    real = video.VideoRenderer.video

    def interrupted(self, *args, **kw):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(self, *args, **kw)

    monkeypatch.setattr(video.VideoRenderer, "video", interrupted)
    out = tmp_path / "sub" / "data.h5"
    with pytest.raises(KeyboardInterrupt):
        generate.generate("tiny", out, progress=False)
    assert not out.exists()
    assert os.listdir(tmp_path / "sub") == []


def test_dataset_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="generate it"):
        dataset.Dataset(tmp_path / "missing.h5")
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"garbage")
    with pytest.raises(ValueError, match="not a readable HDF5"):
        dataset.Dataset(bad)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as fh:
        fh.attrs["format"] = "something-else"
    with pytest.raises(ValueError, match="format"):
        dataset.Dataset(other)


def _exr_sequence(tmp_path, video, factor):
    """Write a rendered video as an external renderer might: motion in UV units with
    y up, pointing previous-to-current; view-space depth under the name 'depth.V'.
    Returns the input and target folders and the sidecar that describes them."""
    lr, hr = tmp_path / "lr", tmp_path / "hr"
    lr.mkdir()
    hr.mkdir()
    near, far = 0.1, 100.0
    x = video[f"x{factor}"]
    h, w = x["color"].shape[1:3]
    for t in range(len(video["target"])):
        mv = x["motion"][t].astype(np.float64)
        uv_up = -np.stack([mv[..., 0] / w, -mv[..., 1] / h], -1)
        view = conventions.view_depth(x["depth"][t, ..., 0].astype(np.float64), near, far)
        exr.write_exr(lr / f"f{t:03d}.exr", {"R": x["color"][t, ..., 0], "G": x["color"][t, ..., 1],
                                             "B": x["color"][t, ..., 2], "depth.V": view,
                                             "vec.u": uv_up[..., 0], "vec.v": uv_up[..., 1]})
        exr.write_exr(hr / f"f{t:03d}.exr", {c: video["target"][t, ..., i]
                                             for i, c in enumerate("RGB")})
    sidecar = tmp_path / "spec.json"
    sidecar.write_text(SIDECAR)
    return lr, hr, sidecar


# the ImportSpec sidecar describing what _exr_sequence writes
SIDECAR = ('{"depth": "depth.V", "depth_kind": "view", "motion": ["vec.u", "vec.v"],'
           ' "motion_units": "uv", "motion_y_up": true, "motion_negate": true}')


def test_exr_import_converts_conventions(tmp_path):
    video = sim.render_video(sim.get_scene("objects"), "test", 0, 4, size=(32, 32), factors=(4,),
                             spp=1)
    lr, hr, sidecar = _exr_sequence(tmp_path, video, 4)
    out = tmp_path / "imported.h5"
    assert data_cli.main(["import-exr", "--input", str(lr), "--target", str(hr), "--factor", "4",
                          "--sidecar", str(sidecar), "--out", str(out)]) == 0
    with dataset.Dataset(out) as ds:
        frames, targets = ds.video("test", "video_00", 4)
    x = video["x4"]
    np.testing.assert_allclose(frames.motion[:, 0], x["motion"], atol=1e-5)
    np.testing.assert_allclose(frames.depth[:, 0], x["depth"], atol=1e-6)
    np.testing.assert_array_equal(frames.color[:, 0], x["color"].astype(np.float16))
    np.testing.assert_array_equal(targets[:, 0], video["target"].astype(np.float16))
    np.testing.assert_array_equal(frames.jitter[:, 0], x["jitter"])  # thesis 4x4 pattern
    # The same folder, without targets, through the upsampler.
    out_dir = tmp_path / "up"
    assert upsample.main(["--input", str(lr), "--exr-spec", str(sidecar), "--factor", "4",
                          "--model", "tus", "--out", str(out_dir), "--format", "exr"]) == 0
    chans, _ = exr.read_exr(out_dir / "frame0003.exr")
    assert chans["R"].shape == (32, 32)


def test_exr_import_errors(tmp_path, capsys):
    video = sim.render_video(sim.get_scene("objects"), "test", 0, 2, size=(16, 16), factors=(4,),
                             spp=1)
    lr, hr, _ = _exr_sequence(tmp_path, video, 4)  # read without its sidecar below
    out = tmp_path / "x.h5"
    rc = data_cli.main(["import-exr", "--input", str(lr), "--target", str(hr), "--factor", "4",
                        "--out", str(out)])
    assert rc == 2 and not out.exists()
    err = capsys.readouterr().err
    assert "depth needs channels ['Z']" in err and "depth.V" in err
    rc = data_cli.main(["import-exr", "--input", str(lr), "--target", str(hr), "--factor", "2",
                        "--depth", "depth.V", "--depth-kind", "view", "--motion", "vec.u,vec.v",
                        "--out", str(out)])
    assert rc == 2 and "not factor 2" in capsys.readouterr().err
    (lr / "f000.exr").write_bytes(b"broken")
    with pytest.raises(ValueError, match="f000.exr: not a readable EXR"):
        exr.read_exr(lr / "f000.exr")


def test_exr_and_png_sequences(tmp_path):
    frames = np.random.default_rng(0).uniform(size=(2, 5, 7, 3)).astype(np.float32)
    paths = exr.write_sequence(frames, tmp_path / "e", "exr")
    chans, _ = exr.read_exr(paths[1])
    np.testing.assert_array_equal(np.stack([chans[c] for c in "RGB"], -1), frames[1])
    # OpenEXR writes a non-contiguous array wrong: jtus must make it contiguous
    noncontig = np.ascontiguousarray(frames[0])[:, ::-1]
    exr.write_exr(tmp_path / "n.exr", {"R": noncontig[..., 0]})
    np.testing.assert_array_equal(exr.read_exr(tmp_path / "n.exr")[0]["R"], noncontig[..., 0])
    pngs = exr.write_sequence(frames, tmp_path / "p", "png")
    assert len(pngs) == 2 and os.path.getsize(pngs[0]) > 0


def test_cli_smoke(tiny_data, tmp_path, capsys):
    assert data_cli.main(["info", "--dataset", str(tiny_data)]) == 0
    assert "train: 2 videos" in capsys.readouterr().out
    assert data_cli.main(["export", "--dataset", str(tiny_data), "--split", "test", "--video",
                          "objects_00", "--what", "color@4", "--format", "png",
                          "--out", str(tmp_path / "png")]) == 0
    assert len(os.listdir(tmp_path / "png")) == 8
    assert sim_cli.main(["list"]) == 0
    out = tmp_path / "strip.png"
    assert sim_cli.main(["preview", "--scene", "thin", "--out", str(out), "--size", "32",
                         "--frame", "1", "--spp", "1"]) == 0
    assert out.exists()


def test_exr_import_refuses_bad_values_and_frame_numbering(tmp_path, capsys):
    """Each defect: an error naming the file and field, exit 2, no file written."""
    import shutil

    video = sim.render_video(sim.get_scene("objects"), "test", 0, 3, size=(16, 16), factors=(4,),
                             spp=1)
    lr, hr, spec = _exr_sequence(tmp_path, video, 4)
    out = tmp_path / "x.h5"

    def run(lr_dir=lr, hr_dir=hr, sidecar=spec):
        capsys.readouterr()
        rc = data_cli.main(["import-exr", "--input", str(lr_dir), "--target", str(hr_dir),
                            "--factor", "4", "--sidecar", str(sidecar), "--out", str(out)])
        return rc, capsys.readouterr().err

    assert run()[0] == 0 and out.exists()
    out.unlink()

    def with_channel(name, value, folder=lr, frame="f001.exr"):
        d = tmp_path / f"bad-{name}-{len(os.listdir(tmp_path))}"
        shutil.copytree(folder, d)
        chans, _ = exr.read_exr(d / frame)
        chans[name] = np.full_like(chans[name], value)
        exr.write_exr(d / frame, chans)
        return d

    for name, value, msg in (("R", np.nan, "color (linear, stored as float16) has"),
                             ("R", 1e6, "color (linear, stored as float16) has values above "
                                        "65504"),
                             ("G", -0.5, "color (linear, stored as float16) has values below 0"),
                             ("vec.u", np.inf, "motion has"),
                             ("depth.V", -1.0, "depth (view) has values below 0"),
                             ("depth.V", np.nan, "depth (view) has")):
        rc, err = run(lr_dir=with_channel(name, value))
        assert rc == 2 and msg in err and "f001.exr" in err, (name, err)
        assert not out.exists()
    rc, err = run(hr_dir=with_channel("G", np.nan, folder=hr))
    assert rc == 2 and "target (linear, stored as float16) has 256 NaN" in err
    rc, err = run(hr_dir=with_channel("B", -1.0, folder=hr))
    assert rc == 2 and "target (linear, stored as float16) has values below 0" in err
    for jit, msg in (("[1.2, 0.3]", "jitter: expected values in [0, 1)"),
                     ("[NaN, 0.3]", "NaN")):
        bad = tmp_path / "jit.json"
        bad.write_text(spec.read_text()[:-1] + f', "jitter": {jit}}}')
        rc, err = run(sidecar=bad)
        assert rc == 2 and msg in err, err
    # frame numbers, not text order: f2 comes before f10; a gap or a mismatch is refused
    d_lr, d_hr = tmp_path / "num-lr", tmp_path / "num-hr"
    for src, dst in ((lr, d_lr), (hr, d_hr)):
        dst.mkdir()
        for t, newname in enumerate(("frame2.exr", "frame9.exr", "frame10.exr")):
            shutil.copyfile(src / f"f{t:03d}.exr", dst / newname)
    rc, err = run(d_lr, d_hr)
    assert rc == 2 and "frames [3, 4, 5, 6, 7, 8] are missing" in err
    (d_lr / "frame9.exr").rename(d_lr / "frame3.exr")
    (d_hr / "frame9.exr").rename(d_hr / "frame3.exr")
    (d_lr / "frame10.exr").rename(d_lr / "frame4.exr")
    (d_hr / "frame10.exr").rename(d_hr / "frame04.exr")
    assert run(d_lr, d_hr)[0] == 0
    with dataset.Dataset(out) as ds:
        frames, _ = ds.video("test", "video_00", 4)
    np.testing.assert_array_equal(frames.color[:, 0], video["x4"]["color"].astype(np.float16))
    out.unlink()
    (d_hr / "frame2.exr").rename(d_hr / "frame5.exr")  # targets 3-5 against inputs 2-4
    rc, err = run(d_lr, d_hr)
    assert rc == 2 and "frames do not pair" in err and "no target for [2]" in err
    assert "no input for [5]" in err
    assert not out.exists()


def test_y_up_jitter_on_the_edge_stays_legal():
    from jtus.data import conventions

    j = conventions.jitter_to_jtus(np.array([[0.25, 0.0], [0.5, 0.5]]), "unit", y_up=True)
    assert np.all((j >= 0) & (j < 1)) and j[1, 1] == 0.5 and j[0, 1] > 0.999999
    c = conventions.jitter_to_jtus(np.array([0.0, -0.5]), "centered", y_up=True)
    assert np.all((c >= 0) & (c < 1))


def test_import_exr_refuses_bad_names_outputs_and_sidecars(tmp_path, capsys):
    video = sim.render_video(sim.get_scene("objects"), "test", 0, 2, size=(16, 16), factors=(4,),
                             spp=1)
    lr, hr, good = _exr_sequence(tmp_path, video, 4)
    out = tmp_path / "x.h5"
    base = ["import-exr", "--input", str(lr), "--target", str(hr), "--factor", "4"]
    assert data_cli.main(base + ["--sidecar", str(good), "--out", str(out)]) == 0
    before = out.read_bytes()
    cases = [(["--sidecar", str(good), "--out", str(out)], "exists"),
             (["--sidecar", str(good), "--out", str(tmp_path)], "is a folder"),
             (["--sidecar", str(good), "--out", str(tmp_path / "y.h5"), "--name", "a/b"], "--name"),
             (["--sidecar", str(good), "--out", str(tmp_path / "y.h5"), "--name", "."], "--name")]
    for text, msg in (('{"motion_y_up": "no"}', "motion_y_up: expected true or false"),
                      ('{"color": ["R", "G"]}', "color: expected 3 channel names"),
                      ('{"near": "0.1"}', "near: expected a finite number"),
                      ('{"far": null}', "far: expected a finite number"),
                      ('{"far": NaN}', "far: expected a finite number"),
                      ('{"jitter": {"x": 1}}', "jitter: expected 'thesis', one [x, y]"),
                      ('{"jitter": ["a", "b"]}', "jitter: expected 'thesis', one [x, y]"),
                      ('{"depth_kind": "log"}', "depth_kind: expected one of"),
                      ('{not json', "not valid JSON"), ('[1, 2]', "expected a JSON object")):
        bad = tmp_path / f"bad{len(cases)}.json"
        bad.write_text(text)
        cases.append((["--sidecar", str(bad), "--out", str(tmp_path / "y.h5")], msg))
    binary = tmp_path / "binary.json"
    binary.write_bytes(b"\x80\x81\x82")
    cases += [(["--sidecar", str(binary), "--out", str(tmp_path / "y.h5")], "not a UTF-8"),
              (["--sidecar", str(tmp_path), "--out", str(tmp_path / "y.h5")], "is a folder")]
    for args, msg in cases:
        capsys.readouterr()
        assert data_cli.main(base + args) == 2, args
        err = capsys.readouterr().err
        assert msg in err, (args, err)
    assert out.read_bytes() == before and not (tmp_path / "y.h5").exists()
    assert data_cli.main(base + ["--sidecar", str(good), "--out", str(out), "--force"]) == 0
    (lr / "frame0099.exr").mkdir()  # a folder with an EXR's name
    assert data_cli.main(base + ["--sidecar", str(good), "--out", str(tmp_path / "y.h5")]) == 2
    assert "expected an EXR file, got a folder" in capsys.readouterr().err
    assert not (tmp_path / "y.h5").exists()


def test_videos_record_their_depth_planes(tiny_data):
    """Each generated video records the near/far planes its device depth was made
    with (the scene's, by default conventions.NEAR/FAR)."""
    from jtus.data.conventions import FAR, NEAR

    with dataset.Dataset(tiny_data) as ds:
        for split in dataset.SPLITS:
            for name in ds.videos(split):
                g = ds.group(split, name)
                assert (float(g.attrs["near"]), float(g.attrs["far"])) == (NEAR, FAR), name


@pytest.mark.parametrize("variant", [
    {"motion_units": "ndc"}, {"motion_units": "uv", "motion_y_up": True},
    {"motion_units": "pixels", "motion_negate": True},
    {"depth_kind": "reversed"}, {"depth_kind": "linear"}, {"depth_kind": "view"},
    {"jitter_kind": "centered"}, {"jitter_y_up": True},
    {"jitter_kind": "centered", "jitter_y_up": True}])
def test_exr_import_every_convention_flag(tmp_path, variant):
    """A hand-built EXR sequence in each source convention, written from jtus-convention
    values by the conventions' definitions (docs/conventions.md), imports back to those
    values: motion in LR pixels, y down, backward; D3D device depth; jitter in [0,1)
    from the pixel's top-left, per frame."""
    from jtus.data import exr

    rng = np.random.default_rng(7)
    T, h, w, f, near, far = 3, 6, 8, 2, 0.1, 100.0
    color = rng.uniform(size=(T, h, w, 3))
    device = rng.uniform(0.05, 0.95, size=(T, h, w))
    motion = rng.uniform(-3, 3, size=(T, h, w, 2))
    jitter = rng.uniform(0.05, 0.95, size=(T, 2))
    spec = exr.ImportSpec(near=near, far=far, jitter=jitter.tolist(), **variant)
    v = motion.copy()
    if spec.motion_negate:  # the source stores current minus previous position
        v = -v
    if spec.motion_y_up:
        v[..., 1] = -v[..., 1]
    v = v / {"pixels": (1, 1), "uv": (w, h), "ndc": (w / 2, h / 2)}[spec.motion_units]
    z = near * far / (far - device * (far - near))  # view depth of the D3D projection
    d = {"device": device, "reversed": 1 - device, "linear": (z - near) / (far - near),
         "view": z}[spec.depth_kind]
    j = jitter.copy()
    if spec.jitter_y_up:  # measured from the pixel's bottom edge
        j[:, 1] = 1 - j[:, 1]
    if spec.jitter_kind == "centered":
        j = j - 0.5
    spec = dataclasses.replace(spec, jitter=j.tolist())
    src = tmp_path / "lr"
    src.mkdir()
    for t in range(T):
        exr.write_exr(src / f"f{t:03d}.exr", {"R": color[t, ..., 0], "G": color[t, ..., 1],
                                              "B": color[t, ..., 2], "Z": d[t],
                                              "motion.X": v[t, ..., 0], "motion.Y": v[t, ..., 1]})
    x = exr.load_sequence(src, None, f, spec)[f"x{f}"]
    # float32 storage; measured at most 1.9e-7 px and 5.0e-8 in device depth
    np.testing.assert_allclose(x["motion"], motion, rtol=0, atol=4e-7)
    np.testing.assert_allclose(x["depth"][..., 0], device, rtol=0, atol=1e-7)
    np.testing.assert_allclose(x["jitter"], jitter, rtol=0, atol=1e-7)  # float32: 3.8e-9 measured


@pytest.mark.parametrize("field,value,message", [
    ("target", np.nan, "target has 1 values NaN or infinite (first in frame 2)"),
    ("x4/color", np.inf, "color has 1 values NaN or infinite (first in frame 2)"),
    ("x4/jitter", 5.0, "jitter has 1 values outside [0, 1) or not finite (first in frame 2)"),
])
def test_stored_arrays_are_checked_where_they_are_read(tiny_data, tmp_path, capsys, field,
                                                       value, message):
    """A dataset damaged after it was written (one bad value) is refused by every reader:
    evaluation and the crops training draws, naming the video, field and frame."""
    import shutil

    import h5py

    from jtus import evaluate

    bad = tmp_path / "bad.h5"
    shutil.copy(tiny_data, bad)
    with h5py.File(bad, "a") as fh:
        name = sorted(fh["test"])[0]
        d = fh[f"test/{name}/{field}"]
        a = d[:]
        a[(2,) + (0,) * (a.ndim - 1)] = value
        d[...] = a
    assert evaluate.main(["--dataset", str(bad), "--models", "jau", "--factor", "4",
                          "--out", str(tmp_path / "e"), "--quiet", "--json"]) == 2
    err = capsys.readouterr().err
    assert f"test/{name}" in err and message in err, err
    assert not (tmp_path / "e").exists()  # a refused evaluation creates nothing
    with h5py.File(bad, "a") as fh:  # now the whole field, so that any crop of it is bad
        d = fh[f"test/{name}/{field}"]
        d[...] = np.full(d.shape, value, d.dtype)
    with dataset.Dataset(bad) as ds, pytest.raises(ValueError, match=field.split("/")[-1]):
        for seed in range(50):  # until a crop of that video is drawn
            ds.crops("test", 4, 2, 4, 16, np.random.default_rng(seed))


def test_writers_refuse_non_finite_videos(tmp_path):
    """No dataset is written with NaN in it: the writer checks every array first."""
    import h5py

    video = sim.render_video(sim.get_scene("objects"), "test", 0, 2, size=(16, 16),
                             factors=(4,), spp=1)
    video["x4"]["motion"][1, 0, 0, 0] = np.nan
    with h5py.File(tmp_path / "v.h5", "w") as fh, pytest.raises(
            ValueError, match=r"x4/motion has 1 NaN.*first in frame 1"):
        dataset.write_video(fh.create_group("test/v"), video, (4,), 1)
