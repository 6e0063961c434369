"""``OptimizerConfig.schedule_seconds``: the warm-up/cosine schedule and the IGD teacher forcing follow the wall
time, not the steps, also across a resume; a run without a length in steps or seconds is refused at its start."""

import time
from types import SimpleNamespace

import lightning as L
import pytest
import torch
import yaml

from dapm_lightning.models import DAPMConfig
from dapm_lightning.training import module as module_file
from dapm_lightning.training.lightning_cli import run_lightning_cli
from dapm_lightning.training.module import DAPMModule, OptimizerConfig, TimeBudgetLR, warmup_cosine
from tests.conftest import QUICKSTART, run_main

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
            module.lr_scheduler_step(scheduler, None)  # as Lightning steps it: the clock is read first
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


LR, WARMUP, MIN_LR = 1e-3, 0.1, 0.02
TINY_FIT = ["--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.batch_size", "2",
            "--data.init_args.num_workers", "0", "--model.net.backbone", "mobilenetv3_small_050",
            "--model.net.decoder_channels", "16", "--model.net.head_channels", "8", "--model.net.pose_hidden", "32",
            "--trainer.limit_val_batches", "0", "--trainer.enable_progress_bar", "false",
            "--trainer.enable_model_summary", "false", "--model.optimizer.lr", str(LR),
            "--model.optimizer.warmup_fraction", str(WARMUP), "--model.optimizer.min_lr_ratio", str(MIN_LR)]


@pytest.fixture()
def one_second_a_step(monkeypatch):
    """The schedule's clock (read once per optimiser step) advances one second a read."""
    now = iter(range(10_000))
    monkeypatch.setattr(module_file, "time", SimpleNamespace(perf_counter=lambda: float(next(now))))


def fit(tmp_path, data, *args, ckpt=None, stop_at=None):
    """Fit in this process with the IGD teacher forcing rising from 0 to 1 over training and last.ckpt saved when
    training ends, stopped after step ``stop_at`` if given; ``(global step, learning rate, predicted share)`` after
    every training batch."""
    config = tmp_path / "callbacks.yaml"
    config.write_text(yaml.safe_dump({"trainer": {"logger": False, "callbacks": [
        {"class_path": "dapm_lightning.training.callbacks.IGDTeacherForcing", "init_args": {"end_share": 1.0}},
        {"class_path": "dapm_lightning.training.checkpointing.LastCheckpoint",
         "init_args": {"dirpath": str(tmp_path / "ckpt")}}]}}))
    seen = []

    class Record(L.Callback):
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            seen.append((trainer.global_step, trainer.optimizers[0].param_groups[0]["lr"],
                         pl_module.igd_predicted_share))
            trainer.should_stop = trainer.global_step == stop_at

    cli = run_lightning_cli(["--config", str(QUICKSTART), "--config", str(config), *TINY_FIT,
                             "--data.init_args.root", str(data), *args], run=False)
    cli.trainer.callbacks.append(Record())
    cli.trainer.fit(cli.model, datamodule=cli.datamodule, ckpt_path=ckpt)
    return seen


def test_a_run_bounded_by_max_time_alone_schedules_by_the_time(tiny_uapd, tmp_path, monkeypatch, one_second_a_step):
    """max_epochs -1 without max_steps: the learning rate and the teacher forcing follow the share of
    schedule_seconds spent (here one second a step of 10: a tenth a step after the first), to the end."""
    monkeypatch.chdir(tmp_path)
    seen = fit(tmp_path, tiny_uapd, "--trainer.max_epochs", "-1", "--trainer.max_time", "00:00:10:00",
               "--model.optimizer.schedule_seconds", "10", stop_at=13)  # stopped as max_time would, sooner
    assert [step for step, _, _ in seen] == list(range(1, 14))
    for step, lr, share in seen:  # the share set before the step: the time at the end of the step before
        assert lr == pytest.approx(LR * warmup_cosine(min(1000, 100 * (step - 1)), 1000, WARMUP, MIN_LR)), step
        assert share == pytest.approx(min(1.0, max(0, step - 2) / 10)), step


def test_without_a_length_in_steps_or_seconds_fit_names_the_settings(tiny_uapd, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code, err = run_main(["fit", "--config", str(QUICKSTART), *TINY_FIT, "--data.init_args.root", str(tiny_uapd),
                          "--trainer.logger", "false", "--trainer.max_epochs", "-1", "--trainer.max_time",
                          "00:00:01:00"], capsys)
    assert code == 1 and "this run has no number of steps (trainer.max_epochs: -1, trainer.max_steps: -1" in err, err
    assert "Fix: set model.optimizer.schedule_seconds" in err and "model.optimizer.schedule_steps" in err, err


def test_a_resumed_run_goes_on_from_the_time_spent(tiny_uapd, tmp_path, monkeypatch, one_second_a_step):
    """Stopped after 4 steps (3 s spent: the clock starts as the first step ends) and resumed: the schedule goes on
    from 3 s, as the first step of a run (its start-up included) does not count."""
    monkeypatch.chdir(tmp_path)
    budget = ["--model.optimizer.schedule_seconds", "10"]
    fit(tmp_path, tiny_uapd, "--trainer.max_steps", "4", *budget)
    saved = torch.load(tmp_path / "ckpt" / "last.ckpt", weights_only=True)["lr_schedulers"][0]
    assert saved["seconds"] == 3.0 and "budget" not in saved
    resumed = fit(tmp_path, tiny_uapd, "--trainer.max_steps", "8", *budget, ckpt=str(tmp_path / "ckpt" / "last.ckpt"))
    assert [step for step, _, _ in resumed] == [5, 6, 7, 8]
    assert [lr for _, lr, _ in resumed] == pytest.approx(
        [LR * warmup_cosine(100 * seconds, 1000, WARMUP, MIN_LR) for seconds in (3, 4, 5, 6)])
    assert [share for _, _, share in resumed] == pytest.approx([0.3, 0.3, 0.4, 0.5])  # set before each step


def test_the_time_budget_counts_whole_thousandths_rounded_down():
    optimizer = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    scheduler = TimeBudgetLR(optimizer, budget=10.0, warmup_fraction=0.1, min_lr_ratio=0.0)
    for seconds, ticks in ((0.0, 0), (0.0196, 1), (9.9999, 999), (10.0, 1000), (25.0, 1000)):
        scheduler.seconds = seconds
        assert scheduler.ticks == ticks, seconds
