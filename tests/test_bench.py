"""A smoke test of ``python -m jtus.bench`` (timings are measured, not asserted)."""

import json
import os

import pytest

from jtus import bench, cost, hostmem, models
from jtus.bench import __main__ as bench_cli


@pytest.mark.long
def test_bench_smoke(capsys, tmp_path):
    out = tmp_path / "new" / "bench.json"  # its folder is created
    assert bench_cli.main(["--sizes", "64", "--factors", "4", "--repeats", "1", "--models",
                           "dlctus", "jau", "tus", "kpn", "--train-models", "dlctus", "mlp",
                           "--train-crop", "16", "--train-seq", "2", "--train-loss-frames", "1",
                           "--train-batch", "1", "--train-warps", "bicubic", "nearest", "--json",
                           "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert json.loads(out.read_text()) == report
    md = (tmp_path / "new" / "bench.md").read_text()
    assert md == bench.markdown(report) + "\n" and "| dlctus | 64x64 | 4x |" in md
    assert sorted(os.listdir(tmp_path / "new")) == ["bench.json", "bench.md"]
    assert report["hardware"]["cores"] >= 1
    assert report["host_memory"] == hostmem.state() and "Host memory: " in md
    assert {r["model"] for r in report["infer"]} == {"dlctus", "jau", "tus", "kpn"}
    by = {r["model"]: r for r in report["infer"]}
    assert by["dlctus"]["ms"] > 0 and by["dlctus"]["network_ms"] > 0
    # beside its PyTorch reference where the model has one (Spec.torch_reference)
    assert "torch_over_jtus" in by["dlctus"] and "torch_over_jtus" in by["kpn"]
    assert "torch_over_jtus" not in by["tus"] and "network_ms" not in by["tus"]
    assert report["peak"]["matmul_gflops"] > 0
    tr = report["train"]
    assert [(r["model"], r["warp"]) for r in tr] == [("dlctus", "bicubic"),
                                                     ("dlctus", "nearest"), ("mlp", "-")]
    for r in tr:
        assert r["s_per_step"] > 0 and r["peak_mib"] > 0
        assert r["frames_per_s"] == r["batch"] * r["seq"] / r["s_per_step"]
    assert "torch_over_jtus" in tr[0] and "torch_over_jtus" not in tr[2]


def test_training_table_says_one_device_per_core_only_when_it_was():
    """The training table's note names the device split, and calls it one device per
    core only when the report's machine has as many cores as the step had devices."""
    row = {"model": "dlctus", "factor": 2, "crop": 128, "batch": 4, "seq": 8,
           "loss_frames": 8, "unroll": False, "remat": False, "conv_backward": "custom",
           "warp": "bicubic", "kernels": "xla", "s_per_step": 0.2, "frames_per_s": 160.0}

    def note(devices, cores):
        report = {"hardware": {"cpu": "x", "cores": cores, "jax": "0", "backend": "cpu"},
                  "command": "python -m jtus.bench", "host_memory": "kept",
                  "train": [dict(row, devices=devices)]}
        return bench.markdown(report)

    assert "split over 2 XLA CPU devices (one per core)" in note(2, 2)
    assert "split over 4 XLA CPU devices." in note(4, 2)
    assert "one XLA device" in note(1, 2) and "split over" not in note(1, 2)


def test_interrupted_bench_keeps_the_rows_it_measured(tmp_path, monkeypatch):
    """The report on disk grows row by row: a run stopped in its second measurement
    (a time limit on a lent GPU, Ctrl-C) leaves the first row and its table."""
    calls = []

    def fake_infer(name, factor, size, repeats, dtype="float32", reference=True, **over):
        if calls:
            raise KeyboardInterrupt
        calls.append(name)
        return {"model": name, "size": f"{size[0]}x{size[1]}", "factor": factor,
                "dtype": dtype, "ms": 1.5, "gflop": 1.0, "gflops": 1.0, "mbytes": 1.0}

    monkeypatch.setattr(bench_cli, "bench_infer", fake_infer)
    out = tmp_path / "bench.json"
    with pytest.raises(KeyboardInterrupt):
        bench_cli.main(["--what", "infer", "--models", "jau", "tus", "--sizes", "64",
                        "--factors", "4", "--out", str(out)])
    report = json.loads(out.read_text())
    assert [r["model"] for r in report["infer"]] == ["jau"]
    assert "| jau | 64x64 | 4x |" in (tmp_path / "bench.md").read_text()


def test_dlctus_flop_count():
    """The network's FLOPs: 4x4x8 -> 32 at 1/16 of the pixels, then 8 3x3 32->32 convs."""
    c = cost.cost("dlctus", models.build("dlctus", 4).config, 1080, 1920)
    n = 270 * 480
    assert c.network_flops == n * 32 * 128 * 2 + 8 * n * 32 * 32 * 9 * 2 + n * 32 * 4 * 3
    assert abs(c.network_flops / 1e9 - 20.22) < 0.01


def test_cost_table_lists_every_model(capsys):
    assert cost.main(["--factors", "4"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| ") and "4x" in line]
    assert [r.split(" | ")[0][2:] for r in rows] == list(models.NAMES)
    dl = [r for r in rows if r.startswith("| dlctus |")][0]
    assert "78,112" in dl and "20.68" in dl


@pytest.mark.long
def test_profile_attributes_a_training_step_to_its_stages(tmp_path, capsys):
    """``python -m jtus.profile`` finds the step's ops in the trace and names their stage
    and pass: the network runs forward and backward, the reprojection's image gradient
    is one scatter per frame segment, and the shares add up."""
    from jtus import profile

    out = tmp_path / "p"
    assert profile.main(["--factor", "4", "--crop", "32", "--batch", "1", "--seq", "3",
                         "--loss-frames", "2", "--steps", "1", "--out", str(out)]) == 0
    assert "| network |" in capsys.readouterr().out
    report = json.loads((tmp_path / "p.json").read_text())
    s = report["summary"]
    assert s["stage_pass"]["network/forward"] > 0 and s["stage_pass"]["network/backward"] > 0
    assert s["stage_pass"]["reprojection/forward"] > 0
    assert s["kind"]["scatter"] > 0 and s["kind"]["convolution"] > 0
    assert abs(sum(s["stage"].values()) - s["op_ms_per_step"]) < 1e-6 * s["op_ms_per_step"]
    assert abs(sum(s["pass"].values()) - s["op_ms_per_step"]) < 1e-6 * s["op_ms_per_step"]
    assert (tmp_path / "p.md").read_text().startswith("Profile of the DLCTUS 4x training step")


def test_profile_classifies_ops_by_their_jax_origin():
    from jtus.profile import classify, hlo_ops

    text = ('  %ynn_fusion.3 = f32[4,34,34,32]{3,2,1,0} fusion(%a, %b), kind=kCustom, '
            'metadata={op_name="jit(train_step)/jvp()/while/body/closed_call/network/'
            'conv_general_dilated" stack_frame_id=3}\n'
            '  ROOT %wrapped_scatter.2 = f32[65536,4]{1,0} fusion(%c), kind=kLoop, metadata='
            '{op_name="jit(train_step)/transpose(jvp())/while/body/closed_call/reprojection/'
            'scatter-add"}\n')
    ops = hlo_ops(text)
    assert classify("ynn_fusion.3", *ops["ynn_fusion.3"]) == ("network", "forward", "convolution")
    assert classify("wrapped_scatter.2", *ops["wrapped_scatter.2"]) == (
        "reprojection", "backward", "scatter")
    assert classify("copy.7", "copy", "") == ("other", "forward", "copy/slice")
    # a split step's gradient exchange (its span holds the wait for the other devices)
    assert classify("all-reduce.9", "all-reduce", "jit(train_step)/shard_map/psum") == (
        "other", "forward", "collective")


def test_profile_names_a_scans_buffer_fills_and_residual_writes():
    """A scan's stacked outputs start as buffers filled from a broadcast (a copy of it per
    buffer) and are written one frame at a time by dynamic-update-slices in the loop
    body: the profile files these as ``fill`` and ``stacking``, not as compute."""
    from jtus.profile import classify, hlo_ops

    text = ('  %wrapped_broadcast.27 = f32[5,4,34,34,32]{4,3,2,1,0} fusion(%constant.1), '
            'kind=kLoop, calls=%wrapped_broadcast_computation.27\n'
            '  %copy.12 = f32[5,4,34,34,32]{4,3,2,1,0} copy(%wrapped_broadcast.27)\n'
            '  %copy.13 = f32[4,32]{1,0} copy(%transpose.2), metadata={op_name="jit(f)/x"}\n'
            '  %bitcast_dynamic-update-slice_fusion.5 = f32[5,4,34,34,32]{4,3,2,1,0} '
            'fusion(%copy.12, %p.1, %i.2), kind=kLoop, metadata={op_name="jit(train_step)/'
            'jvp()/while/body/jit(dynamic_update_index_in_dim)/dynamic_update_slice"}\n')
    ops = hlo_ops(text)
    assert ops["copy.12"] == ("copy", "", "wrapped_broadcast.27")
    assert classify("wrapped_broadcast.27", *ops["wrapped_broadcast.27"])[2] == "fill"
    assert classify("copy.12", *ops["copy.12"])[2] == "fill"
    assert classify("copy.13", *ops["copy.13"])[2] == "copy/slice"
    name = "bitcast_dynamic-update-slice_fusion.5"
    assert classify(name, *ops[name]) == ("other", "forward", "stacking")


@pytest.mark.long
def test_bench_train_preset_sets_the_recipe_workload(capsys):
    from jtus import config, recipe
    assert bench_cli.main(["--what", "train", "--train-models", "dlctus", "--train-preset",
                           "tiny", "--factors", "4", "--repeats", "1", "--no-torch",
                           "--json"]) == 0
    tr = json.loads(capsys.readouterr().out)["train"][0]
    cfg = config.PRESETS["tiny"]
    plan = recipe.plan(cfg)
    assert (tr["crop"], tr["batch"], tr["seq"], tr["loss_frames"]) == (
        cfg.crop, cfg.batch, plan.window, plan.loss_frames)
    with pytest.raises(SystemExit):
        bench_cli.main(["--what", "train", "--train-preset", "nope", "--no-torch"])
    assert "--train-preset: invalid choice" in capsys.readouterr().err


@pytest.mark.parametrize("name", [n for n in models.NAMES
                                  if models.spec(n).stages and n != "dlctus"])
def test_each_model_labels_the_stages_the_profile_files_its_ops_under(name):
    """Every stage a model declares (``Spec.stages``) is a named scope in its step's HLO,
    and nearly every op is in one: ``python -m jtus.profile --model NAME`` then splits
    the step by stage rather than filing it under "other". DLCTUS's own labels are
    checked op by op in ``tests/test_rollout.py``."""
    import re

    import jax

    from jtus import profile
    from jtus.bench.workloads import random_frame

    model = models.build(name, 2)
    params = model.init(jax.random.PRNGKey(0))
    frame = random_frame(8, 8)
    state = model.init_state(frame)
    hlo = jax.jit(model.step).lower(params, state, frame).as_text(dialect="hlo",
                                                                  debug_info=True)
    for stage in models.spec(name).stages:
        assert f"/{stage}/" in hlo, stage
    ops = re.findall(r'op_name="(jit\([^"]*)"', hlo)
    stages = profile.stages_of(name)
    outside = [op for op in ops if profile.classify("", "", op, stages=stages)[0] == "other"]
    assert len(ops) > 20 and len(outside) <= 0.05 * len(ops), sorted(set(outside))
    # control: the same ops filed under another model's stages miss most of them
    if set(stages) - set(profile.stages_of("dlctus")):
        assert sum(profile.classify("", "", op)[0] == "other" for op in ops) > len(outside)


def test_profile_markdown_lists_the_models_stages_and_its_largest_ops():
    """The report's markdown has a row per stage the model declared (in its order, then
    "other") and the largest single ops with the JAX operation that made each."""
    from jtus import profile

    top = [dict(ms=3.0, op="fusion.1", stage="reconstruction", pass_="forward",
                kind="convolution",
                op_name="jit(f)/while/body/reconstruction/conv_general_dilated")]
    report = {"workload": "w", "hardware": {"cpu": "c", "cores": 2, "jax": "0"}, "command": "x",
              "steps": 1, "wall_ms": 5.0, "stages": list(profile.stages_of("nsrr")),
              "summary": {"op_ms_per_step": 4.0,
                          "stage_pass": {"reconstruction/forward": 3.0, "other/forward": 1.0},
                          "kind": {"convolution": 3.0, "other": 1.0},
                          "stage_kind": {"reconstruction/forward/convolution": 3.0},
                          "top_ops": top}}
    md = profile.markdown(report)
    rows = [line.split(" | ")[0][2:] for line in md.splitlines()
            if line.startswith("| ") and line.count("|") == 5 and "%" in line]
    assert rows[:2] == ["reconstruction", "other"]
    assert "| fusion.1 | reconstruction/forward/convolution | 3.0 | 75% | " \
           "`body/reconstruction/conv_general_dilated` |" in md
    assert "per device" not in md
    # a step split over devices: its times are one device's, and the report says so
    assert "op spans summed 4.0 ms per step on each of 2 devices" in profile.markdown(
        dict(report, devices=2))


def test_profile_refuses_a_device_split_it_cannot_run(tmp_path, capsys):
    """``--host-devices`` is checked before any work and nothing is written: a count
    below 1, a split of inference (one frame, no batch), a count that does not divide
    the batch, and (in a process whose JAX already runs on one device) any split."""
    from jtus import profile

    out = str(tmp_path / "p")
    for argv, words in ((["--host-devices", "0"], "expected a positive count"),
                        (["--what", "infer", "--host-devices", "2"], "--what train"),
                        (["--batch", "3", "--host-devices", "2"], "do not divide --batch 3"),
                        (["--crop", "16", "--batch", "2", "--seq", "2", "--loss-frames", "1",
                          "--host-devices", "2"], "already runs on 1 device")):
        with pytest.raises(SystemExit) as e:
            profile.main(argv + ["--out", out])
        assert e.value.code == 2
        err = capsys.readouterr().err
        assert "--host-devices" in err and words in err, err
    assert os.listdir(tmp_path) == []


@pytest.mark.long
def test_profile_of_a_split_step_files_each_devices_ops(tmp_path):
    """``python -m jtus.profile --host-devices 2`` (its own process: JAX's devices are set
    before it starts) profiles the step split over two devices: the gradient exchange
    shows as a collective, and the per-device times add up."""
    import subprocess
    import sys

    out = tmp_path / "p"
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    res = subprocess.run([sys.executable, "-m", "jtus.profile", "--factor", "4", "--crop", "32",
                          "--batch", "2", "--seq", "2", "--loss-frames", "1", "--steps", "1",
                          "--host-devices", "2", "--out", str(out)], cwd=root,
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    report = json.loads((tmp_path / "p.json").read_text())
    s = report["summary"]
    assert report["devices"] == 2 and s["kind"]["collective"] > 0
    assert s["stage_pass"]["network/forward"] > 0
    assert abs(sum(s["kind"].values()) - s["op_ms_per_step"]) < 1e-6 * s["op_ms_per_step"]
    assert "split over 2 XLA CPU devices" in (tmp_path / "p.md").read_text()


def test_profile_divides_the_spans_of_a_split_step_among_its_devices(monkeypatch):
    """``profile(..., devices=N)`` sums every device's spans of an op and divides them by
    N and by the steps: one device's time per step."""
    from jtus import profile

    text = ('  %ynn_fusion.3 = f32[4,34,34,32]{3,2,1,0} fusion(%a, %b), kind=kCustom, '
            'metadata={op_name="jit(train_step)/jvp()/while/body/closed_call/network/'
            'conv_general_dilated"}\n')
    monkeypatch.setattr(profile, "trace_ops", lambda run, hlo, steps, logdir: (
        {"ynn_fusion.3": 4 * 2 * 3e6}, profile.hlo_ops(hlo), 0))  # 2 devices, 4 steps
    report = profile.profile(lambda: None, text, steps=4, devices=2)
    assert report["devices"] == 2
    assert report["summary"]["op_ms_per_step"] == pytest.approx(3.0)
    assert report["summary"]["stage_pass"] == {"network/forward": pytest.approx(3.0)}
