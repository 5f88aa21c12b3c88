"""Property-based bad input: random wrong frames, import sidecars, run
configs, dataset files and command lines. Every case ends in a correct result or a
clean error naming the field, with a non-zero exit for the CLIs; never a traceback
(any other exception fails the test), never a changed file on failure.

Examples per property are listed in ``docs/reliability.md``; ``JTUS_HYPOTHESIS_SCALE=10``
multiplies them for a long run.
"""

import hashlib
import json
import os
import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jtus import checkpoint
from jtus import config as run_config
from jtus.data import __main__ as data_cli
from jtus.data import exr
from jtus.data.dataset import Dataset
from jtus.frame import Frame, validate

SCALE = int(os.environ.get("JTUS_HYPOTHESIS_SCALE", "1"))
FIELDS = ("color", "depth", "motion", "jitter", "reset", "exposure")


def _examples(n):
    return settings(max_examples=n * SCALE, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture,
                                           HealthCheck.too_slow])


# ---------------------------------------------------------------- frames

_DTYPES = st.sampled_from([np.float32, np.float64, np.int32, np.bool_])
_SPECIAL = st.sampled_from([None, "nan", "inf", "neg", "big"])


@st.composite
def frames(draw):
    """A frame whose every field may be off in shape, dtype or values."""
    b, h, w = draw(st.integers(1, 2)), draw(st.integers(1, 3)), draw(st.integers(1, 3))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    what = {}

    def field(name, shape):
        if draw(st.integers(0, 5)) == 0:  # a wrong shape
            shape = tuple(max(1, s + draw(st.integers(-1, 1))) for s in shape) + (
                (1,) if draw(st.booleans()) else ())
        dtype = draw(_DTYPES) if draw(st.integers(0, 5)) == 0 else np.float32
        x = rng.uniform(0.0, 0.99, shape)
        special = draw(_SPECIAL) if draw(st.integers(0, 3)) == 0 else None
        if special and x.size:
            i = tuple(int(rng.integers(s)) for s in shape)
            x[i] = {"nan": np.nan, "inf": np.inf, "neg": -0.5, "big": 7.0}[special]
        what[name] = (shape, dtype, special)
        return x.astype(dtype)

    fr = Frame(field("color", (b, h, w, 3)), field("depth", (b, h, w, 1)),
               field("motion", (b, h, w, 2)), field("jitter", (b, 2)),
               np.zeros(b, bool) if draw(st.booleans()) else None,
               field("exposure", (b,)) if draw(st.booleans()) else None)
    return fr, what


def _valid(fr, what):
    """The oracle: what validate must accept."""
    b, h, w = fr.color.shape[:3] if fr.color.ndim == 4 else (None, None, None)
    want = {"color": (b, h, w, 3), "depth": (b, h, w, 1), "motion": (b, h, w, 2),
            "jitter": (b, 2), "exposure": (b,)}
    for name, (shape, dtype, special) in what.items():
        if fr.color.ndim != 4 or shape != want[name] or not np.issubdtype(dtype, np.floating):
            return False
        if special in ("nan", "inf"):
            return False
        if name in ("jitter", "depth") and special in ("neg", "big"):
            return False
        if name == "color" and special == "neg":
            return False
        if name == "exposure" and special == "neg":
            return False
    return True


@_examples(150)
@given(frames())
def test_validate_accepts_exactly_the_valid_frames(case):
    fr, what = case
    try:
        validate(fr)
        ok = True
    except ValueError as e:
        ok = False
        assert re.match(r"(color|depth|motion|jitter|reset|exposure): ", str(e)), str(e)
    assert ok == _valid(fr, what), (what, ok)


# ---------------------------------------------------------------- sidecars and configs

_JSON = st.recursive(st.none() | st.booleans() | st.integers(-5, 5) | st.floats(
    allow_nan=False, allow_infinity=False, width=32) | st.text(max_size=6),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner,
                                                                max_size=2), max_leaves=4)


def _field_dicts(cls):
    import dataclasses
    names = [f.name for f in dataclasses.fields(cls)]
    return st.dictionaries(st.sampled_from(names + ["bogus", "Color"]), _JSON, max_size=4)


