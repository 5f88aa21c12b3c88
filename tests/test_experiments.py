"""The experiment scripts' own logic, each loaded as a module: the ablations' variants
and run bookkeeping, the comparison table's systems and targets, the comparison
runs' logs, the README figure's choice, the training script's per-run overrides."""

import dataclasses
import json
import os
import re

import jax
import numpy as np
import pytest

from jtus import checkpoint, loading, recipe, train
from jtus import config as config_mod
from jtus.config import PRESETS
from jtus.models import dlctus, kernels
from tests import seqdata


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


def _load_ablations():
    return seqdata.load_script("ablations")


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
    ablations = seqdata.load_script("common")  # the ablations' run bookkeeping
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
    cp = seqdata.load_script("collapse_probe")
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
    saved_runs = seqdata.load_script("saved_runs")
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


def test_a_fine_tunes_budget_adds_the_run_it_started_from(tmp_path, monkeypatch):
    """experiments/comparison_table.py: a run whose ``init_from`` names exported weights
    (with their config and log beside them) counts their steps and seconds too."""
    ct = seqdata.load_script("comparison_table")
    monkeypatch.setattr(ct, "ROOT", str(tmp_path))
    (tmp_path / "w").mkdir()
    base = {"epochs": 2, "crop": 128, "seq_len": 16}
    (tmp_path / "w" / "base.json").write_text(json.dumps(base))
    (tmp_path / "w" / "base-training.csv").write_text(
        "epoch,step,val_psnr,seconds\n1,400,30,100\n2,800,31,110\n")
    rows = [{"epoch": "1", "step": "400", "val_psnr": "32", "seconds": "50"}]
    tune = dict(base, epochs=1, init_from="w/base.msgpack")
    assert ct.budget(tune, rows) == {"steps": 1200, "crop": 128, "frames": 16, "seconds": 260}
    assert ct.budget(dict(tune, init_from="w/missing.msgpack"), rows)["steps"] == 400


def test_second_stage_needs_weights_config_and_log(tmp_path):
    """experiments/common.second_stage: a comparison system's adopted fine-tune is
    ``experiments/weights/<model>-mix-x<f>`` with its config and log beside it; a
    missing file means none was adopted."""
    common = seqdata.load_script("common")
    base = tmp_path / "experiments" / "weights"
    base.mkdir(parents=True)
    assert common.second_stage("kpn", 4, str(tmp_path)) is None
    (base / "kpn-mix-x4.msgpack").write_bytes(b"w")
    (base / "kpn-mix-x4.json").write_text(json.dumps(
        {"config": {"epochs": 1, "init_from": "experiments/weights/kpn-x4.msgpack"}}))
    assert common.second_stage("kpn", 4, str(tmp_path)) is None  # no log
    (base / "kpn-mix-x4-training.csv").write_text("epoch,step,val_psnr,seconds\n1,100,30,9\n")
    path, rows, cfg = common.second_stage("kpn", 4, str(tmp_path))
    assert path == "experiments/weights/kpn-mix-x4.msgpack" and rows[0]["step"] == "100"
    assert cfg["init_from"] == "experiments/weights/kpn-x4.msgpack"
    assert common.second_stage("kpn", 2, str(tmp_path)) is None


