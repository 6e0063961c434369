"""The epoch's losses and metrics as logged: the training losses are the mean over the steps that trained (a step
skipped as non-finite weighs 0), every figure on the module's device."""

import math

import lightning as L
import pytest
import torch

from dapm_lightning.models import DAPMConfig
from dapm_lightning.training.lightning_cli import run_lightning_cli
from dapm_lightning.training.module import DAPMModule
from tests.conftest import QUICKSTART

TINY = ["--model.net.backbone", "mobilenetv3_small_050", "--model.net.decoder_channels", "16",
        "--model.net.head_channels", "8", "--model.net.pose_hidden", "32", "--data.init_args.batch_size", "2",
        "--data.init_args.num_workers", "0", "--trainer.enable_progress_bar", "false", "--trainer.logger", "false",
        "--trainer.enable_checkpointing", "false", "--trainer.callbacks", "[]", "--trainer.limit_val_batches", "0"]


class StepLosses(L.Callback):
    """Every logged training value of each step."""

    def __init__(self):
        self.steps = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.steps.append({k: float(v) for k, v in trainer.callback_metrics.items() if k.endswith("_step")})


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_a_skipped_nonfinite_step_leaves_the_epoch_losses_finite(tiny_uapd, tmp_path, monkeypatch, bad):
    monkeypatch.chdir(tmp_path)
    cli = run_lightning_cli(["--config", str(QUICKSTART), "--data.class_path",
                             "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(tiny_uapd),
                             *TINY, "--trainer.max_epochs", "1"], run=False)
    model, calls = cli.model, []
    real = model.criterion.forward

    def first_step_nonfinite(out, targets):
        terms = real(out, targets)
        calls.append(1)
        return {k: v * bad for k, v in terms.items()} if len(calls) == 1 else terms

    monkeypatch.setattr(model.criterion, "forward", first_step_nonfinite)
    recorder = StepLosses()
    cli.trainer.callbacks.append(recorder)
    with pytest.warns(UserWarning, match="non-finite training loss"):
        cli.trainer.fit(model, datamodule=cli.datamodule)
    assert model.nonfinite_steps == 1 and len(recorder.steps) == 2  # 4 images, 2 a batch: step 0 skipped, step 1 ran
    first, second = recorder.steps
    assert math.isnan(first["train_loss_step"]) or math.isinf(first["train_loss_step"])  # each step as it was
    assert math.isfinite(second["train_loss_step"])
    metrics = {k: float(v) for k, v in cli.trainer.callback_metrics.items()}
    epoch = {k: v for k, v in metrics.items() if k.startswith("train_loss") and k.endswith("_epoch")}
    assert {"train_loss_epoch", "train_loss_depth_epoch", "train_loss_pose_epoch"} <= set(epoch)
    for key, value in epoch.items():  # the mean over the one finite step
        assert value == pytest.approx(second[key.replace("_epoch", "_step")], rel=1e-6), key
    assert all(math.isfinite(v) for v in epoch.values()), epoch
    assert torch.isfinite(cli.trainer.callback_metrics["train_loss_epoch"])


def test_an_evaluation_cut_short_leaves_nothing_to_the_next(tiny_uapd, tmp_path, monkeypatch):
    """A validation stopped by an error mid-way (out of memory, Ctrl-C in a notebook): the next one starts afresh."""
    monkeypatch.chdir(tmp_path)
    cli = run_lightning_cli(["--config", str(QUICKSTART), "--data.class_path",
                             "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(tiny_uapd),
                             *TINY, "--data.init_args.eval_batch_size", "1", "--trainer.limit_val_batches", "1.0"],
                            run=False)
    model, trainer = cli.model, cli.trainer
    expected = {k: float(v) for k, v in trainer.validate(model, datamodule=cli.datamodule, verbose=False)[0].items()}
    real, calls = model.criterion.forward, []

    def fail_on_the_second_batch(out, targets):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("out of memory")
        return real(out, targets)

    monkeypatch.setattr(model.criterion, "forward", fail_on_the_second_batch)
    with pytest.raises(RuntimeError, match="out of memory"):
        trainer.validate(model, datamodule=cli.datamodule, verbose=False)
    monkeypatch.setattr(model.criterion, "forward", real)
    again = {k: float(v) for k, v in trainer.validate(model, datamodule=cli.datamodule, verbose=False)[0].items()}
    assert again.keys() == expected.keys() and "val_loss" in again and "val_depth_d1" in again
    for key, value in expected.items():
        assert again[key] == pytest.approx(value, rel=1e-6, nan_ok=True), key


def test_an_evaluation_s_losses_are_summed_per_image_across_batches_of_unequal_size():
    """Batches of 2 and 1 images: the epoch's loss is the mean over the 3 images, not over the 2 batches."""
    from dapm_lightning.models import DAPMConfig
    from dapm_lightning.training.module import DAPMModule

    module = DAPMModule(DAPMConfig(backbone="resnet18", pretrained=False, decoder_channels=16, head_channels=8,
                                   igd_channels=4, pose_hidden=16)).eval()
    depth = torch.full((3, 1, 32, 48), 80.0)
    depth[:, :, :4] = 1000.0  # some sky
    batch = {"image": torch.rand(3, 3, 32, 48), "depth": depth, "has_pose": torch.ones(3, dtype=torch.bool),
             "pose": torch.tensor([[40.0, -50.0, 5.0, 70.0], [60.0, -70.0, -5.0, 90.0], [30.0, -30.0, 0.0, 60.0]]),
             "name": ["a", "b", "c"]}
    parts = [{k: v[:2] for k, v in batch.items()}, {k: v[2:] for k, v in batch.items()}]
    with torch.no_grad():
        losses = [module._shared_step(part, "test")[0] for part in parts]
        module.eval_losses.clear()
        for part in parts:
            module._shared_step(part, "val")
    sums, images = module.eval_losses["val"]
    assert images == 3 and losses[0] != losses[1]
    torch.testing.assert_close(sums["val_loss"] / images, (2 * losses[0] + losses[1]) / 3)


def test_epoch_metrics_are_logged_on_the_module_s_device():
    """NCCL, the backend of multi-GPU DDP, reduces no CPU tensor. Before, the pose AUCs (computed on the CPU) were
    logged there with ``sync_dist`` and a GPU run under DDP stopped at its first validation's end. No GPU here: the
    module's device is faked (meta), and every logged figure must be on it."""
    module = DAPMModule(DAPMConfig(backbone="resnet18"))
    pose = torch.tensor([[50.0, -40, 0, 60], [80.0, -60, 5, 70]])
    module.metrics["val_pose"].update(pose + 1, pose)
    module.metrics["val_depth"].update(torch.full((2, 1, 8, 8), 40.0), torch.full((2, 1, 8, 8), 50.0))
    logged: dict[str, torch.Tensor] = {}
    module.log_dict = lambda values, **kwargs: logged.update(values)
    module._device = torch.device("meta")
    module._log_metrics("val")
    assert {"val_pose_pitch_auc5", "val_depth_d1"} <= set(logged)
    assert {name: value.device.type for name, value in logged.items() if value.device.type != "meta"} == {}