@_examples(150)
@given(data=_field_dicts(exr.ImportSpec))
def test_import_sidecar_is_a_spec_or_a_named_error(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("s") / "spec.json"
    path.write_text(json.dumps(data))
    try:
        exr.ImportSpec.from_json(str(path))
    except ValueError as e:
        assert str(path) in str(e) or re.match(r"\w+", str(e)), str(e)
        named = [k for k in list(data) + ["keys"] if k in str(e)]
        assert named, (data, str(e))


@_examples(100)
@given(data=_field_dicts(run_config.Config))
def test_run_config_file_is_a_config_or_a_named_error(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("c") / "config.json"
    path.write_text(json.dumps(data))
    try:
        run_config.from_json(str(path))
    except ValueError as e:
        assert str(path) in str(e), str(e)


# ---------------------------------------------------------------- dataset files


@_examples(40)
@given(content=st.one_of(st.binary(max_size=64), st.just(b"\x89HDF\r\n\x1a\n" + b"\0" * 32)),
       attrs=st.dictionaries(st.sampled_from(["format", "version", "factors", "size"]),
                             st.one_of(st.integers(-2, 3), st.text(st.characters(
                                 min_codepoint=32, max_codepoint=126), max_size=5)),
                             max_size=4))
def test_dataset_reader_refuses_what_is_not_a_dataset(tmp_path_factory, content, attrs):
    import h5py
    d = tmp_path_factory.mktemp("d")
    raw, h5 = d / "raw.h5", d / "attrs.h5"
    raw.write_bytes(content)
    with h5py.File(h5, "w") as fh:
        fh.attrs.update(attrs)
    for path in (raw, h5):
        with pytest.raises(ValueError, match=re.escape(str(path))):
            Dataset(path).close()


# ---------------------------------------------------------------- command lines


def _digest(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


@pytest.fixture(scope="module")
def exr_inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("exr")
    lr, hr = d / "lr", d / "hr"
    lr.mkdir()
    hr.mkdir()
    rng = np.random.default_rng(0)
    for t in range(2):
        exr.write_exr(lr / f"f{t}.exr", {"R": rng.random((4, 4)), "G": rng.random((4, 4)),
                                         "B": rng.random((4, 4)), "Z": rng.random((4, 4)),
                                         "motion.X": np.zeros((4, 4)),
                                         "motion.Y": np.zeros((4, 4))})
        exr.write_exr(hr / f"f{t}.exr", {c: rng.random((16, 16)) for c in "RGB"})
    out = d / "existing.h5"
    assert data_cli.main(["import-exr", "--input", str(lr), "--target", str(hr), "--factor",
                          "4", "--out", str(out)]) == 0
    return {"lr": str(lr), "hr": str(hr), "out": str(out), "missing": str(d / "nope"),
            "file": str(out), "dir": str(d)}


_WORDS = ["lr", "hr", "missing", "file", "dir"]


@_examples(80)
@given(inp=st.sampled_from(_WORDS), tgt=st.sampled_from(_WORDS),
       factor=st.sampled_from(["4", "2", "3", "0", "-4", "x", "4.0"]),
       split=st.sampled_from(["test", "train", "bogus", ""]),
       name=st.sampled_from(["v", "a/b", "", "..", "ok_1"]),
       extra=st.lists(st.sampled_from(["--depth-kind", "reversed", "--near", "-1", "--far",
                                       "nan", "--motion", "a", "--color", "R,G",
                                       "--motion-units", "furlongs"]), max_size=3))
def test_import_exr_cli_succeeds_or_fails_cleanly_without_touching_the_file(
        exr_inputs, capsys, inp, tgt, factor, split, name, extra):
    out = exr_inputs["out"]
    before = _digest(out)
    argv = ["import-exr", "--input", exr_inputs[inp], "--target", exr_inputs[tgt],
            "--factor", factor, "--out", out, "--split", split, "--name", name] + extra
    try:
        rc = data_cli.main(argv)
    except SystemExit as e:  # argparse: usage line and exit status 2
        rc = e.code
    err = capsys.readouterr().err
    assert rc in (0, 2), (argv, rc)
    if rc:
        assert err.strip(), argv
        assert "Traceback" not in err
    # without --force an existing --out is never replaced, valid arguments or not
    assert _digest(out) == before
    assert rc == 2 and ("exists" in err or "error" in err or "usage" in err)


# ---------------------------------------------------------------- scene JSON and NSS metadata

_BAD = st.one_of(st.none(), st.booleans(), st.text(max_size=3), st.just(float("nan")),
                 st.just(float("inf")), st.just(-1.0), st.just(0), st.just([]),
                 st.lists(st.floats(-2, 2), min_size=1, max_size=4), st.just({}))


def _paths(tree, prefix=()):
    """Every leaf and list of a JSON tree, as key paths."""
    if isinstance(tree, dict):
        for k, v in tree.items():
            yield prefix + (k,)
            yield from _paths(v, prefix + (k,))
    elif isinstance(tree, list) and tree and isinstance(tree[0], (dict, list)):
        for i, v in enumerate(tree):
            yield from _paths(v, prefix + (i,))


def _set(tree, path, value):
    for k in path[:-1]:
        tree = tree[k]
    tree[path[-1]] = value


@pytest.fixture(scope="module")
def scene_tree():
    from jtus import sim
    return json.loads(sim.to_json(sim.random_scene(7, effects=sim.EFFECTS)))


@_examples(150)
@given(pick=st.integers(0, 10**6), value=_BAD)
def test_scene_json_loads_or_names_the_field(tmp_path_factory, scene_tree, pick, value):
    """Any field of a user's scene set to a wrong type, null, NaN, Inf, a wrong length
    or an out-of-range value: ``sim show --scene FILE`` prints the scene or ends in one
    ``error:`` naming the file and the field, exit 2; never a traceback."""
    import contextlib
    import copy
    import io

    from jtus.sim import __main__ as sim_cli

    paths = list(_paths(scene_tree))
    path = paths[pick % len(paths)]
    tree = copy.deepcopy(scene_tree)
    _set(tree, path, value)
    f = tmp_path_factory.mktemp("scene") / "s.json"
    f.write_text(json.dumps(tree))
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        rc = sim_cli.main(["show", "--scene", str(f)])
    if rc == 0:  # accepted: every value has its field's kind, numbers are finite
        _same_kinds(scene_tree, json.loads(out.getvalue()), path)
        return
    assert rc == 2
    msg = err.getvalue().strip()
    assert msg.startswith("error: ") and "\n" not in msg and str(f) in msg, msg
    key = next(k for k in reversed(path) if isinstance(k, str))
    assert key in msg or "objects" in msg or "lights" in msg or "effects" in msg, (path, msg)


def _kind(v):
    if isinstance(v, bool) or v is None or isinstance(v, str):
        return type(v).__name__
    if isinstance(v, (int, float)):
        assert np.isfinite(v), v
        return "number"
    return type(v).__name__


EMPTY_OK = ("color2", "extra_lights", "effects")  # fields whose default is empty


def _same_kinds(want, got, where, key=None):
    if isinstance(want, dict):
        for k in want:
            _same_kinds(want[k], got[k], where, k)
    elif isinstance(want, list) and want:
        if got == [] and key in EMPTY_OK:
            return
        # numeric vectors keep their length; lists of objects or names may not
        fixed = not isinstance(want[0], (dict, str))
        assert isinstance(got, list) and (len(got) == len(want) or not fixed), (where, got)
        for w, g in zip(want, got):
            _same_kinds(w, g, where, key)
    else:
        assert _kind(want) == _kind(got) or (isinstance(want, list) and got == []), (where, got)


@pytest.fixture(scope="module")
def nss_root(tmp_path_factory):
    from tests import nss_fixture
    root = tmp_path_factory.mktemp("nss")
    nss_fixture.write_dataset(str(root))
    return root


@_examples(60)
@given(pick=st.integers(0, 10**6), value=_BAD)
def test_nss_metadata_imports_or_names_the_field(tmp_path_factory, nss_root, pick, value):
    """Any field of an NSS sequence's JSON set to a wrong value: ``import-nss`` imports
    or ends in one ``error:`` naming the file, exit 2, with nothing written; never a
    traceback."""
    import contextlib
    import copy
    import io
    import shutil

    root = tmp_path_factory.mktemp("nss-case")
    shutil.copytree(nss_root, root, dirs_exist_ok=True)
    meta = json.loads((root / "0000.json").read_text())
    paths = [p for p in _paths(meta) if p[-1] not in ("ViewProjection", "Samples",
                                                        "EmulatedFramerate", "Version")]
    tree = copy.deepcopy(meta)
    _set(tree, paths[pick % len(paths)], value)
    (root / "0000.json").write_text(json.dumps(tree))
    out = root / "out.h5"
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = data_cli.main(["import-nss", "--root", str(root), "--factor", "2", "--out",
                            str(out), "--quiet"])
    if rc == 0:
        assert out.exists()
        return
    assert rc == 2 and not out.exists()
    msg = err.getvalue().strip()
    assert msg.startswith("error: ") and "\n" not in msg and "0000.json" in msg, msg


# ---------------------------------------------------------------- run history

_RECORD = {"epoch": 1, "step": 400, "train_loss": 0.0105, "grad_norm": 0.011,
           "grad_norm_max": 0.047, "param_norm": 24.2, "val_loss": 0.0041, "val_psnr": 39.7,
           "val_ssim": 0.976, "seconds": 246.2}


@_examples(100)
@given(key=st.sampled_from(sorted(_RECORD)), value=_BAD, which=st.integers(0, 1))
def test_run_history_is_records_or_a_named_error(tmp_path_factory, key, value, which):
    """One field of one record of a run's ``metrics.json`` set to a wrong type, null,
    NaN, Inf, a negative or a list: ``--resume`` reads it as it was written or refuses
    it naming the file, the epoch and the field."""
    history = [dict(_RECORD), {**_RECORD, "epoch": 2, "step": 800}]
    history[which][key] = value
    path = tmp_path_factory.mktemp("m") / "metrics.json"
    path.write_text(json.dumps(history))
    try:
        got = checkpoint.read_history(str(path), 2)
    except ValueError as e:
        assert str(path) in str(e) and (f"{key}:" in str(e) or key == "epoch"), str(e)
        return
    assert got == history
    assert all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)
               for r in got for v in r.values())
    assert all(isinstance(r["step"], int) and r["step"] >= 0 for r in got)