def test_redesign_needs_weights_config_and_log(tmp_path, monkeypatch):
    """experiments/common.redesigned: a system's adopted redesign is
    ``experiments/weights/<name>-x<f>`` (``REDESIGNED``) with its config and log beside
    it, described for the table, at the factors where it was adopted (each factor may
    name its own weights); a missing file, a factor not adopted, or a system without one,
    gives None."""
    common = seqdata.load_script("common")
    monkeypatch.setattr(common, "REDESIGNED", {"kpn": {4: ("kpn-new", "a new design")}})
    base = tmp_path / "experiments" / "weights"
    base.mkdir(parents=True)
    for f in (4, 2):
        (base / f"kpn-new-x{f}.msgpack").write_bytes(b"w")
        (base / f"kpn-new-x{f}.json").write_text(json.dumps({"config": {"epochs": 1}}))
    assert common.redesigned("kpn", 4, str(tmp_path)) is None  # no log
    for f in (4, 2):
        (base / f"kpn-new-x{f}-training.csv").write_text(
            "epoch,step,val_psnr,seconds\n1,100,30,9\n")
    path, rows, cfg, what = common.redesigned("kpn", 4, str(tmp_path))
    assert (path, rows[0]["step"], cfg, what) == (
        "experiments/weights/kpn-new-x4.msgpack", "100", {"epochs": 1}, "a new design")
    assert common.redesigned("kpn", 2, str(tmp_path)) is None  # not adopted at 2x
    assert common.redesigned("nsrr", 4, str(tmp_path)) is None
    # a factor's own weights: the 2x entry names others than the 4x one
    common.REDESIGNED["kpn"][2] = ("kpn-tuned", "tuned further")
    assert common.redesigned("kpn", 2, str(tmp_path)) is None  # kpn-tuned-x2 not exported
    for suffix in (".msgpack", "-training.csv", ".json"):
        (base / f"kpn-tuned-x2{suffix}").write_bytes((base / f"kpn-new-x2{suffix}").read_bytes())
    assert common.redesigned("kpn", 2, str(tmp_path))[::3] == (
        "experiments/weights/kpn-tuned-x2.msgpack", "tuned further")


@pytest.mark.parametrize("factor", [4, 2])
def test_adopted_redesigns_load_as_the_model_they_were_trained_as(factor):
    """Every ``REDESIGNED`` entry's exported weights exist at each factor it was adopted
    at and load with their run config into the model they name, its config overrides
    included (the parameter tree equals a fresh ``init``'s, shape for shape), so the
    table scores what was trained."""
    common = seqdata.load_script("common")
    for model, adopted in common.REDESIGNED.items():
        if factor not in adopted:
            continue
        name = adopted[factor][0]
        path, rows, _, _ = common.redesigned(model, factor)
        params, cfg = loading.load_params(os.path.join(common.ROOT, path))
        assert (cfg.model, cfg.factor) == (model, factor) and rows
        fresh = recipe.model_for(cfg).init(jax.random.PRNGKey(0))
        shapes = lambda t: jax.tree_util.tree_map(np.shape, t)  # noqa: E731
        assert shapes(params) == shapes(fresh), name


def test_comparison_table_systems_and_targets():
    """experiments/comparison_table.py: every system is listed at both factors with a
    spec that loads (or none, when it has no training on the diverse data), and the
    targets' margins and verdicts follow their thresholds."""
    ct = seqdata.load_script("comparison_table")
    for f in (4, 2):
        rows = ct.systems(f)
        game = [lab for lab in ct.DLCTUS_RUNS if ct.dlctus_run(f, lab)]
        assert [r[0] for r in rows] == ["jau", "tus", "dlctus", *game, *ct.SYSTEMS]
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
                            "nsrr": psnr(27.5), "thesis": psnr(29.75)},
                 "external": {"dlctus": psnr(22.0), "tus": psnr(22.5), "jau": psnr(21.0)}},
           "2": {"handmade": {"dlctus": psnr(33.4), "tus": psnr(32.0), "jau": psnr(31.0),
                              "mlp": psnr(31.5)}}}
    got = {what: (round(m, 6), ok) for what, m, ok in ct.targets(res)}
    assert got == {"DLCTUS - TUS >= 2.0 dB, random, 4x": (2.0, True),
                   "DLCTUS - TUS > 0, external, 4x": (-0.5, False),
                   "nsrr - JAU > 0, random, 4x": (0.5, True),
                   "DLCTUS - TUS >= 1.5 dB, handmade, 2x": (1.4, False),
                   "mlp - JAU > 0, handmade, 2x": (0.5, True),
                   "NSRR - TUS > 0, random, 4x": (-0.5, False),
                   "dlctus - thesis > 0, random, 4x": (0.25, True)}


