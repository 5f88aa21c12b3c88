"""tests.compile_profile: the plugin that splits each test's time into JAX's compile
stages (docs/testing.md)."""

import json
import os
import subprocess
import sys

from tests import compile_profile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_compile_profile_counts_an_eager_operation_in_its_test(tmp_path):
    (tmp_path / "test_probe.py").write_text(
        "import jax.numpy as jnp, numpy as np\n"
        "def test_eager():\n"
        "    jnp.sin(np.ones((3, 5), np.float32)).block_until_ready()\n"
        "def test_nothing():\n"
        "    pass\n")
    out = tmp_path / "prof.json"
    env = {k: v for k, v in os.environ.items() if k != compile_profile.ENV}
    env["PYTHONPATH"] = ROOT + os.pathsep + env.get("PYTHONPATH", "")
    (tmp_path / "tmp").mkdir()
    env["TMPDIR"] = str(tmp_path / "tmp")  # where the plugin makes its rows' folder
    res = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "0",
         "-p", "tests.compile_profile", "--compile-profile-out", str(out),
         "--rootdir", str(tmp_path), "-c", os.devnull, str(tmp_path / "test_probe.py")],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stdout + res.stderr
    rows = {r["test"].split("::")[-1]: r for r in json.loads(out.read_text())}
    assert set(rows) == {"test_eager", "test_nothing"}
    eager, nothing = rows["test_eager"], rows["test_nothing"]
    # one operation compiled on its own: small, lowered and timed within the call
    assert eager["small_compiles"] == 1 and eager.get("large_compiles", 0) == 0
    assert 0 < eager["small_compile_s"] < compile_profile.SMALL_S
    assert 0 < eager["lower_s"] and eager["small_compile_s"] < eager["call_s"]
    assert "small_compiles" not in nothing
    assert "compile profile (tests.compile_profile)" in res.stdout
    assert "2 tests" in res.stdout and "(1)" in res.stdout
    assert not list((tmp_path / "tmp").glob("jtus-compile-profile-*"))  # merged, removed


def test_summarize_sums_per_file_and_orders_by_compile_time():
    rows = [{"test": "a.py::x", "call_s": 2.0, "small_compile_s": 0.5, "small_compiles": 5},
            {"test": "b.py::y", "call_s": 3.0, "large_compile_s": 2.0, "large_compiles": 1},
            {"test": "a.py::z", "call_s": 1.0, "small_compile_s": 0.25, "small_compiles": 2}]
    total, files = compile_profile.summarize(rows)
    assert total["call_s"] == 6.0 and total["small_compiles"] == 7
    assert [name for name, _ in files] == ["b.py", "a.py"]
    a = dict(files)["a.py"]
    assert a["tests"] == 2 and a["small_compile_s"] == 0.75 and a["call_s"] == 3.0
