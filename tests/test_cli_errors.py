"""What the CLIs do with bad paths and names: each refuses them with one line naming
the flag, exit code 2, before any work, and writes nothing. And what they write when the
input is good: the values checked against quantities computed independently."""

import os

import numpy as np
import pytest

from jtus import cost, evaluate, upsample
from jtus.data import __main__ as data_cli
from jtus.data import dataset
from tests import seqdata


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


def test_values_written_by_evaluate_and_upsample(tiny_data, tmp_path):
    """What the CLIs write, against quantities computed here: JAU from its definition
    in numpy, PSNR and SSIM from scikit-image, the frames read back from the EXRs."""
    import json

    from skimage.metrics import peak_signal_noise_ratio, structural_similarity

    from jtus.data import exr

    psnr, ssim = [], []
    with dataset.Dataset(tiny_data) as ds:
        names = ds.videos("test")
        for name in names:
            frames, targets = ds.video("test", name, 4)
            ref = seqdata.jau_reference(frames.color[:, 0], frames.jitter[:, 0], 4)
            for o, t in zip(ref, targets[:, 0].astype(np.float64)):
                psnr.append(peak_signal_noise_ratio(t, o, data_range=1.0))
                ssim.append(structural_similarity(t, o, data_range=1.0, channel_axis=-1,
                                                  gaussian_weights=True, sigma=1.5,
                                                  use_sample_covariance=False))
        f0, _ = ds.video("test", names[0], 4)
        first = seqdata.jau_reference(f0.color[:, 0], f0.jitter[:, 0], 4)
    out = tmp_path / "ev"
    assert evaluate.main(["--dataset", tiny_data, "--factor", "4", "--models", "jau", "--out",
                          str(out), "--quiet", "--no-crops"]) == 0
    got = json.loads((out / "results.json").read_text())["4"]["jau"]
    # jtus computes in float32: measured 1.9e-6 dB and 3.7e-6 SSIM from float64 skimage
    assert abs(got["psnr"] - np.mean(psnr)) < 1e-5, (got["psnr"], np.mean(psnr))
    assert abs(got["ssim"] - np.mean(ssim)) < 1e-5, (got["ssim"], np.mean(ssim))
    frames_dir = tmp_path / "up"
    assert upsample.main(["--input", tiny_data, "--video", names[0], "--factor", "4", "--model",
                          "jau", "--format", "exr", "--out", str(frames_dir)]) == 0
    files = exr.sequence_files(frames_dir)
    assert len(files) == len(first)
    for f, want in zip(files, first):
        ch, _ = exr.read_exr(frames_dir / f)
        img = np.stack([ch[c] for c in "RGB"], -1)
        np.testing.assert_allclose(img, want, rtol=0, atol=1e-6)  # measured: 0 (dyadic jitter)


def test_train_refuses_loss_frames_that_tbptt_would_ignore(tiny_data, tmp_path, capsys):
    """tbptt takes the loss on each window's last k1 frames: an explicit --loss-frames
    that differs is refused (it was silently ignored), one that agrees is accepted."""
    from jtus import train

    work = tmp_path / "run"
    base = ["--preset", "tiny", "--dataset", tiny_data, "--workdir", str(work), "--quiet",
            "--no-eval", "--mode", "tbptt", "--seq-len", "4", "--k1", "2", "--k2", "2"]
    _refused(capsys, train.main, base + ["--loss-frames", "1"], "loss_frames", "k1=2")
    assert not work.exists()
    assert train.config_from_argv(base + ["--loss-frames", "2"]).loss_frames == 2


