"""The GPU kit (`make bench-gpu`): its CPU path end to end, as docs/gpu.md runs it, and its pieces."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from benchmarks.bench_gpu import NETWORKS, Scale, curve_gap, main, make_net, render, train_run

REPO = Path(__file__).resolve().parents[2]


def test_curve_gap_by_hand():
    gap = curve_gap([2.0, 1.0, 1.0, 1.0], [2.0, 1.5, 1.0, 0.5], window=2)
    assert gap["max_relative_gap"] == pytest.approx(0.5)  # step 2: |1.5 - 1| / 1
    assert gap["max_relative_gap_smoothed"] == pytest.approx(0.25)  # means (1.5, 1, 1) vs (1.75, 1.25, 0.75)


def test_without_a_gpu_the_kit_says_how_to_check_it(monkeypatch, capsys):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(SystemExit):
        main([])
    assert "--device cpu --tiny" in capsys.readouterr().err


def test_a_training_run_times_wait_and_compute_and_keeps_the_loss_curve(tmp_path, monkeypatch):
    from dapm_lightning.training.module import DAPMModule

    steps: list[int] = []
    real_step = DAPMModule.training_step

    def counted(self, batch, batch_idx):
        steps.append(batch_idx)
        return real_step(self, batch, batch_idx)

    monkeypatch.setattr(DAPMModule, "training_step", counted)
    scale = Scale.tiny()
    root = render(tmp_path / "data", 64, 4, 2, 1)
    rows = [train_run("efficient", "32-true", False, root, scale, 2, torch.device("cpu"), workers=0)
            for _ in range(2)]
    assert len(steps) == 2 * (scale.warmup_steps + 2)  # every step is the module's own, in a Trainer
    assert rows[0]["losses"] == rows[1]["losses"]  # the same seed: the same weights and batches, the same curve
    row = rows[0]
    assert row["finite"] and len(row["losses"]) == scale.warmup_steps + 2
    assert 0.0 <= row["stall_share"] < 1.0 and row["images_per_s"] == pytest.approx(2 / row["s_per_step"])
    assert row["peak_memory_mb"] > 0
    tiny_paper = make_net("paper", scale, torch.device("cpu"), False)
    assert tiny_paper.config.head_stride == NETWORKS["paper"]["head_stride"]  # the paper's structure, narrow


@pytest.mark.slow
def test_the_kit_runs_end_to_end_on_the_cpu(tmp_path):
    """``python -m benchmarks.bench_gpu --device cpu --tiny``: every phase, the JSON and the markdown."""
    result = subprocess.run([sys.executable, "-m", "benchmarks.bench_gpu", "--device", "cpu", "--tiny",
                             "--out", str(tmp_path)], capture_output=True, text=True, timeout=600, cwd=REPO)
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((tmp_path / "bench_gpu.json").read_text())
    assert set(report["phase_seconds"]) == {"render", "loader", "train", "inference", "learning"}
    assert report["loader"]["samples_per_s"] > 0
    settings = {(r["network"], r["precision"], r["channels_last"]) for r in report["train"]}
    assert settings == {(n, p, c) for n in NETWORKS for p in ("32-true", "bf16-mixed") for c in (False, True)}
    for row in report["train"]:
        assert row["finite"] and row["s_per_step"] > 0 and 0 <= row["stall_share"] < 1 and row["peak_memory_mb"] > 0
    assert [g["network"] for g in report["bf16_vs_fp32"]] == list(NETWORKS)
    assert all(g["all_finite"] and math.isfinite(g["max_relative_gap"]) for g in report["bf16_vs_fp32"])
    variants = {(r["network"], r["variant"], r["batch"]) for r in report["inference"]}
    for network in NETWORKS:
        for batch in Scale.tiny().infer_batches:
            assert {(network, v, batch) for v in ("eager fp32", "eager bf16", "channels-last fp32",
                                                  "channels-last bf16", "onnxruntime CPU")} <= variants
    assert ("efficient", "compile bf16 channels-last", 1) in variants
    for row in report["inference"]:
        assert row["fps"] > 0 and row["x_table7"] == pytest.approx(row["fps"] / 24.1)
        assert row["max_depth_rel_change"] < 0.2, row  # every variant computes the same network
        if row["variant"] == "eager bf16":
            assert row["max_depth_rel_change_to_bf16"] == 0.0, row  # its own reference
        if row["variant"] == "compile bf16 channels-last":  # ran in bf16: nearer eager bf16 than eager fp32
            assert row["max_depth_rel_change_to_bf16"] <= row["max_depth_rel_change"] + 1e-3, row
    learning = report["learning"]
    assert learning["steps"] > 0 and 0 <= learning["d1"] <= 1 and math.isfinite(learning["roll_median"])
    markdown = (tmp_path / "bench_gpu.md").read_text()
    assert markdown.strip() in result.stdout
    assert "| efficient | bf16-mixed | on |" in markdown and "| paper | onnxruntime CPU | 1 |" in markdown
    assert "Learning: the efficient variant" in markdown
