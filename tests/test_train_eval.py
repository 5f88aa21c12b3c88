"""End to end in seconds: train -> checkpoint -> resume -> evaluate -> upsample."""

import dataclasses
import json
import os
import re
import shutil

import h5py
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from jtus import evaluate, loading, losses, rollout, train, upsample
from jtus.config import PRESETS
from jtus.files import UnknownKeyWarning
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
                       (["--overwrite", "--seed", "-1"], "seed: expected an integer"),
                       (["--overwrite", "--seed", "99999999999999999999999"], "seed"),
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
    # a damaged history is refused on --resume, naming the file; the checkpoint stays
    (work / "metrics.json").write_text("[{\"epoch\": 1,")
    ckpt = (work / "checkpoint.msgpack").read_bytes()
    capsys.readouterr()
    assert train.main(base[:-2] + ["--epochs", "2", "--lr", "0.002", "--resume"]) == 2
    assert "metrics.json: not valid JSON" in capsys.readouterr().err
    assert (work / "checkpoint.msgpack").read_bytes() == ckpt


def test_non_finite_data_stops_training_without_a_checkpoint(tiny_data, tmp_path):
    """NaN colour in the training split: the crops that read it are refused, naming the
    videos and the field, before any step; no checkpoint is written."""
    import shutil

    import h5py

    bad = tmp_path / "nan.h5"
    shutil.copyfile(tiny_data, bad)
    with h5py.File(bad, "r+") as fh:
        for name in fh["train"]:
            fh[f"train/{name}/x4/color"][...] = np.nan
    with pytest.raises(ValueError, match=r"train crops of .*color has \d+ values NaN"):
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
    with pytest.warns(UnknownKeyWarning, match=r"p.json: unknown config key 'colour' ignored"):
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


def test_mixed_datasets_share_each_batch(tiny_data, tmp_path):
    """``mix_dataset``: the last ``round(batch * mix_fraction)`` crops of each batch (at
    least one from each dataset) come from the second dataset's training videos;
    validation stays on ``dataset``; a missing or unfit second dataset and a fraction
    outside (0, 1) are refused before anything is written."""
    import shutil

    import h5py

    from jtus import recipe
    from jtus.data.dataset import Dataset

    mix = tmp_path / "mix.h5"
    shutil.copy(tiny_data, mix)
    with h5py.File(mix, "a") as fh:
        for name in list(fh["train"]):
            fh.move(f"train/{name}", f"train/mixed_{name}")
    config = _config(tiny_data, epochs=1, batch=4, mix_dataset=str(mix), mix_fraction=0.5)
    assert [recipe.mix_count(dataclasses.replace(config, mix_fraction=f), b)
            for f, b in ((0.5, 4), (0.25, 4), (0.9, 2), (0.1, 2))] == [2, 1, 1, 1]
    with Dataset(tiny_data) as ds, Dataset(str(mix)) as mx:
        frames, targets, index = recipe.train_crops(config, ds, mx, 4,
                                                    np.random.default_rng(0))
    assert frames.color.shape[1] == targets.shape[1] == 4
    assert [i[0] for i in index] == [tiny_data] * 2 + [str(mix)] * 2
    assert all(i[1].startswith("mixed_") for i in index[2:])
    assert not any(i[1].startswith("mixed_") for i in index[:2])
    _, hist = train.train_and_evaluate(config, tmp_path / "run", progress=False)
    assert np.isfinite(hist[0]["train_loss"]) and np.isfinite(hist[0]["val_psnr"])
    with pytest.raises(ValueError, match="mix_dataset: .*nope.h5 does not exist"):
        train.train_and_evaluate(dataclasses.replace(config, mix_dataset=str(
            tmp_path / "nope.h5")), tmp_path / "other", progress=False)
    with pytest.raises(ValueError, match="crop: 64 exceeds"):
        recipe.check_data(dataclasses.replace(config, crop=64))
    assert not (tmp_path / "other").exists()
    with pytest.raises(ValueError, match="mix_fraction"):
        dataclasses.replace(config, mix_fraction=1.0)