def test_host_devices_must_be_positive(tiny_data, tmp_path, capsys):
    """``--host-devices`` below 1 is refused, naming the flag, before a workdir is made
    or a step timed."""
    from jtus import train
    from jtus.bench import __main__ as bench_cli

    work = tmp_path / "run"
    _refused(capsys, train.main, ["--preset", "tiny", "--dataset", tiny_data, "--workdir",
                                  str(work), "--quiet", "--host-devices", "0"],
             "--host-devices", "positive")
    assert not work.exists()
    with pytest.raises(SystemExit) as e:
        bench_cli.main(["--what", "train", "--host-devices", "-1"])
    assert e.value.code == 2
    assert "--host-devices" in capsys.readouterr().err


def test_bench_refuses_its_out_path_before_timing(tmp_path, capsys):
    """``--out`` is checked before the minute of timing, not after it (a missing parent
    folder is created: the report is written atomically)."""
    from jtus.bench import __main__ as bench_cli

    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    for out, words in ((tmp_path, "is a folder"), (a_file / "r.json", "is a file")):
        with pytest.raises(SystemExit) as e:
            bench_cli.main(["--what", "peak", "--no-torch", "--out", str(out)])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert "--out" in err and words in err, err
    assert sorted(os.listdir(tmp_path)) == ["file.txt"]


def test_model_override_merges_with_the_preset_overrides(capsys):
    """``--model-override`` adds to a preset's own model overrides: ``--preset hdr``
    keeps ``hdr=True`` beside ``warp=bilinear``; a later value wins for the same key;
    an unknown field or a malformed pair is refused, naming it."""
    from jtus import recipe, train

    cfg = train.config_from_argv(["--preset", "hdr", "--model-override", "warp=bilinear"])
    assert dict(cfg.model_overrides) == {"hdr": True, "warp": "bilinear"}
    model_cfg = recipe.model_config(cfg)
    assert model_cfg.hdr is True and model_cfg.warp == "bilinear"
    cfg = train.config_from_argv(["--preset", "hdr", "--model-override", "hdr=false",
                                  "--model-override", "warp_a=-0.5"])
    assert dict(cfg.model_overrides) == {"hdr": False, "warp_a": -0.5}
    assert train.config_from_argv(["--preset", "tiny"]).model_overrides == ()
    with pytest.raises(ValueError, match="no such field"):
        train.config_from_argv(["--preset", "tiny", "--model-override", "wrap=bilinear"])
    with pytest.raises(ValueError, match="KEY=VALUE"):
        train.config_from_argv(["--preset", "tiny", "--model-override", "bilinear"])


def test_remat_and_hoist_reach_the_config():
    """Every rematerialization variant and the hoisted preparation are reachable from
    the command line and land in the run's config."""
    from jtus import config, train

    for name, value in config.REMAT_CHOICES.items():
        assert train.config_from_argv(["--preset", "tiny", "--remat", name]).remat == value
    assert train.config_from_argv(["--preset", "tiny", "--hoist"]).hoist is True
    with pytest.raises(ValueError, match="remat"):
        config.Config(remat="sometimes")


def test_sizes_past_what_the_code_or_machine_can_hold(tmp_path, capsys, monkeypatch):
    """Sizes beyond the documented bounds, and work past the free memory or disk, are
    refused before anything is allocated or written; ``--force`` is the way past the
    budget."""
    from jtus import export, files
    from jtus.sim import __main__ as sim_cli

    out = tmp_path / "x.h5"
    _refused(capsys, sim_cli.main, ["render", "--random", "3", "--size", "1000000",
                                    "--out", str(out)], "--size", "16384")
    _refused(capsys, sim_cli.main, ["render", "--random", "3", "--size", "8192", "--frames",
                                    "1000", "--videos", "100", "--out", str(out)],
             "GiB of memory", "--force")
    monkeypatch.setattr(files, "available_memory", lambda: 2 ** 40)
    monkeypatch.setattr(files.shutil, "disk_usage", lambda p: type("U", (), {"free": 1000}))
    _refused(capsys, sim_cli.main, ["render", "--random", "3", "--size", "64", "--frames",
                                    "2", "--out", str(out)], "writes about", "GiB free")
    for size in (["-32", "32"], ["0", "0"]):
        _refused(capsys, export.main, ["--factor", "4", "--format", "stablehlo", "--size",
                                       *size, "--out", str(tmp_path / "s")], "--size")
    assert sorted(os.listdir(tmp_path)) == []


