"""``python -m jtus.data import-nss``: Arm's NSS dataset layout, written here by the test
(two sequences, HDR colour, UV motion, Arm's jitter, reversed Z, a camera cut) and by
the independent ``tests/nss_fixture.py``, read back through ``jtus.data.Dataset`` with
every convention converted as Arm's own reader converts it."""

import json
import os

import numpy as np
import pytest

from jtus import models
from jtus.data import __main__ as cli
from jtus.data import conventions, nss
from jtus.data.dataset import Dataset
from jtus.data.exr import write_exr
from tests import nss_fixture

H, W, F, T = 16, 24, 2, 4


def _write_nss(root, rng, names=("0000", "0001"), exposure=True):
    """An NSS capture: per sequence a JSON and, per frame, ground truth, colour, depth
    and motion EXRs. Returns what was written, in the source's own conventions."""
    h, w = H // F, W // F
    written = {}
    for name in names:
        frames, src = [], {"color": [], "depth": [], "motion": [], "target": [], "jit": []}
        for t in range(T):
            num = 10 + t  # frame numbers need not start at 0
            stem = f"{num:04d}.exr"
            color = rng.uniform(0, 8, (h, w, 3))        # linear HDR
            target = rng.uniform(0, 8, (H, W, 3))
            depth = rng.uniform(0.05, 0.95, (h, w))      # reversed Z
            uv = rng.uniform(-0.1, 0.1, (h, w, 2))       # UV-space backward motion
            jit = rng.uniform(-0.5, 0.5, 2)              # Arm's offsets, LR pixels
            for sub, chans in ((f"x{F}/color", {"R": color[..., 0], "G": color[..., 1],
                                                "B": color[..., 2]}),
                               (f"x{F}/depth", {"R": depth}),
                               (f"x{F}/motion", {"R": uv[..., 0], "G": uv[..., 1]}),
                               ("ground_truth", {"R": target[..., 0], "G": target[..., 1],
                                                 "B": target[..., 2]}),
                               ("motion_gt", {"R": np.zeros((H, W)), "G": np.zeros((H, W))})):
                os.makedirs(os.path.join(root, sub, name), exist_ok=True)
                write_exr(os.path.join(root, sub, name, stem), chans)
            fr = {"Frame": num, "FovX": 1.2, "FovY": 0.8, "CameraNearPlane": 0.1,
                  "CameraFarPlane": -1.0, "ViewProjection": [0.0] * 16,
                  "Jitter": {"X": 9.0, "Y": 9.0},  # raw pixels: unused when normalized exist
                  "NormalizedPerRatioJitter": [{"X": 0.0, "Y": 0.0},
                                               {"X": jit[0] / w, "Y": jit[1] / h}]}
            if exposure:
                fr["Exposure"] = 0.5 + 0.25 * t
            if t == 2:
                fr["CameraCut"] = True
            frames.append(fr)
            for k, v in (("color", color), ("depth", depth), ("motion", uv),
                         ("target", target), ("jit", jit)):
                src[k].append(v)
        meta = {"Version": "1.0", "EmulatedFramerate": 60,
                "TargetResolution": {"X": W, "Y": H},
                "Samples": {"Sequence": "TiledHalton", "Count": 16, "Quantized": True},
                "ReverseZ": True, "UpscalingRatiosIndices": {"x1_5_index": 0, "x2_index": 1},
                "Frames": frames}
        with open(os.path.join(root, f"{name}.json"), "w") as fh:
            json.dump(meta, fh)
        written[name] = {k: np.stack(v) for k, v in src.items()}
    return written