def test_training_continues_holds_past_their_stored_length(tmp_path):
    """``extend_holds``: training on sequences longer than a held dataset's videos runs
    (each hold continued by its jitter period), as TBPTT windows and as one window as
    long as the sequence (then validation's windows are continued holds too), and
    without it the same config is refused before anything is written, naming the
    option."""
    from jtus import recipe
    from jtus.sim import generate

    p = dataclasses.replace(generate.preset("tiny"), splits={
        "train": (("camera_orbit",), 1, 13), "val": (("camera_orbit",), 1, 13),
        "test": ((), 1, 1)}, jitters=("halton8",), hold_from=5)
    data = tmp_path / "holds.h5"
    generate.generate(p, data, progress=False)
    config = _config(str(data), epochs=1, steps_per_epoch=2, seq_len=24, mode="tbptt",
                     k1=8, k2=8, val_batches=1, val_videos=1, extend_holds=True)
    for k in (8, 24):
        c = dataclasses.replace(config, k1=k, k2=k)
        _, hist = train.train_and_evaluate(c, tmp_path / f"run{k}", progress=False)
        assert np.isfinite(hist[0]["train_loss"]) and np.isfinite(hist[0]["val_psnr"])
    with pytest.raises(ValueError, match="shortest train video.*13 frames.*extend-holds"):
        recipe.check_data(dataclasses.replace(config, extend_holds=False))
    with pytest.raises(ValueError, match="not even with its hold continued"):
        recipe.check_data(dataclasses.replace(config, seq_len=24, extend_holds=True,
                                              dataset=str(_short_hold(tmp_path))))


def _short_hold(tmp_path):
    """A held dataset whose hold (4 frames) is shorter than its jitter period (8)."""
    from jtus.sim import generate

    p = dataclasses.replace(generate.preset("tiny"), splits={
        "train": (("camera_orbit",), 1, 9), "val": (("camera_orbit",), 1, 9),
        "test": ((), 1, 1)}, jitters=("halton8",), hold_from=5)
    generate.generate(p, tmp_path / "short.h5", progress=False)
    return tmp_path / "short.h5"


def test_temporal_from_weighs_the_temporal_term_from_a_frame_on(tiny_data, tmp_path,
                                                               monkeypatch):
    """``temporal_from``: the run's optimizer steps score frames from it on with the
    temporal weight and earlier frames with weight 1; it is refused without a weighted
    temporal loss, with weight 1, with several windows per sequence, or past the
    sequence; an alternate keeps it only with a loss that has a temporal term."""
    from jtus import recipe

    config = _config(tiny_data, epochs=1, steps_per_epoch=1, loss="log-salvi",
                     temporal_weight=3.0, temporal_from=2)
    rng = np.random.default_rng(0)
    args = [jnp.asarray(rng.uniform(size=(2, 8, 8, 3)), jnp.float32) for _ in range(4)]
    # LR motion of a still 8x8 frame at 4x
    args += [jnp.asarray(True), seqdata.frame_with_motion(jnp.zeros((2, 2, 2, 2)))]
    k, late = recipe.late_loss_for(config)
    assert k == 2
    np.testing.assert_allclose(late(*args), losses.make("log-salvi", 4, temporal_weight=3.0)(
        *args), rtol=1e-6)
    np.testing.assert_allclose(recipe.loss_for(config)(*args),
                               losses.make("log-salvi", 4)(*args), rtol=1e-6)
    assert abs(float(late(*args)) - float(recipe.loss_for(config)(*args))) > 0.1
    assert recipe.late_loss_for(dataclasses.replace(config, temporal_from=0)) is None
    built = []
    real = train.make_train_step

    def spy(*a, late=None, **kw):
        built.append(None if late is None else late[0])
        return real(*a, late=late, **kw)

    monkeypatch.setattr(train, "make_train_step", spy)
    scored, real_window_loss = [], rollout.window_loss

    def window_spy(*a, late=None, **kw):  # the training step's and the validation's
        scored.append(None if late is None else late[0])
        return real_window_loss(*a, late=late, **kw)

    monkeypatch.setattr(rollout, "window_loss", window_spy)
    _, hist = train.train_and_evaluate(config, tmp_path / "run", progress=False)
    assert built == [2] and np.isfinite(hist[0]["train_loss"])
    assert len(scored) >= 2 and set(scored) == {2}, scored
    for kw, msg in (({"temporal_from": -1}, "temporal_from: expected an integer >= 0"),
                    ({"loss": "l1", "temporal_weight": 1.0}, "temporal_from: 2 moves"),
                    ({"temporal_weight": 1.0}, "temporal_from: 2 moves"),
                    ({"temporal_from": 4}, "temporal_from: expected a frame before seq_len=4"),
                    ({"mode": "tbptt", "k1": 2, "k2": 2},
                     r"temporal_from: needs one window per sequence .* k1=2, k2=2, seq_len=4")):
        with pytest.raises(ValueError, match=msg):
            dataclasses.replace(config, **kw)
    monkeypatch.setitem(PRESETS, "alt-long", dataclasses.replace(PRESETS["tiny"], seq_len=6))
    alt = dataclasses.replace(config, alternate="alt-long")
    assert recipe.alternate_config(alt).temporal_from == 2
    alt = dataclasses.replace(alt, alternate_loss="log-mse")
    assert recipe.alternate_config(alt).temporal_from == 0


