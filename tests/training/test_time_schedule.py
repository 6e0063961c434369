"""``OptimizerConfig.schedule_seconds``: the warm-up/cosine schedule follows the wall time, not the steps."""

import time

import pytest

from dapm_lightning.models import DAPMConfig
from dapm_lightning.training.module import DAPMModule, OptimizerConfig, warmup_cosine

TINY = {"backbone": "resnet18", "decoder_channels": 16, "head_channels": 8, "igd_channels": 4, "pose_hidden": 16,
        "depth_bins": (2, 4), "pose_bins": (4,)}


def test_the_learning_rate_follows_the_time_spent_not_the_steps(monkeypatch):
    now = [100.0]
    monkeypatch.setattr(time, "perf_counter", lambda: now[0])
    config = OptimizerConfig(lr=1e-3, warmup_fraction=0.1, min_lr_ratio=0.02, schedule_seconds=20.0)
    module = DAPMModule(DAPMConfig(**TINY), optimizer=config)  # no trainer: the step count is never asked
    scheduled = module.configure_optimizers()
    optimizer, scheduler = scheduled["optimizer"], scheduled["lr_scheduler"]["scheduler"]

    def lr_after(step_seconds: float, steps: int = 1) -> float:
        for _ in range(steps):
            now[0] += step_seconds
            optimizer.step()
            scheduler.step()
        return optimizer.param_groups[0]["lr"]

    assert optimizer.param_groups[0]["lr"] == pytest.approx(1e-3 * warmup_cosine(0, 1000, 0.1, 0.02))
    assert lr_after(0.0) == pytest.approx(1e-3 / 100)  # the clock starts after the first step: still tick 0
    assert lr_after(1.0) == pytest.approx(1e-3 * 51 / 100)  # 1 s of 20: tick 50 of the 100-tick warm-up
    assert lr_after(0.0, steps=50) == pytest.approx(1e-3 * 51 / 100)  # steps without time: the rate stays
    assert lr_after(1.0) == pytest.approx(1e-3)  # 2 s = 10 % of the budget: warm-up done, the peak
    assert lr_after(9.0) == pytest.approx(1e-3 * warmup_cosine(550, 1000, 0.1, 0.02))  # half-way through cosine
    assert lr_after(9.0) == pytest.approx(1e-3 * 0.02)  # 20 s: the budget spent, the final rate
    assert lr_after(30.0) == pytest.approx(1e-3 * 0.02)  # and stays there past it


def test_schedule_seconds_must_be_positive():
    with pytest.raises(ValueError, match="schedule_seconds"):
        OptimizerConfig(schedule_seconds=0.0)
    assert DAPMModule(DAPMConfig(**TINY), optimizer=OptimizerConfig(schedule_seconds=5.0)).hparams[
        "optimizer"]["schedule_seconds"] == 5.0