def test_import_nss_converts_every_convention(tmp_path):
    root = tmp_path / "nss"
    src = _write_nss(str(root), np.random.default_rng(0))
    out = tmp_path / "nss.h5"
    assert cli.main(["import-nss", "--root", str(root), "--factor", str(F), "--out", str(out),
                     "--quiet", "--linear-truth"]) == 0
    with Dataset(out) as ds:
        assert ds.videos("test") == ["0000", "0001"] and ds.factors == (F,) and ds.hdr
        for name, s in src.items():
            g = ds.group("test", name)
            x = g[f"x{F}"]
            assert g.attrs["far"] == nss.INFINITE_FAR and g.attrs["near"] == pytest.approx(0.1)
            # colour and target: linear HDR kept (float16 storage: 2^-11 relative)
            np.testing.assert_allclose(x["color"][:], s["color"], rtol=2 ** -11)
            np.testing.assert_allclose(g["target"][:], s["target"], rtol=2 ** -11)
            # UV backward motion, y down: times the LR size
            np.testing.assert_allclose(x["motion"][:], s["motion"] * [W // F, H // F],
                                       rtol=1e-6, atol=1e-6)
            # reversed Z -> device depth 1 - d
            np.testing.assert_allclose(x["depth"][:], 1.0 - s["depth"][..., None], atol=1e-6)
            # Arm's jitter: the sample lies at p + 0.5 + jitter
            np.testing.assert_allclose(x["jitter"][:], 0.5 + s["jit"], atol=1e-6)
            np.testing.assert_array_equal(g["reset"][:], [True, False, True, False])
            np.testing.assert_allclose(g["exposure"][:], [0.5, 0.75, 1.0, 1.25])
        frames, targets = ds.video("test", "0001", F)
        assert frames.exposure.shape == (T, 1) and targets.shape == (T, 1, H, W, 3)


def test_jitter_kinds_fsr2_and_arm_are_mirrored():
    """FSR 2's ComputeHrPosFromLrPos puts the sample of LR pixel p at ``p + 0.5 -
    jitter``; Arm's generate_lr_to_hr_lut at ``p + 0.5 + jitter``."""
    j = np.array([[0.25, -0.125]])
    np.testing.assert_allclose(conventions.jitter_to_jtus(j, "fsr2"), [[0.25, 0.625]])
    np.testing.assert_allclose(conventions.jitter_to_jtus(j, "arm"), [[0.75, 0.375]])


def _import_fixture(tmp_path, factor, edit=None):
    root = str(tmp_path / "nss")
    used = nss_fixture.write_dataset(root)
    if edit:
        _edit_json(root, "0000", edit)
    out = tmp_path / f"fixture-x{factor}.h5"
    assert cli.main(["import-nss", "--root", root, "--factor", str(factor), "--out",
                     str(out), "--quiet", "--force"]) == 0
    with Dataset(out) as ds:
        frames, targets = ds.video("test", "0000", factor)
    return used[factor], frames, np.asarray(targets)


def _jau_error(jitter, frames, factor):
    model = models.build("jau", factor)
    worst = 0.0
    for t in range(len(jitter)):
        fr = jax_frame(frames, t)
        out, _ = model.step({}, (), fr)
        worst = max(worst, float(np.abs(np.asarray(out[0]) -
                                        nss_fixture.jau_reference(factor, jitter[t])).max()))
    return worst


def jax_frame(frames, t):
    return type(frames)(*(None if x is None else x[t] for x in frames))


@pytest.mark.parametrize("factor", nss_fixture.FACTORS)
def test_import_nss_reproduces_arms_jitter_aligned_frame(tmp_path, factor):
    """The independent fixture's samples lie at ``p + 0.5 + J`` (Arm's convention);
    jtus's JAU on the imported frames reproduces the JAU the fixture computes from that
    convention, to the float16 storage of the colour (values up to 2.2: 2^-11 relative,
    1.1e-3). The control: the same data with the jitter read mirrored (FSR 2's sign)
    misses by far more."""
    jitter, frames, targets = _import_fixture(tmp_path, factor)
    assert _jau_error(jitter, frames, factor) < 1.5e-3
    # files are numbered from 1 and paired with Frames by position; the truth is the
    # fixture's radiance, brought back from its Karis tone map
    v, u = np.meshgrid((np.arange(nss_fixture.H) + 0.5) / nss_fixture.H,
                       (np.arange(nss_fixture.W) + 0.5) / nss_fixture.W, indexing="ij")
    np.testing.assert_allclose(targets[:, 0], np.broadcast_to(
        nss_fixture.radiance(u, v), targets[:, 0].shape), rtol=3e-3)
    mirrored = conventions.jitter_to_jtus(-jitter, "arm")  # what an FSR 2 reading stores
    wrong = frames._replace(jitter=np.asarray(mirrored, np.float32)[:, None])
    assert _jau_error(jitter, wrong, factor) > 0.05


def test_import_nss_follows_arms_reader_on_planes_order_and_truth(tmp_path, capsys):
    """An infinite far plane becomes 5000 (Arm's reader); ``motion_gt`` is required;
    a linear truth given as tone-mapped is refused with the option named."""
    root = str(tmp_path / "nss")
    nss_fixture.write_dataset(root)
    out = tmp_path / "a.h5"
    assert cli.main(["import-nss", "--root", root, "--factor", "2", "--out", str(out),
                     "--quiet"]) == 0
    with Dataset(out) as ds:
        assert ds.group("test", "0000").attrs["far"] == nss.INFINITE_FAR == 5000.0
    for f in os.listdir(os.path.join(root, "motion_gt", "0000")):
        os.remove(os.path.join(root, "motion_gt", "0000", f))
    assert cli.main(["import-nss", "--root", root, "--factor", "2", "--out",
                     str(tmp_path / "b.h5"), "--quiet"]) == 2
    assert "motion_gt" in capsys.readouterr().err and not (tmp_path / "b.h5").exists()


def test_import_nss_warns_once_per_key_outside_arms_specification(tmp_path):
    """A sequence key and a frame key that neither Arm's specification nor its reader
    defines each give one ``UnknownKeyWarning`` naming the JSON file and the key; the
    import is the one without them. The specification's optional keys warn nothing."""
    from jtus.files import UnknownKeyWarning

    def edit(m):
        m.update(Notes="x", MotionVectorsDilated=False)
        for fr in m["Frames"]:
            fr["Tag"] = 1
    with pytest.warns(UnknownKeyWarning) as got:
        _, frames, targets = _import_fixture(tmp_path, 2, edit)
    msgs = sorted({str(w.message) for w in got})
    assert len(msgs) == 2, msgs
    assert "0000.json.Frames[0]: unknown key 'Tag' ignored" in msgs[0]
    assert "0000.json: unknown key 'Notes' ignored" in msgs[1]
    _, plain_frames, plain_targets = _import_fixture(tmp_path / "plain", 2)
    np.testing.assert_array_equal(targets, plain_targets)
    np.testing.assert_array_equal(frames.color, plain_frames.color)


@pytest.mark.parametrize("break_it,message", [
    (lambda root: os.remove(os.path.join(root, f"x{F}", "depth", "0001", "0012.exr")),
     r"x2/depth/0001 holds 3 \.exr files, .* 4"),
    (lambda root: _edit_json(root, "0000", lambda m: m.update(ReverseZ="yes")),
     "ReverseZ: expected true or false"),
    (lambda root: _edit_json(root, "0000", lambda m: m["Frames"][1].update(CameraCut="no")),
     "CameraCut: expected true or false"),
    (lambda root: _edit_json(root, "0000", lambda m: m["TargetResolution"].update(X=None)),
     "TargetResolution.X: expected a finite number, got None"),
    (lambda root: _edit_json(root, "0000", lambda m: m["Frames"][1].update(
        CameraNearPlane=None)), r"Frames\[1\].CameraNearPlane: expected a finite number"),
    (lambda root: _edit_json(root, "0000", lambda m: m.update(
        UpscalingRatiosIndices=[1])), "UpscalingRatiosIndices: expected dict"),
    (lambda root: _edit_json(root, "0000", lambda m: m["Frames"][0][
        "NormalizedPerRatioJitter"][1].pop("X")), r"NormalizedPerRatioJitter\[1\]: missing 'X'"),
    (lambda root: _edit_json(root, "0000", lambda m: m["Frames"][2].update(Exposure="x")),
     r"Frames\[2\].Exposure: expected a finite number, got 'x'"),
    (lambda root: _edit_json(root, "0000", lambda m: m["Frames"][1].pop("Exposure")),
     "Exposure on 3 of 4 frames"),
    (lambda root: _edit_json(root, "0000", lambda m: m["Frames"][0].update(
        CameraNearPlane=5.0, CameraFarPlane=1.0)), "CameraNearPlane < CameraFarPlane"),
    (lambda root: _edit_json(root, "0001", lambda m: m["Frames"][3].update(
        NormalizedPerRatioJitter=[{"X": 0, "Y": 0}, {"X": 0.2, "Y": 0.0}])),
     "jitter outside the pixel"),
    (lambda root: _edit_json(root, "0000", lambda m: m.update(
        TargetResolution={"X": 25, "Y": 16})), "not a multiple of factor"),
])
def test_import_nss_refuses_bad_input_before_writing(tmp_path, capsys, break_it, message):
    root = str(tmp_path / "nss")
    _write_nss(root, np.random.default_rng(1))
    break_it(root)
    out = tmp_path / "bad.h5"
    assert cli.main(["import-nss", "--root", root, "--factor", str(F), "--out", str(out),
                     "--quiet", "--linear-truth"]) == 2
    import re
    assert re.search(message, capsys.readouterr().err)
    assert not out.exists() and not list(tmp_path.glob("*.h5*"))


def test_import_nss_without_a_ratio_folder_names_the_ratios(tmp_path, capsys):
    root = str(tmp_path / "nss")
    _write_nss(root, np.random.default_rng(2), names=("0000",), exposure=False)
    assert cli.main(["import-nss", "--root", root, "--factor", "4", "--out",
                     str(tmp_path / "o.h5"), "--quiet"]) == 2
    assert "no x4/ folder" in capsys.readouterr().err


def _edit_json(root, name, fn):
    path = os.path.join(root, f"{name}.json")
    with open(path) as fh:
        meta = json.load(fh)
    fn(meta)
    with open(path, "w") as fh:
        json.dump(meta, fh)