def test_readme_figure_takes_the_best_trained_system_on_validation(tmp_path):
    """experiments/readme_figure.py's default comparison column: the trained system with
    the highest validation PSNR, never a baseline, at the weights the README table
    scores for it (an adopted redesign over the finished run); a clear error when none
    scored."""
    rf = seqdata.load_script("readme_figure")
    d = tmp_path / "docs" / "results" / "comparison-val" / "x4"
    d.mkdir(parents=True)
    scores = {"jau": 25.3, "tus": 25.4, "dlctus-shipped": 28.3, "mlp": 25.0, "nsrr": 27.1,
              "nsrr-fast": 27.0}
    (d / "results.json").write_text(json.dumps({"4": {k: {"psnr": v} for k, v in
                                                      scores.items()}}))
    assert rf.best_on_validation(4, str(tmp_path)) == "nsrr=experiments/weights/nsrr-x4.msgpack"
    name = seqdata.load_script("common").REDESIGNED["nsrr"][4][0]
    w = tmp_path / "experiments" / "weights"
    w.mkdir(parents=True)
    for suffix in (".msgpack", ".json", "-training.csv"):
        (w / f"{name}-x4{suffix}").write_text("{}" if suffix == ".json" else "epoch\n")
    assert rf.best_on_validation(4, str(tmp_path)) == f"nsrr=experiments/weights/{name}-x4.msgpack"
    (d / "results.json").write_text(json.dumps({"4": {"jau": {"psnr": 1.0}}}))
    with pytest.raises(ValueError, match="no comparison system scored"):
        rf.best_on_validation(4, str(tmp_path))


def test_training_summary_takes_the_longer_log(tmp_path):
    """A run's newest log is its longer one (file times mean nothing in a fresh clone);
    on a tie the exported (finished) one; logs of other data are not counted."""
    ts = seqdata.load_script("training_summary")

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


def test_comparison_table_only_rescores_the_named_systems(tmp_path, monkeypatch):
    """comparison_table.py --only: the named system is scored again, every other row is
    carried over from the earlier result with the command that scored it; a system
    without weights, or an earlier result of other factors, is refused."""
    import sys

    ct = seqdata.load_script("comparison_table")
    written = []
    monkeypatch.setattr(ct, "write", lambda name, table, data, note="": written.append(
        (table, data, note)))
    monkeypatch.setattr(ct, "RESULTS", str(tmp_path))

    def scorer(value):
        return lambda entries, fam, f, root: {e.label: {"psnr": value, "ssim": 0.5,
                                                        "temporal": 0.1} for e in entries}

    monkeypatch.setattr(ct, "score", scorer(20.0))
    # NSRR without any weights, whatever runs the repository holds at the time
    find, redesigned = ct.find, ct.redesigned
    monkeypatch.setattr(ct, "find", lambda m, f, root: None if m == "nsrr" else find(m, f, root))
    monkeypatch.setattr(ct, "redesigned", lambda m, f, root: None if m == "nsrr"
                        else redesigned(m, f, root))
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
    assert ("| dlctus | shipped (diverse; game and diverse half and half; both families' "
            "static holds) | 30.00 / 0.5000 / 0.10000 |") in table
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


