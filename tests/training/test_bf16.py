"""bf16 mixed precision on the CPU: the losses and metrics compute in float32 inside autocast, and training runs."""

import json
import subprocess
import sys

import pytest
import torch

from dapm_lightning.data.synthetic import generate_uapd
from dapm_lightning.geometry import MAX_DEPTH_M
from dapm_lightning.geometry.precision import to_float32
from dapm_lightning.metrics import AuthorsDepthMetrics, DepthMetrics, PoseMetrics
from dapm_lightning.models import DAPMConfig, DAPMNet
from dapm_lightning.training.lightning_cli import run_lightning_cli
from dapm_lightning.training.loss import DAPMLoss, LossConfig
from tests.conftest import QUICKSTART
from tests.training.test_ddp import HERE

SIZE = (32, 48)


def bf16_outputs():
    """A small network's outputs under bf16 autocast (bf16 tensors, as Lightning's bf16-mixed hands them over)."""
    torch.manual_seed(0)
    net = DAPMNet(DAPMConfig(backbone="resnet18", pretrained=False, decoder_channels=32, head_channels=16))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = net(torch.rand(2, 3, *SIZE))
    assert out.depth.depth_init_norm.dtype == torch.bfloat16 and out.pose.pose_norm.dtype == torch.bfloat16
    depth = torch.rand(2, 1, *SIZE) * 300 + 2
    depth[:, :, :4] = MAX_DEPTH_M
    pose = torch.tensor([[57.3, -63.4, 12.75, 88.1], [23.0, -88.0, -4.5, 61.0]])
    targets = dict(depth=depth, sky=depth >= MAX_DEPTH_M, valid=torch.ones_like(depth, dtype=torch.bool), pose=pose,
                   has_pose=torch.tensor([True, True]))
    return out, targets


@pytest.mark.parametrize("config", [LossConfig(), LossConfig(depth_space="log_norm", use_gradient_loss=True)],
                         ids=["metric", "authors"])
def test_every_loss_term_under_autocast_matches_float32(config):
    out, targets = bf16_outputs()
    loss = DAPMLoss(config)
    expected = loss(to_float32(out), targets)  # the same values in float32, no autocast
    with torch.autocast("cpu", dtype=torch.bfloat16):
        got = loss(out, targets)
    assert set(got) == set(expected) and {"depth", "init_depth", "dq", "pose", "init_pose", "pq", "pd"} <= set(got)
    for term, value in got.items():
        assert value.dtype == torch.float32, term
        torch.testing.assert_close(value, expected[term], rtol=1e-5, atol=0, msg=term)


def test_metrics_under_autocast_match_float32():
    """The metrics compute in float64 whatever they are handed: bf16 depth and pose give float32's figures."""
    out, targets = bf16_outputs()
    depths = [out.depth_m.bfloat16(), targets["depth"].bfloat16()]
    poses = [out.pose_physical.bfloat16(), targets["pose"].bfloat16()]
    results = []
    for autocast in (False, True):
        metrics = [DepthMetrics(), AuthorsDepthMetrics(), PoseMetrics()]
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            for metric, pair in zip(metrics, (depths, depths, poses)):
                metric.update(*(pair if autocast else to_float32(pair)))
        results.append({f"{k}_{m}": v for k, metric in enumerate(metrics) for m, v in metric.compute().items()})
    for key, value in results[1].items():
        torch.testing.assert_close(value, results[0][key], rtol=1e-5, atol=1e-7, msg=key)


def assert_finite_training(metrics: dict) -> None:
    losses = {k: v for k, v in metrics.items() if k.startswith("train_loss")}
    assert {"train_loss_depth_epoch", "train_loss_pd_epoch", "train_loss_pose_epoch"} <= set(losses), sorted(metrics)
    assert all(torch.isfinite(torch.tensor(v)) for v in losses.values()), losses


def test_quickstart_trains_in_bf16_mixed(tiny_uapd, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cli = run_lightning_cli(["fit", "--config", str(QUICKSTART), "--data.class_path",
                             "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(tiny_uapd),
                             "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
                             "--trainer.precision", "bf16-mixed", "--trainer.max_epochs", "1",
                             "--trainer.limit_train_batches", "2", "--trainer.limit_val_batches", "1"])
    assert cli.trainer.precision == "bf16-mixed" and cli.trainer.global_step == 2
    assert cli.model.nonfinite_steps == 0
    assert_finite_training({k: float(v) for k, v in cli.trainer.callback_metrics.items()})
    assert torch.isfinite(cli.trainer.callback_metrics["val_depth_d1"])


@pytest.mark.slow
def test_quickstart_trains_in_bf16_mixed_under_two_process_ddp(tmp_path):
    root = generate_uapd(tmp_path / "data", train=8, val=4, size=(24, 40), seed=11, workers=1)
    out = tmp_path / "bf16.json"
    args = ["fit", "--config", str(QUICKSTART), "--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule",
            "--data.init_args.root", str(root), "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
            "--trainer.accelerator", "cpu", "--trainer.devices", "2", "--trainer.strategy", "ddp",
            "--trainer.precision", "bf16-mixed", "--trainer.max_steps", "3", "--trainer.limit_val_batches", "1"]
    try:
        subprocess.run([sys.executable, str(HERE / "ddp_run.py"), str(out), *args], check=True, cwd=tmp_path,
                       capture_output=True, text=True, timeout=300)
    except subprocess.CalledProcessError as error:
        pytest.fail(f"bf16 DDP fit failed:\n{error.stderr[-3000:]}")
    result = json.loads(out.read_text())
    assert result["global_step"] == 3
    assert_finite_training(result["metrics"])
