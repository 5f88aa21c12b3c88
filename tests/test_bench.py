"""A smoke test of ``python -m jtus.bench`` (timings are measured, not asserted)."""

import json

from jtus import bench, cost, models


def test_bench_smoke(capsys):
    assert bench.main(["--sizes", "64", "--factors", "4", "--repeats", "1", "--models",
                       "dlctus", "jau", "tus", "--train-crop", "16", "--train-seq", "2",
                       "--train-loss-frames", "1", "--train-batch", "1", "--train-warps", "bicubic",
                       "nearest", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["hardware"]["cores"] >= 1
    assert {r["model"] for r in report["infer"]} == {"dlctus", "jau", "tus"}
    dl = [r for r in report["infer"] if r["model"] == "dlctus"][0]
    assert dl["ms"] > 0 and dl["network_ms"] > 0 and "torch_over_jtus" in dl
    assert report["train"]["s_per_step"] > 0 and report["peak"]["matmul_gflops"] > 0
    assert [r["warp"] for r in report["train_warps"]] == ["bicubic", "nearest"]
    assert report["train"] == report["train_warps"][0]


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