def test_static_hold_fall_and_cycle_change():
    """experiments/static_hold.py: the fall is the best PSNR of the last 12 frames minus
    the last frame's (0 while a model keeps converging), the gain last minus first; the
    cycle change compares whole jitter cycles, so a periodic steady state reads 0 at any
    phase and a drift reads its size; holds too short for either are refused."""
    sh = seqdata.load_script("static_hold")
    curve = [20.0] * 12 + [21.0, 22.0, 23.0, 22.5] + [22.25] * 8
    assert sh.fall_and_gain(curve) == pytest.approx((0.75, 2.25))
    assert sh.fall_and_gain(np.linspace(20, 24, 24)) == pytest.approx((0.0, 4.0))
    assert sh.fall_and_gain([30.0] * 11 + [29.0] * 13)[0] == pytest.approx(0.0)
    # cycle change: a steady periodic ripple (the jitter cycle's steady state) reads 0,
    # whatever its phase at the end, where the fall reads the ripple
    ripple = 0.3 * np.sin(2 * np.pi * np.arange(64) / 16)
    for shift in range(16):
        change, rng_, last = sh.cycles(30.0 + np.roll(ripple, shift))
        assert change == pytest.approx(0.0, abs=1e-12) and last == pytest.approx(30.0)
        assert rng_ == pytest.approx(np.ptp(ripple))
    assert sh.fall_and_gain(30.0 + ripple)[0] > 0.4
    # a drift of 1 dB per cycle under the ripple reads -1
    down = 30.0 + ripple - np.arange(64) / 16
    assert sh.cycles(down)[0] == pytest.approx(-1.0)
    with pytest.raises(ValueError, match="two jitter cycles"):
        sh.cycles([1.0] * 31)
    with pytest.raises(ValueError, match="at least 12 frames"):
        sh.fall_and_gain([1.0] * 11)


def test_hold_dynamics_traces_the_step_that_evaluation_runs():
    """experiments/hold_dynamics.py: its frame-by-frame trace of a DLCTUS hold gives the
    PSNR jtus.evaluate gives for the same model and hold (float32 rounding, 1e-3 dB), a
    blend share and accumulation inside [0, 1]; the sharpness measure is the mean squared
    step between neighbours (1 for one-pixel stripes of 0 and 1, 0 for a flat image);
    whole jitter cycles are averaged."""
    import jax

    from jtus import evaluate
    from jtus.models import dlctus
    from jtus.sim import get_scene
    from jtus.sim.video import static_hold

    hd = seqdata.load_script("hold_dynamics")
    config = dlctus.Config(factor=4)
    model = dlctus.make(config)
    params = model.init(jax.random.PRNGKey(3))
    frames, targets = static_hold(get_scene("textures"), 32, 4, "thesis", 20, spp=4)
    t = hd.trace(params, config, frames, targets)
    ref = evaluate.video_metrics(model, params, *jax.tree_util.tree_map(
        jax.numpy.asarray, (frames, targets)), 4)["psnr"]
    np.testing.assert_allclose(t["psnr"], ref, atol=1e-3)
    assert (0 <= t["blend"]).all() and (t["blend"] <= 1).all()
    assert (0 <= t["acc"]).all() and (t["acc"] <= 1).all()
    stripes = np.broadcast_to((np.arange(8) % 2)[None, None, :, None], (1, 8, 8, 3))
    assert hd._energy(stripes) == 1.0 and hd._energy(np.ones((1, 8, 8, 3))) == 0.0
    np.testing.assert_allclose(hd.per_cycle(np.arange(40.0)), [7.5, 23.5])


def test_candidate_scores_table_marks_validation_and_test_columns():
    """experiments/candidate_scores.py: validation columns (which choose) are marked
    apart from the test families (which only report), one row per model."""
    cs = seqdata.load_script("candidate_scores")
    res = {"diverse val": {"a": 30.0, "b": 30.5}, "game val": {"a": 40.0, "b": 39.0},
           "random": {"a": 28.123, "b": 28.0}}
    lines = cs.table(res).splitlines()
    assert lines[0] == ("| model | diverse val (validation) | game val (validation) | "
                        "random (test) |")
    assert lines[2:] == ["| a | 30.00 | 40.00 | 28.12 |", "| b | 30.50 | 39.00 | 28.00 |"]