def test_alternate_preset_gives_every_second_sequence(tiny_data, tmp_path, monkeypatch):
    """``alternate``: sequences 1, 3, ... follow the run's own data and windows, 2, 4, ...
    the alternate preset's (another length, another window plan), with the loss
    ``alternate_loss`` where one is named; the optimizer's schedule counts both kinds of
    step; an unknown or self-alternating preset, an unknown alternate loss or one without
    an alternate preset, or a temporal weight with no loss that has a temporal term, are
    refused before anything is written; the weight stays with the loss that has one."""
    from jtus import recipe

    monkeypatch.setitem(PRESETS, "alt-test", dataclasses.replace(
        PRESETS["tiny"], dataset=tiny_data, seq_len=6, mode="tbptt", k1=3, k2=3))
    config = _config(tiny_data, epochs=1, steps_per_epoch=4, alternate="alt-test",
                     alternate_loss="log-salvi")
    drawn, made = [], []
    real, real_loss = recipe.training_sequence, recipe.loss_for

    def spy(cfg, *a, **kw):
        out = real(cfg, *a, **kw)
        drawn.append((cfg.seq_len, cfg.mode, out[1].shape[0]))
        return out

    def spy_loss(cfg):
        made.append((cfg.seq_len, cfg.loss))
        return real_loss(cfg)

    monkeypatch.setattr(recipe, "training_sequence", spy)
    monkeypatch.setattr(recipe, "loss_for", spy_loss)
    _, hist = train.train_and_evaluate(config, tmp_path / "run", progress=False)
    assert drawn == [(4, "bptt", 4), (6, "tbptt", 6)] * 2
    assert made == [(4, "l1"), (6, "log-salvi")]  # the run's own steps and validation: l1
    assert recipe.alternate_config(dataclasses.replace(config, alternate_loss="")).loss == "l1"
    # two BPTT windows (one step each) and two sequences of two TBPTT windows
    assert hist[0]["step"] == recipe.steps_per_epoch(config) == 2 * 1 + 2 * 2
    assert np.isfinite(hist[0]["train_loss"]) and np.isfinite(hist[0]["val_psnr"])
    assert recipe.alternate_config(config).crop == config.crop
    monkeypatch.setitem(PRESETS, "alt-loop", dataclasses.replace(config, alternate="tiny"))
    for name, msg in (("nope", "alternate: unknown preset 'nope'"),
                      ("alt-loop", "alternate: preset 'alt-loop' alternates itself")):
        with pytest.raises(ValueError, match=msg):
            train.train_and_evaluate(dataclasses.replace(config, alternate=name),
                                     tmp_path / name, progress=False)
        assert not (tmp_path / name).exists()
    for kw, msg in (({"alternate_loss": "nope"}, "alternate_loss: expected '' or one of"),
                    ({"alternate": ""}, "alternate_loss: 'log-salvi' needs an alternate"),
                    ({"alternate_loss": "", "temporal_weight": 3.0},
                     "temporal_weight: 3.0 weighs the temporal term of salvi or log-salvi")):
        with pytest.raises(ValueError, match=msg):
            dataclasses.replace(config, **kw)
    # the temporal weight goes with the loss that weighs a temporal term, whichever it is
    weighted = dataclasses.replace(config, temporal_weight=3.0)
    assert recipe.alternate_config(weighted).temporal_weight == 3.0
    weighted = dataclasses.replace(weighted, loss="log-salvi", alternate_loss="log-mse")
    assert recipe.alternate_config(weighted).temporal_weight == 1.0


def test_training_on_data_without_a_test_split_skips_the_evaluation(tiny_data, tmp_path,
                                                                     capsys):
    """Training data with no test split (the holds presets') trains, says before
    training that no evaluation follows, and exits 0 without one."""
    data = tmp_path / "no-test.h5"
    shutil.copy(tiny_data, data)
    with h5py.File(data, "a") as fh:
        del fh["test"]
    work = tmp_path / "run"
    assert train.main(["--preset", "tiny", "--dataset", str(data), "--workdir", str(work),
                       "--epochs", "1", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert f"{data} has no test split: no evaluation after training" in err
    assert (work / "checkpoint.msgpack").exists() and not (work / "eval").exists()
