"""Callbacks that depend on training progress: the IGD teacher-forcing share and picture panels."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import lightning as L
import torch
from lightning.pytorch.utilities import rank_zero_warn

from dapm_lightning.models.teacher_forcing import predicted_share_at
from dapm_lightning.training.module import DAPMModule
from dapm_lightning.training.visualize import depth_panel


class IGDTeacherForcing(L.Callback):
    """Sets :attr:`DAPMModule.igd_predicted_share` before every training batch (the IGD teacher forcing).

    The schedule is :func:`~dapm_lightning.models.teacher_forcing.predicted_share_at`.

    The predicted share ``w`` of the IGD input ``w * predicted + (1 - w) * true`` pose rises linearly from
    ``start_share`` at ``start_fraction`` of training to ``end_share`` at ``end_fraction`` (paper: from true
    poses to predictions only by the end of training): of its steps, or with ``model.optimizer.schedule_seconds``
    of that time, as the learning rate (:meth:`DAPMModule.schedule_progress`). Logged as
    ``train_igd_predicted_share``.
    """

    def __init__(self, start_share: float = 0.0, end_share: float = 1.0, start_fraction: float = 0.0,
                 end_fraction: float = 1.0) -> None:
        self.schedule = dict(start_share=start_share, end_share=end_share, start_fraction=start_fraction,
                             end_fraction=end_fraction)
        predicted_share_at(0.0, **self.schedule)  # checks the shares and the fractions

    def share(self, step: int, total_steps: int) -> float:
        """The predicted share at ``step`` of ``total_steps``."""
        return predicted_share_at(step / max(1, total_steps), **self.schedule)

    @property
    def keeps_the_true_pose(self) -> bool:
        """Whether the IGD sees the true pose throughout training (both shares 0)."""
        return self.schedule["start_share"] == 0.0 and self.schedule["end_share"] == 0.0

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        module = _dapm_module(pl_module)
        if self.keeps_the_true_pose and module.prior_training.enabled and not module.net_config.pose_prior_input:
            rank_zero_warn("model.prior_training changes nothing here: IGDTeacherForcing keeps the IGD on the true "
                           "pose throughout training (start_share and end_share 0), which replaces the fused pose. "
                           "Tell the pose branch the priors (model.net.pose_prior_input: true), turn them off, or "
                           "let the share rise (end_share > 0) for them to act.")

    def on_train_batch_start(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: Any,
                             batch_idx: int) -> None:
        module = _dapm_module(pl_module)
        module.igd_predicted_share = predicted_share_at(module.schedule_progress(trainer.global_step), **self.schedule)
        module.log("train_igd_predicted_share", module.igd_predicted_share, on_step=True, on_epoch=False,
                   batch_size=1)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        _dapm_module(pl_module).igd_predicted_share = 1.0


def _dapm_module(pl_module: L.LightningModule) -> DAPMModule:
    if not isinstance(pl_module, DAPMModule):
        raise TypeError(f"IGDTeacherForcing drives a DAPMModule, got {type(pl_module).__name__}")
    return pl_module


class DepthPanelLogger(L.Callback):
    """Picture panels of the current batch, to the logger and as PNG files.

    Every ``every_n_steps`` training steps and on the first test batch, renders
    ``RGB | true depth | predicted depth | IGD of predicted pose | error``, sends it to the logger
    (TensorBoard) and writes it under ``<output_dir or log_dir>/panels``. Without ``output_dir`` it belongs
    to the logger's run (:attr:`needs_logger`): ``dapm-lightning`` leaves it out when there is no logger.
    """

    def __init__(self, every_n_steps: int = 500, max_images: int = 4, output_dir: str | None = None) -> None:
        self.every_n_steps, self.max_images, self.output_dir = every_n_steps, max_images, output_dir
        self._last_train_step: int | None = None
        self.written: list[Path] = []
        self._test_log_dir: str | None = None

    @property
    def needs_logger(self) -> bool:
        """True without ``output_dir``: the panels go to the logger and its log folder."""
        return self.output_dir is None

    def _render(self, trainer: L.Trainer, pl_module: L.LightningModule, batch: dict[str, Any], tag: str,
                log_dir: str | None) -> None:
        was_training = pl_module.training
        pl_module.eval()
        with torch.no_grad():
            image = batch["image"][: self.max_images]
            out = pl_module(image)
        pl_module.train(was_training)
        panel = depth_panel(image, batch["depth"][: self.max_images], out, self.max_images,
                            _dapm_module(pl_module).net_config.igd)
        step = trainer.global_step
        experiment = getattr(trainer.logger, "experiment", None)
        if experiment is not None and hasattr(experiment, "add_image"):
            experiment.add_image(f"panels/{tag}", panel, step, dataformats="HWC")
        if trainer.is_global_zero:
            folder = Path(self.output_dir or log_dir or ".") / "panels"
            folder.mkdir(parents=True, exist_ok=True)
            path = folder / f"{tag}_step{step:06d}.png"
            cv2.imwrite(str(path), cv2.cvtColor(panel, cv2.COLOR_RGB2BGR))
            self.written.append(path)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        # once per optimizer step: under gradient accumulation global_step stands still for the window's micro-batches
        step = trainer.global_step
        if self.every_n_steps > 0 and step % self.every_n_steps == 0 and step != self._last_train_step:
            self._last_train_step = step
            # a broadcast under DDP: every rank asks (all train every step), or rank 0 waits for the others forever
            self._render(trainer, pl_module, batch, "train", trainer.log_dir)

    def on_test_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._test_log_dir = trainer.log_dir  # asked here, by every rank: one may have no test batch (DDP)

    def on_test_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                          batch_idx: int, dataloader_idx: int = 0) -> None:
        if batch_idx == 0:
            self._render(trainer, pl_module, batch, "test", self._test_log_dir)