def test_inference_bound_splits_a_frame_into_network_floor_and_rest():
    """experiments/inference_bound.py: the target is PyTorch's time over the ratio, the
    network's floor its FLOPs at the measured convolution peak, the rest the frame minus
    the network; rows without a PyTorch time or of other models are skipped."""
    ib = seqdata.load_script("inference_bound")
    report = {"peak": {"conv_dlctus_gflops": 100.0}, "infer": [
        {"model": "dlctus", "size": "8x8", "factor": 4, "gflop": 5.0, "ms": 90.0,
         "network_ms": 60.0, "torch_ms": 120.0},
        {"model": "dlctus", "size": "8x8", "factor": 2, "gflop": 5.0, "ms": 90.0,
         "network_ms": 60.0, "torch_ms": None},
        {"model": "kpn", "size": "8x8", "factor": 4, "gflop": 5.0, "ms": 9.0,
         "network_ms": 6.0, "torch_ms": 12.0}]}
    (row,) = ib.bounds(report, 1.5)
    assert row["target_ms"] == pytest.approx(80.0)
    assert row["network_floor_ms"] == pytest.approx(50.0)
    assert row["rest_ms"] == pytest.approx(30.0)
    assert row["at_peak_ms"] == pytest.approx(80.0)


def test_trunk_in_bands_of_rows_is_the_trunk(monkeypatch):
    """experiments/trunk_strips.py times the band trunk and the trunk in output-channel
    groups only after checking them against the XLA trunk in float64 (SAME and VALID
    bands): the check passes, and it stops the run when one band row or one channel is
    off by 1e-9."""
    ts = seqdata.load_script("trunk_strips")
    weights = kernels.stack_blocks(dlctus.init(jax.random.PRNGKey(0)), 4)
    ts.check(weights, [3], [2, 4])
    right = ts.trunk_bands
    monkeypatch.setattr(ts, "trunk_bands",
                        lambda *a: right(*a).at[:, 17].add(1e-9))
    with pytest.raises(SystemExit, match="2 bands .* differ from the trunk"):
        ts.check(weights, [2])
    monkeypatch.setattr(ts, "trunk_bands", right)
    parts = ts.trunk_parts
    monkeypatch.setattr(ts, "trunk_parts", lambda *a: parts(*a).at[..., 20].add(1e-9))
    with pytest.raises(SystemExit, match="4 channel groups differ from the trunk"):
        ts.check(weights, [], [4])


def test_winograd_trunk_is_the_trunk(monkeypatch):
    """experiments/trunk_winograd.py times the Winograd trunks only after checking them
    against the XLA trunk in float64 on a map no tile divides: the check passes for
    F(2x2) and F(4x4), and it stops the run when one tile's output is off by 1e-9."""
    tw = seqdata.load_script("trunk_winograd")
    weights = kernels.stack_blocks(dlctus.init(jax.random.PRNGKey(0)), 1)
    tw.check(weights, [2, 4])
    right = tw.conv_winograd
    monkeypatch.setattr(tw, "conv_winograd", lambda *a: right(*a).at[:, 4:8, 4:8].add(1e-9))
    with pytest.raises(SystemExit, match=r"F\(4x4, 3x3\) differs from the trunk"):
        tw.check(weights, [4])


def test_scan_residuals_sums_the_buffers_the_scan_stacks():
    """experiments/scan_residuals.py reads ``print_saved_residuals``'s lines: bytes from
    dtype and shape, and only the scan's outputs counted as stacked over the frames."""
    sr = seqdata.load_script("scan_residuals")
    text = ("f32[3,3,32,32] from the argument p\n"
            "bool[8,4,32,32,32] output of scan from rollout.py:160:11 (_segment)\n"
            "f32[8,4,34,34,32] output of scan from rollout.py:160:11 (_segment)\n"
            "f32[] from a literal\n")
    rows = sr.parse(text)
    assert [r[2] for r in rows] == [4 * 9 * 32 * 32, 8 * 4 * 32 ** 3, 4 * 8 * 4 * 34 * 34 * 32, 4]
    assert [r[1] for r in sr.stacked(rows)] == [(8, 4, 32, 32, 32), (8, 4, 34, 34, 32)]
    assert "2 buffers" in sr.table(rows, 8)


def test_recomputed_edges_stack_fewer_bytes_per_frame():
    """With DLCTUS's down-sampling and output construction recomputed (``remat_edges``),
    a training window's scan stacks fewer residual bytes than when it keeps them
    (experiments/scan_residuals.py on a small window)."""
    sr = seqdata.load_script("scan_residuals")
    kept, recomputed = (sum(r[2] for r in sr.stacked(sr.residuals(4, 32, 1, 2, remat)))
                        for remat in (False, True))
    assert 0 < recomputed < 0.8 * kept


