"""End to end in seconds: train -> checkpoint -> resume -> evaluate -> upsample."""

import dataclasses
import json
import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jtus import evaluate, loading, losses, recipe, rollout, train, upsample
from jtus.config import PRESETS
from jtus.models import dlctus
from tests import seqdata


def _config(tiny_data, **kw):
    return dataclasses.replace(PRESETS["tiny"], **{"dataset": tiny_data, "epochs": 3, **kw})


def _leaves(params):
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(params)]


def test_killed_run_resumes_to_the_same_parameters(tiny_data, tmp_path):
    config = _config(tiny_data)
    full, hist_full = train.train_and_evaluate(config, tmp_path / "full", progress=False)
    part, hist_part = train.train_and_evaluate(config, tmp_path / "cut", progress=False,
                                               stop_after=2)
    assert len(hist_part) == 2  # killed after its second checkpoint
    resumed, hist = train.train_and_evaluate(config, tmp_path / "cut", resume=True,
                                             progress=False)
    assert [h["epoch"] for h in hist] == [1, 2, 3]
    for a, b in zip(_leaves(full), _leaves(resumed)):
        np.testing.assert_array_equal(a, b)
    assert hist[-1]["train_loss"] == hist_full[-1]["train_loss"]
    for name in ("checkpoint.msgpack", "metrics.json", "metrics.csv", "training.png",
                 "config.json"):
        assert (tmp_path / "cut" / name).exists()
    assert not [f for f in os.listdir(tmp_path / "cut") if f.endswith(".tmp")]
    # exported parameters load back unchanged, with their config
    path = loading.export_params(str(tmp_path / "full"), str(tmp_path / "shipped" / "m-x4"))
    params, cfg = loading.load_params(path, str(tmp_path / "shipped" / "m-x4.json"))
    assert cfg == config
    for a, b in zip(_leaves(full), _leaves(params)):
        np.testing.assert_array_equal(a, b)
    # stop_when (the ablations stop a collapsed run): checked after each epoch, and on
    # a resumed history, which then trains nothing more
    longer = dataclasses.replace(config, epochs=6)
    at4 = lambda h: "epoch 4" if h[-1]["epoch"] >= 4 else None  # noqa: E731
    for _ in range(2):
        _, hist = train.train_and_evaluate(longer, tmp_path / "cut", resume=True,
                                           progress=False, stop_when=at4)
        assert [h["epoch"] for h in hist] == [1, 2, 3, 4]
    # a finished run extended with more epochs lands where the longer run lands
    short = dataclasses.replace(config, epochs=2)
    train.train_and_evaluate(short, tmp_path / "ext", progress=False)
    extended, hist = train.train_and_evaluate(config, tmp_path / "ext", resume=True,
                                              progress=False)
    assert [h["epoch"] for h in hist] == [1, 2, 3]
    for a, b in zip(_leaves(full), _leaves(extended)):
        np.testing.assert_array_equal(a, b)


def test_resume_refuses_another_config(tiny_data, tmp_path):
    train.train_and_evaluate(_config(tiny_data, epochs=1), tmp_path, progress=False)
    with pytest.raises(ValueError, match="different config"):
        train.train_and_evaluate(_config(tiny_data, epochs=1, lr=0.5), tmp_path, resume=True,
                                 progress=False)


@pytest.mark.parametrize("mode,extra", [("tbptt", {"seq_len": 6, "k1": 2, "k2": 4}),
                                        ("bptt", {"loss": "st-linear", "remat": True})])
def test_training_variants_run(tiny_data, tmp_path, mode, extra):
    config = _config(tiny_data, epochs=1, mode=mode, **extra)
    _, hist = train.train_and_evaluate(config, tmp_path, progress=False)
    assert np.isfinite(hist[0]["train_loss"]) and np.isfinite(hist[0]["val_psnr"])


def test_train_loss_decreases(tiny_data, tmp_path):
    config = _config(tiny_data, epochs=4, steps_per_epoch=6, lr=3e-3, crop=32, batch=4)
    _, hist = train.train_and_evaluate(config, tmp_path, progress=False)
    assert hist[-1]["train_loss"] < hist[0]["train_loss"]


