"""Bad paths and names on the command line (issue 15, defects 10 and 13): each CLI
refuses them with one line naming the flag, exit code 2, before any work, and
writes nothing."""

import os

import pytest

from jtus import cost, evaluate, upsample
from jtus.data import __main__ as data_cli
from jtus.data import dataset


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "tiny.h5"
    dataset.generate("tiny", path, progress=False)
    return str(path)


def _refused(capsys, main, argv, *words):
    capsys.readouterr()
    assert main(argv) == 2, argv
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "\n" not in err, err
    for w in words:
        assert w in err, (w, err)


def test_output_paths_that_cannot_take_the_output(tiny_data, tmp_path, capsys):
    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    before = sorted(os.listdir(tmp_path))
    _refused(capsys, data_cli.main, ["generate", "--preset", "tiny", "--out", str(tmp_path)],
             "--out", "is a folder")
    _refused(capsys, data_cli.main, ["generate", "--preset", "tiny", "--out",
                                     str(a_file / "x.h5")], "--out", "is a file")
    _refused(capsys, upsample.main, ["--input", tiny_data, "--factor", "4", "--model", "jau",
                                     "--out", str(a_file)], "--out", "expected a folder")
    _refused(capsys, evaluate.main, ["--dataset", tiny_data, "--models", "jau", "--out",
                                     str(a_file), "--quiet"], "is a file")
    _refused(capsys, data_cli.main, ["export", "--dataset", tiny_data, "--split", "test",
                                     "--video", "objects_00", "--what", "target", "--out",
                                     str(a_file)], "--out", "expected a folder")
    assert sorted(os.listdir(tmp_path)) == before and a_file.read_text() == "x"


def test_names_that_do_not_exist(tiny_data, tmp_path, capsys):
    out = str(tmp_path / "o")
    _refused(capsys, upsample.main, ["--input", tiny_data, "--factor", "4", "--model", "jau",
                                     "--video", "nope", "--out", out], "video", "'nope'",
             "objects_00")
    _refused(capsys, upsample.main, ["--input", tiny_data, "--factor", "4", "--model", "jau",
                                     "--split", "nope", "--out", out], "--split", "'nope'")
    _refused(capsys, data_cli.main, ["export", "--dataset", tiny_data, "--split", "nope",
                                     "--video", "x", "--what", "target", "--out", out],
             "split", "'nope'")
    for what in ("colour", "color@3", "color@x"):
        _refused(capsys, data_cli.main, ["export", "--dataset", tiny_data, "--split", "test",
                                         "--video", "objects_00", "--what", what, "--out", out],
                 "--what")
    _refused(capsys, evaluate.main, ["--dataset", tiny_data, "--models", "jau", "--max-videos",
                                     "-1", "--out", out, "--quiet"], "max_videos")
    assert not os.path.exists(out)


@pytest.mark.parametrize("argv,flag", [(["--factors", "0"], "--factors"),
                                       (["--factors", "3"], "--factors"),
                                       (["--height", "0"], "--height"),
                                       (["--width", "1918"], "--width")])
def test_cost_refuses_bad_sizes_and_factors(capsys, argv, flag):
    _refused(capsys, cost.main, argv, flag)


def test_upsample_and_export_refuse_a_folder_with_old_frames(tiny_data, tmp_path, capsys):
    """Defect 13: new frames written beside stale ones would read as one sequence."""
    out = tmp_path / "frames"
    base = ["--input", tiny_data, "--factor", "4", "--model", "jau", "--out", str(out)]
    assert upsample.main(base) == 0
    n = len(os.listdir(out))
    (out / "frame9999.png").write_bytes(b"stale")
    _refused(capsys, upsample.main, base, "--out", "earlier sequence", "--force")
    assert (out / "frame9999.png").read_bytes() == b"stale"
    assert upsample.main(base + ["--force"]) == 0
    assert len(os.listdir(out)) == n  # the stale frame is gone
    ex = ["export", "--dataset", tiny_data, "--split", "test", "--video", "objects_00",
          "--out", str(out)]
    _refused(capsys, data_cli.main, ex, "--out", "earlier sequence")
    assert data_cli.main(ex + ["--force"]) == 0