def test_interpolated_weights_lie_on_the_line_between_two_checkpoints():
    """experiments/interpolate_weights.py: alpha 0 and 1 give the two checkpoints, 0.5
    their mean leaf by leaf; different trees, shapes or an alpha outside [0, 1] are
    refused naming what differs."""
    iw = seqdata.load_script("interpolate_weights")
    a = {"w": np.arange(6.0).reshape(2, 3), "b": np.ones(3)}
    b = {"w": np.full((2, 3), 10.0), "b": np.zeros(3)}
    np.testing.assert_array_equal(iw.interpolate(a, b, 0.0)["w"], a["w"])
    np.testing.assert_array_equal(iw.interpolate(a, b, 1.0)["b"], b["b"])
    np.testing.assert_allclose(iw.interpolate(a, b, 0.5)["w"], (a["w"] + 10.0) / 2, rtol=0)
    with pytest.raises(ValueError, match="alpha"):
        iw.interpolate(a, b, 1.5)
    with pytest.raises(ValueError, match="different parameters"):
        iw.interpolate(a, {"w": b["w"]}, 0.5)
    with pytest.raises(ValueError, match=r"\['b'\] has shape \(3,\)"):
        iw.interpolate(a, {"w": b["w"], "b": np.zeros(4)}, 0.5)


@pytest.mark.parametrize("name,overrides", [
    ("kpn", (("current", "samples"), ("history", "clamped"))), ("nsrr-fast", ())])
def test_checkpoint_switched_to_normalized_exposure_keeps_its_outputs(tmp_path, name,
                                                                      overrides):
    """experiments/exposure_normalize.py writes a checkpoint (a samples KPN; NSRR-fast)
    fed exposure-normalized colour, with ``exposure`` in its config and the source's
    per-epoch log beside it, that computes over 3 frames whose mean colour is
    ``--mean`` what the original computes (the weights reading colour times the mean,
    NSRR's output layer divided by it); a normalized
    checkpoint, another model's, or a mean that is not positive is refused by name,
    and nothing is written."""
    from jtus import rollout
    from jtus.config import Config

    ks = seqdata.load_script("exposure_normalize")
    cfg = Config(model=name, factor=2, model_overrides=overrides)
    original = recipe.model_for(cfg)
    params = original.init(jax.random.PRNGKey(0))
    (tmp_path / "log.csv").write_text("epoch,step,seconds\n1,100,5.0\n")
    src = checkpoint.write_params(str(tmp_path / name), params, config_mod.to_json(cfg),
                                  str(tmp_path / "log.csv"))
    frames, _ = seqdata.sequence(T=3, B=1, h=8, w=8, factor=2, seed=3, max_motion=1.0)
    mean = 0.2
    frames = frames._replace(color=frames.color * mean
                             / frames.color.mean(axis=(2, 3, 4), keepdims=True))
    jf = seqdata.to_jax(frames)
    ks.main([src, "--mean", repr(mean), "--out", str(tmp_path / "norm")])
    norm, ncfg = loading.load_params(str(tmp_path / "norm.msgpack"))
    assert dict(ncfg.model_overrides) == {**dict(overrides), "exposure": "normalized"}
    # the source's per-epoch log travels, so a training budget counts the runs before
    assert (tmp_path / "norm-training.csv").read_text() == (tmp_path / "log.csv").read_text()
    model = recipe.model_for(ncfg)
    want, _ = rollout.outputs(original.step, params, rollout.first_state(original, jf), jf)
    got, _ = rollout.outputs(model.step, norm, rollout.first_state(model, jf), jf)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-6)
    assert np.abs(np.asarray(want)).max() > 1e-2  # not a comparison of zeros
    with pytest.raises(SystemExit, match="exposure is already normalized"):
        ks.main([str(tmp_path / "norm.msgpack"), "--out", str(tmp_path / "again")])
    with pytest.raises(SystemExit, match="mean: expected a positive mean colour, got 0.0"):
        ks.main([src, "--mean", "0", "--out", str(tmp_path / "zero")])
    from jtus.models import mlp
    other = checkpoint.write_params(str(tmp_path / "mlp"), mlp.init(
        jax.random.PRNGKey(0), mlp.Config(factor=2)), config_mod.to_json(
        Config(model="mlp", factor=2)))
    with pytest.raises(SystemExit, match=r"expected a checkpoint of one of \('kpn', 'nsrr', "
                                         r"'nsrr-fast'\), got mlp"):
        ks.main([other, "--out", str(tmp_path / "no")])
    assert not any((tmp_path / f"{n}.msgpack").exists() for n in ("again", "zero", "no"))