def test_cli_train_evaluate_upsample(tiny_data, tmp_path, capsys):
    work = tmp_path / "run-x4"
    assert train.main(["--preset", "tiny", "--dataset", tiny_data, "--workdir", str(work),
                       "--epochs", "1", "--quiet", "--no-eval"]) == 0
    ckpt = work / "checkpoint.msgpack"
    assert ckpt.exists()
    out = tmp_path / "eval"
    # "{f}" in a path stands for the factor being evaluated
    assert evaluate.main(["--dataset", tiny_data, "--factor", "4", "--models", "jau", "tus",
                          f"mine={tmp_path / 'run-x{f}' / 'checkpoint.msgpack'}", "--out",
                          str(out), "--json", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert set(summary["4"]) == {"jau", "tus", "mine"}
    for name in ("results.md", "results.json", "per_frame_x4.png", "crops_x4.png"):
        assert (out / name).exists()
    frames_dir = tmp_path / "frames"
    assert upsample.main(["--input", tiny_data, "--factor", "4", "--model", f"mine={ckpt}",
                          "--out", str(frames_dir), "--mp4", str(tmp_path / "v.mp4")]) == 0
    assert len(os.listdir(frames_dir)) == 8 and (tmp_path / "v.mp4").stat().st_size > 0
    assert train.main(["--preset", "tiny", "--dataset", tiny_data, "--mode", "tbptt",
                       "--k1", "3", "--k2", "2", "--workdir", str(tmp_path / "bad"),
                       "--quiet", "--no-eval"]) == 2
    assert "k1 <= k2" in capsys.readouterr().err
    assert evaluate.main(["--dataset", tiny_data, "--models", "nerf", "--out",
                          str(out), "--quiet"]) == 2


def test_a_failed_command_leaves_an_existing_run_alone(tiny_data, tmp_path, capsys):
    work = tmp_path / "t1"
    base = ["--preset", "tiny", "--dataset", tiny_data, "--workdir", str(work), "--quiet",
            "--no-eval", "--epochs", "1"]
    assert train.main(base) == 0
    before = {n: (work / n).read_bytes() for n in os.listdir(work)}
    for extra, msg in ((["--factor", "2", "--crop", "64"], "holds a run"),
                       (["--overwrite", "--crop", "64"], "crop: 64 exceeds"),
                       (["--overwrite", "--seq-len", "20"], "shortest train video"),
                       (["--val-videos", "0"], "val_videos"),
                       (["--lr", "nan"], "lr"), (["--epochs", "0"], "epochs"),
                       (["--steps-per-epoch", "0"], "steps_per_epoch"),
                       (["--batch", "0"], "batch"), (["--crop", "0"], "crop"),
                       (["--seq-len", "0"], "seq_len")):
        capsys.readouterr()
        assert train.main(base + extra) == 2, extra
        assert msg in capsys.readouterr().err, extra
    assert {n: (work / n).read_bytes() for n in os.listdir(work)} == before
    # a bad new run writes nothing at all
    assert train.main(base[:4] + ["--workdir", str(tmp_path / "new"), "--quiet", "--no-eval",
                                  "--crop", "64"]) == 2
    assert not (tmp_path / "new").exists()
    # --overwrite starts again
    assert train.main(base + ["--overwrite", "--lr", "0.002"]) == 0
    assert json.loads((work / "config.json").read_text())["lr"] == 0.002


def test_non_finite_data_stops_training_without_a_checkpoint(tiny_data, tmp_path):
    import shutil

    import h5py

    bad = tmp_path / "nan.h5"
    shutil.copyfile(tiny_data, bad)
    with h5py.File(bad, "r+") as fh:
        for name in fh["train"]:
            fh[f"train/{name}/x4/color"][...] = np.nan
    with pytest.raises(ValueError, match="non-finite loss.*no checkpoint was written"):
        train.train_and_evaluate(_config(str(bad)), tmp_path / "run", progress=False)
    assert not (tmp_path / "run" / "checkpoint.msgpack").exists()


def test_evaluate_refuses_ambiguous_or_empty_model_lists(tiny_data, tmp_path, capsys):
    work = tmp_path / "run-x4"
    assert train.main(["--preset", "tiny", "--dataset", tiny_data, "--workdir", str(work),
                       "--epochs", "1", "--quiet", "--no-eval"]) == 0
    ckpt = str(work / "checkpoint.msgpack")
    base = ["--dataset", tiny_data, "--factor", "4", "--out", str(tmp_path / "e"), "--quiet",
            "--no-crops"]
    for specs, msg in ((["tus", "tus"], "more than once"),
                       ([f"a={ckpt}", f"a={ckpt}"], "more than once"),
                       (["dlctus"], "needs weights"), (["kpn"], "needs weights"),
                       (["nerf"], "not a model")):
        capsys.readouterr()
        assert evaluate.main(base + ["--models"] + specs) == 2, specs
        assert msg in capsys.readouterr().err, specs
    assert evaluate.main(base + ["--models", "tus", "--videos", "objects*"]) == 0
    assert evaluate.main(base + ["--models", "tus", "--videos", "nothing*"]) == 2
    assert "match 'nothing*'" in capsys.readouterr().err
    # a checkpoint of another factor is skipped; when nothing is left, that is an error
    base2 = [b if b != "4" else "2" for b in base]
    assert evaluate.main(base2 + ["--models", f"m={ckpt}"]) == 2
    assert "none of" in capsys.readouterr().err


def test_load_params_checks_structure_shapes_and_values(tiny_data, tmp_path):
    from flax import serialization

    work = tmp_path / "run"
    train.train_and_evaluate(_config(tiny_data, epochs=1), work, progress=False)
    good, _ = loading.load_params(str(work / "checkpoint.msgpack"))
    base = str(tmp_path / "p")
    loading.export_params(str(work), base)
    path, cfg = base + ".msgpack", base + ".json"

    def write(obj):
        with open(path, "wb") as fh:
            fh.write(obj if isinstance(obj, bytes) else serialization.to_bytes(obj))

    bad_kernel = jax.tree_util.tree_map(np.asarray, good)
    bad_kernel["down"]["kernel"] = np.zeros((3, 3, 8, 32), np.float32)
    ints = jax.tree_util.tree_map(lambda x: np.zeros(x.shape, np.int32), good)
    nans = jax.tree_util.tree_map(lambda x: np.full(x.shape, np.nan, np.float32), good)
    for obj, msg in ((b"\xc1\xc1 garbage", "not a readable checkpoint"),
                     ({"weights": 1}, "no 'params' entry"),
                     ({"params": bad_kernel}, "['down']['kernel'] has shape (3, 3, 8, 32)"),
                     ({"params": ints}, "dtype int32"), ({"params": nans}, "NaN or Inf")):
        write(obj)
        with pytest.raises(ValueError, match=re.escape(msg)) as e:
            loading.load_params(path)
        assert "p.msgpack" in str(e.value)
    write({"params": good})
    with open(cfg) as fh:
        data = json.load(fh)
    with open(cfg, "w") as fh:
        json.dump({**data, "colour": 1}, fh)
    with pytest.raises(ValueError, match=r"p.json: unknown config keys \['colour'\]"):
        loading.load_params(path)


def test_epoch_log_keeps_gradient_norms_and_collapse_reads_it(tiny_data, tmp_path):
    _, hist = train.train_and_evaluate(_config(tiny_data, epochs=1), tmp_path, progress=False)
    rec = hist[0]
    assert 0 < rec["grad_norm"] <= rec["grad_norm_max"] and rec["param_norm"] > 0
    assert "grad_norm" in (tmp_path / "metrics.csv").read_text().splitlines()[0]
    assert train.collapsed(hist) is None
    flat = [dict(rec, epoch=e, grad_norm=0.0, grad_norm_max=0.0) for e in (1, 2)]
    assert "gradient norm" in train.collapsed(flat)
    same = [dict(rec, epoch=e, val_loss=0.25) for e in (1, 2, 3)]
    assert "validation loss" in train.collapsed(same)
    # a log written before the norms were kept (old runs resume) still reads
    old = [{k: v for k, v in rec.items() if "norm" not in k}]
    assert train.collapsed(old) is None


def test_train_comparison_script_passes_valid_configs():
    """Every run of experiments/train_comparison.sh (each model's arguments, its
    per-factor override, both factors) parses into a valid training config, so a typo
    there fails here and not hours into a background run."""
    import shlex

    text = open(os.path.join(os.path.dirname(__file__), "..", "experiments",
                             "train_comparison.sh")).read()
    common = shlex.split(re.search(r'^common="([^"]*)"', text, re.M).group(1)
                         .replace("${EXTRA:-}", ""))

    def table(name):  # the bash associative array NAME: key -> argument string
        body = re.search(rf"^declare -A {name}=\((.*?)^\)", text, re.M | re.S).group(1)
        return dict(re.findall(r'^\s+\[([\w-]+)\]="([^"]*)"', body, re.M))

    args, override = table("args"), table("override")
    assert set(args) == {"mlp", "kpn", "nsrr-fast", "nsrr"}
    assert set(override) <= {f"{m}-{f}" for m in args for f in (2, 4)}, override
    for m, a in args.items():
        for f in (4, 2):
            argv = common + shlex.split(a) + shlex.split(override.get(f"{m}-{f}", "")) + [
                "--factor", str(f), "--workdir", "unused"]
            cfg = train.config_from_argv(argv)
            assert (cfg.model, cfg.factor, cfg.dataset) == (m, f, PRESETS["diverse"].dataset)
            if f"{m}-{f}" in override:
                assert "--lr" not in override[f"{m}-{f}"] or cfg.lr != train.config_from_argv(
                    common + shlex.split(a) + ["--factor", str(f)]).lr


def _load_experiment(name, folder="experiments"):
    """An experiment script (or a tool) as a module (its folder on sys.path while it
    loads, as when it runs as a script)."""
    import importlib.util
    import sys

    exp = os.path.join(os.path.dirname(__file__), "..", folder)
    sys.path.insert(0, exp)
    try:
        spec = importlib.util.spec_from_file_location(name, os.path.join(exp, f"{name}.py"))
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(exp)
    return module


def _load_ablations():
    return _load_experiment("ablations")


def test_ablation_studies_build_valid_models():
    """Every variant of experiments/ablations.py is a valid training config whose model
    builds and differs from the first variant's where the study says (a typo in a model
    override would otherwise surface hours into a run)."""
    ablations = _load_ablations()
    for study, field, expected in (("accumulation", "accumulation", [True, False]),
                                   ("warp", "warp", ["bicubic", "bilinear"]),
                                   ("theta", None, None)):
        vs = ablations.variants(study, [0.2, 0.8])
        cfgs = [dataclasses.replace(PRESETS["diverse"], **ch) for _, ch in vs]
        built = [recipe.model_for(c) for c in cfgs]
        if field:
            assert [getattr(m.config, field) for m in built] == expected
        else:
            assert [(c.loss, c.theta) for c in cfgs[1:]] == [("st-linear", 0.2),
                                                             ("st-linear", 0.8)]
            assert cfgs[0].loss == "l1"
        assert len({ablations.slug(label) for label, _ in vs}) == len(vs)
    with pytest.raises(ValueError, match="study"):
        ablations.variants("nope", [])
    # DLCTUS as the recipe has it is a variant of all three studies: it trains once,
    # under the accumulation study; the other variants train in their own study
    base = dataclasses.replace(PRESETS["diverse"], lr=ablations.LR)
    shared = os.path.join(ablations.ROOT, "runs", "ablation-accumulation", "with_buffer-s3")
    for study, expected in (("accumulation", [shared, "without_buffer-s3"]),
                            ("warp", [shared, "bilinear-s3"]),
                            ("theta", [shared, "l_st_linear_θ_0_2-s3", "l_st_linear_θ_0_8-s3"])):
        dirs = [ablations.run_of(study, label, ch, base, 3, [0.2, 0.8])[0]
                for label, ch in ablations.variants(study, [0.2, 0.8])]
        assert dirs[0] == shared
        assert [os.path.relpath(d, os.path.join(ablations.ROOT, "runs", f"ablation-{study}"))
                for d in dirs[1:]] == expected[1:]
    # a variant that reads another's run resumes it with that run's own config (the
    # bicubic variant sets the warp the recipe already has: the same network, but a
    # config that train's resume check would refuse)
    label, bicubic = ablations.variants("warp", [])[0]
    work, cfg = ablations.run_of("warp", label, bicubic, base, 3)
    assert work == shared and cfg == dataclasses.replace(base, seed=3)
    assert cfg != dataclasses.replace(base, seed=3, **bicubic)
    # at another learning rate the runs (and results) have their own folders
    other = dataclasses.replace(base, lr=1e-3)
    assert ablations.run_of("warp", "bilinear", ablations.variants("warp", [])[1][1], other,
                            3)[0] == os.path.join(ablations.ROOT, "runs",
                                               "ablation-warp-lr0.001", "bilinear-s3")
    assert ablations.study_name("theta", 1e-3) == "ablation-theta-lr0.001"
    # a run's checkpoint goes to experiments/checkpoints/ablation-<study>/<run>/ and back
    work = os.path.join(ablations.ROOT, "runs", "ablation-warp", "bilinear-s4")
    assert os.path.relpath(ablations.saved_dir(work), ablations.ROOT) == os.path.join(
        "experiments", "checkpoints", "ablation-warp", "bilinear-s4")


def test_ablation_progress_reads_the_committed_runs(tmp_path, monkeypatch):
    """Before a study's table exists, docs/results.md lists its committed runs: epochs
    done of the config's, the last validation PSNR, collapsed (train.collapsed) or not."""
    ablations = _load_experiment("common")  # the ablations' run bookkeeping
    monkeypatch.setattr(ablations, "ROOT", str(tmp_path))
    assert ablations.runs_so_far("warp") == []
    keys = ("epoch", "step", "train_loss", "grad_norm", "grad_norm_max", "param_norm",
            "val_loss", "val_psnr")
    for run, rows in (("with_buffer-s0", [(1, 4, 0.1, 0.5, 0.9, 3, 0.2, 24.5),
                                          (2, 8, 0.1, 0.4, 0.8, 3, 0.19, 25.25)]),
                      ("with_buffer-s1", [(1, 4, 0.1, 0.0, 0.0, 3, 0.3, 20.0)])):
        d = tmp_path / "experiments" / "checkpoints" / "ablation-accumulation" / run
        d.mkdir(parents=True)
        (d / "config.json").write_text('{"epochs": 10}')
        (d / "metrics.json").write_text(json.dumps([dict(zip(keys, r)) for r in rows]))
    text = "\n".join(ablations.runs_so_far("accumulation"))
    assert "| with_buffer-s0 | 2 of 10 | 25.25 | in training |" in text
    assert "| with_buffer-s1 | 1 of 10 | 20.00 | collapsed (the gradient norm stayed" in text


def test_collapse_probe_reads_committed_runs_over_their_first_epochs(tmp_path):
    """experiments/collapse_probe.py: a committed ablation run joins the table with its
    variant, learning rate and seed from its folder and config, judged collapsed or not
    (train.collapsed) on its first epochs only."""
    cp = _load_experiment("collapse_probe")
    keys = ("epoch", "grad_norm", "grad_norm_max", "val_loss", "val_psnr")
    for run, lr, rows in (("without_buffer-s3", 1e-3, [(1, 0.1, 0.2, 0.3, 25.1),
                                                         (2, 0.0, 0.0, 0.3, 25.1),
                                                         (3, 0.0, 0.0, 0.3, 25.1)]),
                          ("with_buffer-s0", 3e-4, [(1, 0.1, 0.2, 0.3, 26.0),
                                                    (2, 0.1, 0.2, 0.2, 26.5),
                                                    (3, 0.0, 0.0, 0.2, 26.5)])):
        d = tmp_path / run
        d.mkdir()
        (d / "config.json").write_text(json.dumps({"lr": lr, "epochs": 10}))
        (d / "metrics.json").write_text(json.dumps([dict(zip(keys, r)) for r in rows]))
    got = {r["seed"]: r for r in cp.committed_runs(str(tmp_path), 2)}
    assert (got[3]["variant"], got[3]["lr"], got[3]["epochs"]) == ("without buffer", 1e-3, 2)
    assert "gradient norm stayed below" in got[3]["collapsed"]
    assert (got[0]["variant"], got[0]["val_psnr"], got[0]["collapsed"]) == (
        "with buffer", [26.0, 26.5], None)  # its third epoch's zero gradient is not read


def test_runs_are_saved_and_restored(tmp_path):
    """Ablation studies and comparison runs span sessions through committed copies of
    their checkpoints (experiments/saved_runs.py, called by ablations.py and by
    train_comparison.sh as a command: exit 1 when there is nothing to copy)."""
    saved_runs = _load_experiment("saved_runs")
    src, dst = tmp_path / "run", tmp_path / "saved"
    src.mkdir()
    assert not saved_runs.copy_run(str(src), str(dst))  # no checkpoint: nothing copied
    assert saved_runs.main([str(src), str(dst)]) == 1
    assert not dst.exists()
    for name, text in (("checkpoint.msgpack", "ck"), ("config.json", "{}"),
                       ("metrics.csv", "epoch"), ("training.png", "not kept")):
        (src / name).write_text(text)
    assert saved_runs.main([str(src), str(dst)]) == 0
    assert sorted(os.listdir(dst)) == ["checkpoint.msgpack", "config.json", "metrics.csv"]
    assert (dst / "checkpoint.msgpack").read_text() == "ck"


def test_comparison_table_systems_and_targets():
    """experiments/comparison_table.py: every system is listed at both factors with a
    spec that loads (or none, when it has no training on the diverse data), and the
    targets' margins and verdicts follow their thresholds."""
    ct = _load_experiment("comparison_table")
    for f in (4, 2):
        rows = ct.systems(f)
        assert [r[0] for r in rows] == ["jau", "tus", "dlctus", *ct.SYSTEMS]
        for label, spec, status, budget in rows:
            if spec is None:
                assert budget is None and "not trained" in status
                continue
            entry = loading.load(spec, f)
            assert entry is not None and entry.label == label
            if label not in ("jau", "tus"):
                assert budget["steps"] > 0 and budget["seconds"] > 0
    psnr = lambda v: {"psnr": v}  # noqa: E731
    res = {"4": {"random": {"dlctus": psnr(30.0), "tus": psnr(28.0), "jau": psnr(27.0),
                            "nsrr": psnr(27.5)},
                 "external": {"dlctus": psnr(22.0), "tus": psnr(22.5), "jau": psnr(21.0)}},
           "2": {"handmade": {"dlctus": psnr(33.4), "tus": psnr(32.0), "jau": psnr(31.0),
                              "mlp": psnr(31.5)}}}
    got = {what: (round(m, 6), ok) for what, m, ok in ct.targets(res)}
    assert got == {"DLCTUS - TUS >= 2.0 dB, random, 4x": (2.0, True),
                   "DLCTUS - TUS > 0, external, 4x": (-0.5, False),
                   "nsrr - JAU > 0, random, 4x": (0.5, True),
                   "DLCTUS - TUS >= 1.5 dB, handmade, 2x": (1.4, False),
                   "mlp - JAU > 0, handmade, 2x": (0.5, True),
                   "NSRR - TUS > 0, random, 4x": (-0.5, False)}


def test_readme_figure_takes_the_best_trained_system_on_validation(tmp_path):
    """experiments/readme_figure.py's default comparison column: the trained system with
    the highest validation PSNR, never a baseline, with a clear error when none scored."""
    rf = _load_experiment("readme_figure")
    d = tmp_path / "docs" / "results" / "comparison-val" / "x4"
    d.mkdir(parents=True)
    scores = {"jau": 25.3, "tus": 25.4, "dlctus-shipped": 28.3, "mlp": 25.0, "nsrr": 27.1,
              "nsrr-fast": 27.0}
    (d / "results.json").write_text(json.dumps({"4": {k: {"psnr": v} for k, v in
                                                      scores.items()}}))
    assert rf.best_on_validation(4, str(tmp_path)) == "nsrr=experiments/weights/nsrr-x4.msgpack"
    (d / "results.json").write_text(json.dumps({"4": {"jau": {"psnr": 1.0}}}))
    with pytest.raises(ValueError, match="no comparison system scored"):
        rf.best_on_validation(4, str(tmp_path))


def test_training_summary_takes_the_longer_log(tmp_path):
    """A run's newest log is its longer one (file times mean nothing in a fresh clone);
    on a tie the exported (finished) one; logs of other data are not counted."""
    ts = _load_experiment("training_summary")

    def log(rel, epochs, dataset="data/diverse.h5", cfg_name="config.json"):
        d = tmp_path / os.path.dirname(rel)
        d.mkdir(parents=True, exist_ok=True)
        rows = "epoch,step,val_psnr,seconds\n" + "".join(
            f"{e},{100 * e},{20 + e},10\n" for e in range(1, epochs + 1))
        (tmp_path / rel).write_text(rows)
        (d / cfg_name).write_text(json.dumps({"epochs": 40, "dataset": dataset}))

    log("experiments/checkpoints/kpn-diverse-x2/metrics.csv", 20)
    log("experiments/weights/kpn-x2-training.csv", 40, cfg_name="kpn-x2.json")
    rows, planned, src = ts.find("kpn", 2, str(tmp_path))
    assert (len(rows), planned, src) == (40, 40, "experiments/weights/kpn-x2-training.csv")
    log("experiments/checkpoints/mlp-diverse-x4/metrics.csv", 7)
    log("experiments/weights/mlp-x4-training.csv", 3, cfg_name="mlp-x4.json")
    assert ts.find("mlp", 4, str(tmp_path))[2].startswith("experiments/checkpoints/")
    log("experiments/weights/nsrr-x4-training.csv", 3, dataset="data/default.h5",
        cfg_name="nsrr-x4.json")
    assert ts.find("nsrr", 4, str(tmp_path)) is None
    s = ts.summarize(rows, planned)
    assert (s["epochs"], s["steps"], s["best"], s["last_fifth"], s["flat"]) == \
        (40, 4000, 60.0, 8.0, False)
    # train_comparison.sh skips a run only when its exported log reaches the planned
    # epochs: not when the longer log is a checkpoint's, nor when more epochs are planned
    assert ts.finished("kpn", 2, 40, str(tmp_path))
    assert not ts.finished("kpn", 2, 41, str(tmp_path))
    assert not ts.finished("mlp", 4, 3, str(tmp_path))
    assert not ts.finished("nsrr", 4, 3, str(tmp_path))


def test_mutation_script_counts_mutants_and_sets_the_jit_mode(tmp_path, monkeypatch):
    """tools/mutation.py: an equivalent mutant and an unchecked one are not in the
    rate, a timeout is not a kill (except a listed mutant that breaks the import); the
    hook it appends to the scratch conftest runs only mutmut's call-recording run op by
    op; results of separate runs merge."""
    mu = _load_experiment("mutation", "tools")
    equivalent = next(iter(mu.EQUIVALENT))
    status = {"m.x_a__mutmut_1": "killed", "m.x_a__mutmut_2": "survived",
              "m.x_a__mutmut_3": "timeout", "m.x_a__mutmut_4": "not checked",
              equivalent: "survived"}
    counts, tested, killed = mu.summarize(status)
    assert (tested, killed) == (3, 1) and equivalent not in counts
    # the results list a timed-out mutant with the survivors, marked as such
    assert mu.row("m.py", status, None)[-1] == ["m.x_a__mutmut_2",
                                                "m.x_a__mutmut_3 (timed out)"]
    # a mutant that breaks the module's import exits before any test (mutmut: timeout):
    # a kill only when it is listed in BREAKS_IMPORT, and only for that exit
    breaks = next(iter(mu.BREAKS_IMPORT))
    _, _, run, killed, *_ = mu.row("m.py", {**status, breaks: "timeout"}, None)
    assert (run, killed) == (4, 2)
    _, _, run, killed, *_, survivors = mu.row("m.py", {**status, breaks: "survived"}, None)
    assert (run, killed) == (4, 1) and breaks in survivors
    # the rate is rounded down: one survivor among 203 is not 100%
    many = {f"m.x_a__mutmut_{i}": "killed" for i in range(202)}
    assert mu.row("m.py", {**many, "m.x_b__mutmut_1": "survived"}, None)[4] == "99.5%"
    assert mu.row("m.py", many, None)[4] == "100%"
    assert mu.row("m.py", status, None)[4] == "33.3%"
    conftest = open(os.path.join(os.path.dirname(__file__), "conftest.py")).read()
    assert "\nimport jax\n" in conftest and "\nimport os\n" in conftest  # the hook's names
    ns = {"jax": jax, "os": os}
    exec(mu.STATS_OP_BY_OP, ns)
    try:
        monkeypatch.setenv("MUTANT_UNDER_TEST", "stats")
        ns["pytest_sessionstart"](None)
        assert jax.config.jax_disable_jit
        monkeypatch.setenv("MUTANT_UNDER_TEST", "jtus.losses.x_make__mutmut_1")
        ns["pytest_sessionstart"](None)
        assert not jax.config.jax_disable_jit
    finally:
        jax.config.update("jax_disable_jit", False)
    import tomllib
    for module, k in (("jtus/models/kpn.py", True), ("jtus/losses.py", False)):
        cfg = tomllib.loads(mu.config_block(module, mu.TESTS[module]))["tool"]["mutmut"]
        assert cfg["paths_to_mutate"] == [module] and cfg["tests_dir"] == mu.TESTS[module]
        args = cfg["pytest_add_cli_args"]
        assert args[:2] == ["-n", "0"] and ("-k" in args) == k
        if k:
            assert args[args.index("-k") + 1].startswith("not test_trains_with_decreasing")
    # a model's scope: its step's functions and its Config's methods, not its FLOP count
    globs, sep = mu.scope_globs("jtus/models/tus.py"), "\u01c1"  # mutmut's class separator
    assert "jtus.models.tus.x_step__mutmut_*" in globs
    assert f"jtus.models.tus.x{sep}Config{sep}*" in globs
    assert not any("x_cost_" in g for g in globs) and mu.scope_globs("jtus/losses.py") == []
    assert not mu.in_scope("jtus/models/tus.py", "jtus.models.tus.x_cost__mutmut_2")
    assert mu.in_scope("jtus/models/tus.py", "jtus.models.tus.x__beta__mutmut_2")
    method = f"jtus.models.tus.x{sep}Config{sep}__post_init____mutmut_1"
    assert mu.in_scope("jtus/models/tus.py", method)
    assert mu.in_scope("jtus/losses.py", "jtus.losses.x_cost__mutmut_1")
    out = str(tmp_path / "results.md")
    mu.write_results(out, [("jtus/metrics.py", 10, 9, 9, "100%", 5.0, [])], "cmd-a")
    mu.write_results(out, [("jtus/losses.py", 20, 18, 17, "94%", 7.0, ["m.x_b"])], "cmd-b")
    text = open(out).read()
    assert "| `jtus/metrics.py` | 10 | 9 | 9 | 100% |" in text and "`cmd-a`" in text
    assert "| `jtus/losses.py` | 20 | 18 | 17 | 94% |" in text and "`m.x_b`" in text
    mu.write_results(out, [("jtus/rollout.py", 9, 4, 4, "100%", None, [])], "cmd-c")
    text = open(out).read()  # a --save-only row has no seconds; the others are kept
    assert "| `jtus/rollout.py` | 9 | 4 | 4 | 100% | - | `cmd-c`" in text and "`cmd-a`" in text


def test_comparison_table_only_rescores_the_named_systems(tmp_path, monkeypatch):
    """comparison_table.py --only: the named system is scored again, every other row is
    carried over from the earlier result with the command that scored it; a system
    without weights, or an earlier result of other factors, is refused."""
    import sys

    ct = _load_experiment("comparison_table")
    written = []
    monkeypatch.setattr(ct, "write", lambda name, table, data, note="": written.append(
        (table, data, note)))
    monkeypatch.setattr(ct, "RESULTS", str(tmp_path))

    def scorer(value):
        return lambda entries, fam, f, root: {e.label: {"psnr": value, "ssim": 0.5,
                                                        "temporal": 0.1} for e in entries}

    monkeypatch.setattr(ct, "score", scorer(20.0))
    # NSRR without any weights, whatever runs the repository holds at the time
    find = ct.find
    monkeypatch.setattr(ct, "find", lambda m, f, root: None if m == "nsrr" else find(m, f, root))
    monkeypatch.setattr(sys, "argv", ["experiments/comparison_table.py", "--first"])
    root = tmp_path / "root"  # the data is only checked to exist: score is replaced
    (root / "data").mkdir(parents=True)
    (root / "data" / "diverse.h5").write_bytes(b"")
    fam = ["--families", "random", "--data-root", str(root), "--thesis", ""]
    ct.main(["--factors", "4", *fam])
    first = written[-1][1]
    labels = [lab for lab, spec, _, _ in ct.systems(4) if spec]
    assert sorted(first["4"]["random"]) == sorted(labels)
    (tmp_path / "comparison-table").mkdir(exist_ok=True)  # readme.md is written there
    (tmp_path / "comparison-table" / "result.json").write_text(json.dumps(first))
    monkeypatch.setattr(ct, "score", scorer(30.0))
    monkeypatch.setattr(sys, "argv", ["experiments/comparison_table.py", "--second"])
    ct.main(["--factors", "4", *fam, "--only", "dlctus"])
    table, data, note = written[-1]
    got = {lab: v["psnr"] for lab, v in data["4"]["random"].items()}
    assert got == {lab: 30.0 if lab == "dlctus" else 20.0 for lab in labels}
    assert data["4"]["made_by"]["dlctus"].endswith("--second")
    assert data["4"]["made_by"]["jau"].endswith("--first")
    assert "4x jau: `python experiments/comparison_table.py --first`" in note
    assert "| dlctus | shipped | 30.00 / 0.5000 / 0.10000 |" in table
    with pytest.raises(SystemExit):  # no weights to evaluate
        ct.main(["--factors", "4", *fam, "--only", "nsrr"])
    with pytest.raises(SystemExit):  # the earlier result has no 2x
        ct.main(["--factors", "4", "2", *fam, "--only", "dlctus"])


def test_ablation_table_sets_each_gap_against_the_thesis():
    """The line under an ablation table: each variant's mean PSNR gap to the first
    variant, its standard error over independent seeds, and the thesis's gap (Table 16:
    35.23 - 35.49 dB without the buffer)."""
    ablations = _load_ablations()
    trained = [{"variant": "with buffer", "psnr": p} for p in (29.0, 29.2, 29.4)] + \
              [{"variant": "without buffer", "psnr": p} for p in (29.5, 29.6)]
    lines = ablations.against_thesis("accumulation", trained)
    se = np.sqrt(0.04 / 3 + 0.005 / 2)  # sample variances 0.04 and 0.005
    assert lines[-1] == f"| without buffer | +0.35 | {se:.2f} | -0.26 |"
    assert ablations.against_thesis("accumulation", []) == []
    # a θ the thesis did not train has no thesis gap
    lines = ablations.against_thesis("theta", [{"variant": "L1", "psnr": 30.0},
                                               {"variant": "L_st-linear θ=0.25", "psnr": 29.9}])
    assert lines[-1] == "| L_st-linear θ=0.25 | -0.10 | - | - |"  # one seed: no spread


def test_real_train_step_hands_on_the_carry_after_k1_frames():
    """TBPTT in the training step ``train`` runs (``make_train_step`` with
    ``keep_at``): the carry it returns, which starts the next window, is the state
    after k1 frames of this window, computed with the parameters before the update.
    Catches: the step handing on the carry after the whole window (``last`` for
    ``kept``), which the rollout-level chaining test does not run."""
    frames, targets = seqdata.to_jax(seqdata.sequence(T=4, B=2))
    model = dlctus.make(dlctus.Config(factor=4))
    params = model.init(jax.random.PRNGKey(0))
    opt = optax.adam(1e-2)
    step = train.make_train_step(model, losses.make("l1", 4), opt, loss_frames=2, keep_at=2)
    carry = rollout.start(model.init_state(seqdata.first(frames)), targets[0])
    ts = train.create_train_state(jax.tree_util.tree_map(jnp.copy, params), opt)
    _, nxt, _ = step(ts, carry, frames, targets)
    head = jax.tree_util.tree_map(lambda x: x[:2], frames)
    state0 = model.init_state(seqdata.first(frames))
    outs, state2 = rollout.outputs(model.step, params, state0, head)
    np.testing.assert_allclose(nxt.state.history, state2.history, rtol=0, atol=1e-5)
    np.testing.assert_allclose(nxt.prev_out, outs[1], rtol=0, atol=1e-5)
    np.testing.assert_array_equal(nxt.prev_target, targets[1])
    assert bool(nxt.has_prev)
    _, state4 = rollout.outputs(model.step, params, model.init_state(seqdata.first(frames)), frames)
    assert float(jnp.abs(state4.history - state2.history).max()) > 1e-3  # control