def test_model_specs_that_name_no_checkpoint(tiny_data, tmp_path, capsys):
    (tmp_path / "folder.pt").mkdir()
    base = ["--dataset", tiny_data, "--factor", "4", "--quiet", "--out", str(tmp_path / "e")]
    _refused(capsys, evaluate.main, base + ["--models", f"m={tmp_path / 'folder.pt'}"],
             "is a folder")
    _refused(capsys, evaluate.main, base + ["--models", f"={tmp_path / 'folder.pt'}"],
             "empty label")
    assert not (tmp_path / "e").exists()


def test_a_video_missing_an_array_is_named(tiny_data, tmp_path, capsys):
    import shutil

    import h5py

    bad = tmp_path / "bad.h5"
    shutil.copy(tiny_data, bad)
    with h5py.File(bad, "a") as fh:
        name = sorted(fh["test"])[0]
        del fh[f"test/{name}/x4/motion"]
    _refused(capsys, evaluate.main, ["--dataset", str(bad), "--factor", "4", "--models",
                                     "jau", "--quiet", "--out", str(tmp_path / "e")],
             f"test/{name} lacks ['x4/motion']")


def test_generate_and_import_budgets_are_checked_before_any_work(tmp_path, capsys,
                                                                  monkeypatch):
    """`data generate` and `data import-exr` work out the memory and disk they need from
    the preset or from the EXR headers and the frame count, and refuse past what the
    machine has before rendering or reading a pixel; ``--force`` goes on."""
    from jtus import files
    from jtus.data import __main__ as data_cli
    from jtus.data import exr
    from jtus.sim import generate

    # the estimate tracks what a dataset takes: the game preset's 819 MB file (0.76 GiB)
    assert generate.preset("game").budget(2)[1] / 2 ** 30 == pytest.approx(0.755, abs=0.01)
    lr, hr = tmp_path / "lr", tmp_path / "hr"
    lr.mkdir(), hr.mkdir()
    for t in range(3):
        exr.write_exr(lr / f"frame{t:04d}.exr", {c: np.zeros((8, 12), np.float32)
                                                 for c in ("R", "G", "B", "Z", "mx", "my")})
        exr.write_exr(hr / f"frame{t:04d}.exr", {c: np.zeros((32, 48), np.float32)
                                                 for c in "RGB"})
    mem, disk = exr.sequence_budget(str(lr), str(hr), 4)
    assert (mem, disk) == (2 * 3 * (96 * 24 + 1536 * 12), 3 * (96 * 18 + 1536 * 6))
    out = tmp_path / "out.h5"
    monkeypatch.setattr(files, "available_memory", lambda: mem - 1)
    imp = ["import-exr", "--input", str(lr), "--target", str(hr), "--factor", "4",
           "--depth", "Z", "--motion", "mx,my", "--out", str(out)]
    _refused(capsys, data_cli.main, imp, "import-exr needs about", "--force")
    _refused(capsys, data_cli.main, ["generate", "--preset", "tiny", "--out", str(out),
                                     "--quiet"], "generate --preset tiny needs", "--force")
    monkeypatch.setattr(files, "available_memory", lambda: 2 ** 40)
    monkeypatch.setattr(files.shutil, "disk_usage", lambda p: type("U", (), {"free": disk - 1}))
    _refused(capsys, data_cli.main, imp, "writes about", "GiB free")
    assert sorted(os.listdir(tmp_path)) == ["hr", "lr"]
    assert data_cli.main(imp + ["--force"]) == 0 and out.exists()