def test_replayed_first_epoch_takes_the_logged_steps(tiny_data, tmp_path):
    """experiments/replay_steps.py redraws a run's first-epoch crops from its starting
    weights: the replayed gradient norms' mean and maximum equal the epoch log's, and
    a spike is picked out against the median."""
    rs = seqdata.load_script("replay_steps")
    config = dataclasses.replace(PRESETS["tiny"], dataset=tiny_data, epochs=1,
                                 steps_per_epoch=3)
    train.train_and_evaluate(config, tmp_path / "run", progress=False)
    with open(tmp_path / "run" / "metrics.json") as fh:
        logged = json.load(fh)[0]
    rows = rs.replay(str(tmp_path / "run"))
    norms = [r[2] for r in rows]
    assert len(rows) == 3
    np.testing.assert_allclose(max(norms), logged["grad_norm_max"], rtol=1e-6)
    np.testing.assert_allclose(np.mean(norms), logged["grad_norm"], rtol=1e-6)
    frozen = rs.replay(str(tmp_path / "run"), frozen=True)
    assert frozen[0] == rows[0] and frozen[1][2] != rows[1][2]  # no update: step 2 differs
    big, median = rs.spikes([(1, 0.0, 1.0), (2, 0.0, 2.0), (3, 0.0, 500.0)], 100.0)
    assert median == 2.0 and [r[0] for r in big] == [3]


def test_exported_fine_tune_names_the_exported_weights_it_started_from(tmp_path):
    """``loading.export_params(..., init_from=)``: the exported config names the given
    weights as the run's start when they hold the parameters the run started from;
    weights that differ, or that do not exist, are refused by name before anything is
    written."""
    from jtus.config import Config
    from jtus.models import kpn

    start = kpn.init(jax.random.PRNGKey(0), kpn.Config(factor=2))
    other = kpn.init(jax.random.PRNGKey(1), kpn.Config(factor=2))
    cfg = Config(model="kpn", factor=2)
    started = checkpoint.write_params(str(tmp_path / "runs-start"), start,
                                      config_mod.to_json(cfg))
    same = checkpoint.write_params(str(tmp_path / "exported"), start, config_mod.to_json(cfg))
    differs = checkpoint.write_params(str(tmp_path / "differs"), other,
                                      config_mod.to_json(cfg))
    run = tmp_path / "run"
    run.mkdir()
    checkpoint.write_params(str(run / "checkpoint"), other, config_mod.to_json(
        dataclasses.replace(cfg, init_from=started)))
    loading.export_params(str(run), str(tmp_path / "out"), init_from=same)
    assert loading.load_params(str(tmp_path / "out.msgpack"))[1].init_from == same
    with pytest.raises(ValueError, match="does not hold the parameters the run started"):
        loading.export_params(str(run), str(tmp_path / "bad"), init_from=differs)
    with pytest.raises(FileNotFoundError, match="init_from: .*nowhere.msgpack: no such"):
        loading.export_params(str(run), str(tmp_path / "bad"),
                              init_from=str(tmp_path / "nowhere.msgpack"))
    assert not (tmp_path / "bad.json").exists()