def test_nss_budget_is_checked_before_a_pixel_is_read(tmp_path, capsys, monkeypatch):
    """`import-nss` works out its memory and disk from each sequence's JSON and frame
    count (every sequence held as float32 until the write; colours stored as float16)
    and refuses past what the machine has, before reading any image; ``--force`` goes on."""
    from jtus import files
    from jtus.data import nss
    from tests import nss_fixture

    root = str(tmp_path / "nss")
    nss_fixture.write_dataset(root)
    names = nss.sequences(root)
    lr, hr, n = (nss_fixture.H // 2) * (nss_fixture.W // 2), nss_fixture.H * nss_fixture.W, \
        nss_fixture.T
    mem, disk = nss.budget(root, 2)
    held = n * (lr * 24 + hr * 12)
    assert (mem, disk) == (held * (len(names) + 1), len(names) * n * (lr * 18 + hr * 6))
    out = tmp_path / "out.h5"
    argv = ["import-nss", "--root", root, "--factor", "2", "--out", str(out), "--quiet"]
    read = []
    monkeypatch.setattr(nss, "_frame_images", lambda *a: read.append(a))
    monkeypatch.setattr(files, "available_memory", lambda: mem - 1)
    _refused(capsys, data_cli.main, argv, "import-nss needs about", "--force")
    monkeypatch.setattr(files, "available_memory", lambda: 2 ** 40)
    monkeypatch.setattr(files.shutil, "disk_usage", lambda p: type("U", (), {"free": disk - 1}))
    _refused(capsys, data_cli.main, argv, "import-nss writes about", "GiB free")
    assert not read and not out.exists()
    monkeypatch.undo()
    assert data_cli.main(argv) == 0 and out.exists()


def test_train_step_memory_is_checked_before_the_workdir_is_touched(tiny_data, tmp_path,
                                                                     capsys, monkeypatch):
    """`train` compiles its optimizer step before any file is written and refuses a step
    whose buffers (XLA's buffer assignment: arguments, outputs, temporaries) exceed the
    machine's free memory; ``--force`` goes on."""
    from jtus import files, loading, train

    run = tmp_path / "run"
    argv = ["--preset", "tiny", "--dataset", tiny_data, "--workdir", str(run), "--quiet",
            "--no-eval", "--epochs", "1"]
    asked = []
    check = train.check_budget
    monkeypatch.setattr(train, "check_budget", lambda m, *a, **k: (asked.append(m),
                                                                   check(m, *a, **k)))
    monkeypatch.setattr(files, "available_memory", lambda: 2 ** 20)
    _refused(capsys, train.main, argv, "this training step needs about", "--batch", "--force")
    assert not run.exists()
    # at least what the step is handed: the train state (parameters and Adam's two
    # moments) and the window's frames and targets (float32: 4 frames of 2 crops, 16x16
    # targets of 3 channels and 4x4 inputs of colour, depth and motion); a tiny model's
    # step stays well under 1 GiB
    cfg = train.config_from_argv(argv)
    params = sum(x.size * 4 for x in train.jax.tree_util.tree_leaves(loading.init_params(cfg)))
    assert 3 * params + 4 * 2 * (16 * 16 * 3 + 4 * 4 * 6) * 4 < asked[0] < 2 ** 30, asked
    assert train.main(argv + ["--force"]) == 0
    assert (run / "checkpoint.msgpack").exists()


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
def test_an_out_path_where_no_file_can_be_created_is_refused_up_front(tiny_data, capsys):
    """/proc passes ``os.access(W_OK)`` for root yet takes no new file: the output
    check creates (and removes) a probe file, so the command stops before any work."""
    from jtus import export
    from jtus.data import __main__ as data_cli

    _refused(capsys, export.main, ["--factor", "4", "--format", "stablehlo", "--size", "32",
                                   "32", "--out", "/proc/jtus-x"], "--out", "/proc")
    _refused(capsys, data_cli.main, ["export", "--dataset", tiny_data, "--video",
                                     "objects_00", "--out", "/proc/jtus-x"], "--out", "/proc")