def test_fine_tune_that_changes_the_model_design_says_so(tmp_path, capsys):
    """``loading.init_params``: starting from weights trained with another model design
    (here NSRR-fast switched to exposure-normalized colour, started without the
    override) prints a note naming each changed field; the same design prints none."""
    from jtus.config import Config
    from jtus.models import nsrr

    normalized = (("exposure", "normalized"),)
    cfg = Config(model="nsrr-fast", factor=2, model_overrides=normalized)
    src = checkpoint.write_params(str(tmp_path / "norm"), nsrr.init(
        jax.random.PRNGKey(0), nsrr.Config(factor=2, fast=True, exposure="normalized")),
        config_mod.to_json(cfg))
    loading.init_params(dataclasses.replace(cfg, init_from=src))
    assert capsys.readouterr().err == ""
    loading.init_params(Config(model="nsrr-fast", factor=2, init_from=src))
    assert (f"note: init_from: {src} was trained with another design than this run's "
            "model (exposure: 'normalized' -> 'absolute'); --model-override sets this "
            "run's" in capsys.readouterr().err)


def test_blend_scale_probe_is_the_model_at_one_and_keeps_the_history_at_zero(rng):
    """experiments/blend_scale.py's DLCTUS with o1 scaled by c: c = 1 gives the model's own
    step (outputs and history, 1e-6); c -> 0 keeps the reprojected history's colour (a
    still frame: the previous output) while the accumulation channel still takes o2."""
    bs = seqdata.load_script("blend_scale")
    model = dlctus.make(dlctus.Config(factor=2))
    params = model.init(jax.random.PRNGKey(1))
    entry = loading.Entry("m", model, params, "dlctus")
    frame = seqdata.frame_with_motion(np.zeros((1, 8, 8, 2), np.float32))._replace(
        color=jax.numpy.asarray(rng.uniform(size=(1, 8, 8, 3)), jax.numpy.float32),
        jitter=jax.numpy.asarray([[0.3, 0.7]], jax.numpy.float32))
    state = model.init_state(frame)
    state = dlctus.State(state.history.at[..., :3].set(
        jax.numpy.asarray(rng.uniform(size=(1, 16, 16, 3)), jax.numpy.float32)))
    want_out, want_state = model.step(params, state, frame)
    got_out, got_state = bs.scaled_entry(entry, 1.0).model.step(params, state, frame)
    np.testing.assert_allclose(got_out, want_out, atol=1e-6)
    np.testing.assert_allclose(got_state.history, want_state.history, atol=1e-6)
    out0, _ = bs.scaled_entry(entry, 1e-9).model.step(params, state, frame)
    np.testing.assert_allclose(out0, state.history[..., :3], atol=1e-6)
    assert float(np.abs(np.asarray(want_out) - np.asarray(state.history[..., :3])).max()) > 1e-3


@pytest.mark.long
def test_donated_residual_pullbacks_give_autodiffs_gradients():
    """experiments/donated_residuals.py: a window whose per-frame pullbacks are rebuilt
    from donated buffers gives the gradients of ``jax.value_and_grad`` of
    ``rollout.window_loss``, and each timed variant runs again after its first call (the
    donated buffers handed back each step)."""
    dr = seqdata.load_script("donated_residuals")
    variants, mib, diff = dr.window(4, 16, 1, 2)
    assert diff <= 1e-7 and mib > 0
    assert set(variants) == {"autodiff", "pullbacks, donated", "pullbacks, fresh"}
    for fn in variants.values():
        fn()


def test_scan_and_loop_of_a_video_time_the_same_outputs():
    """experiments/scan_vs_loop.py: a model's video as one scan and as its step looped
    from Python gives the same outputs up to float32 rounding (compared inside
    ``per_frame``) and a time per frame for each."""
    script = seqdata.load_script("scan_vs_loop")
    frames, _ = seqdata.sequence(T=3, B=1, h=8, w=8, factor=4, seed=0)
    frames = seqdata.to_jax(frames)
    scan, loop, diff = script.per_frame("tus", frames, 1)
    assert scan > 0 and loop > 0 and diff <= 1e-6
