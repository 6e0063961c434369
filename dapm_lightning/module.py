"""DAPMModule: the LightningModule around :class:`DAPMNet` and :class:`DAPMLoss`."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

import lightning as L
import torch
from lightning.pytorch.utilities import rank_zero_warn
from torch import Tensor

from dapm_lightning.data.sample import depth_masks
from dapm_lightning.geometry.constants import MAX_DEPTH_M
from dapm_lightning.geometry.igd import DepthKind, IGDModel
from dapm_lightning.geometry.pose import normalize_pose
from dapm_lightning.losses import DAPMLoss
from dapm_lightning.metrics import DepthMetrics, PoseMetrics, per_image_depth_metrics
from dapm_lightning.models.dapm import DAPMNet, DAPMOutput
from dapm_lightning.reliability import check_architecture, rng_states, set_rng_states

Stage = Literal["train", "val", "test"]


def warmup_cosine(step: int, total_steps: int, warmup_fraction: float, min_lr_ratio: float) -> float:
    """LR factor: linear warm-up over ``warmup_fraction`` of the steps, then cosine annealing to ``min_lr_ratio``."""
    warmup = max(1, int(round(total_steps * warmup_fraction)))
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total_steps - warmup))
    return min_lr_ratio + (1.0 - min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))


class DAPMModule(L.LightningModule):
    """Train, validate, test and predict DAPM and its ablations; every loss term and metric logged by name.

    Model arguments are those of :class:`DAPMNet`; ``use_igd_loss`` and ``loss_weights`` those of
    :class:`DAPMLoss`. The optimiser is AdamW (paper: lr 1e-4, betas 0.9/0.999, wd 0.01) with linear
    warm-up over ``warmup_fraction`` of the steps and cosine annealing. ``predicted_share`` (the IGD
    teacher forcing weight) is set by :class:`~dapm_lightning.callbacks.IGDTeacherForcing` during
    training; validation, test and predict always use the predicted pose alone.

    A non-finite training loss skips the step with a warning and ``train_nonfinite_steps``
    (``skip_nonfinite_loss``). Checkpoints carry the RNG states, and loading one trained with another
    architecture fails with a message listing what differs.

    Logged keys: ``<stage>_loss_<term>``, ``<stage>_depth_<metric>`` (metres),
    ``<stage>_depthlog_<metric>`` (paper's 8-bit log space), ``<stage>_pose_<component>_<stat>``.
    """

    def __init__(self, backbone: str = "resnet50", pretrained: bool = False, weights_path: str | None = None,
                 use_depth: bool = True, use_pose: bool = True, depth_bins: tuple[int, ...] = (2, 16, 64),
                 pose_bins: tuple[int, ...] = (16, 64), use_igd_feature: bool = True, use_igd_loss: bool = True,
                 igd_model: IGDModel = "pinhole", depth_kind: DepthKind = "range", max_depth: float = MAX_DEPTH_M,
                 decoder_channels: int = 96, head_channels: int = 32, igd_channels: int = 16, head_stride: int = 4,
                 dropout: float = 0.1, pose_hidden: int = 256, igd_feature_grad: bool = False,
                 loss_weights: dict[str, float] | None = None, lr: float = 1e-4, weight_decay: float = 0.01,
                 betas: tuple[float, float] = (0.9, 0.999), warmup_fraction: float = 0.3, min_lr_ratio: float = 0.0,
                 log_space_metrics: bool = True, pose_auc_min_error: float | None = None,
                 viewpoint_bins: int = 5, output_dir: str | None = None, skip_nonfinite_loss: bool = True) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.net = DAPMNet(backbone, pretrained=pretrained, weights_path=weights_path, use_depth=use_depth,
                           use_pose=use_pose, depth_bins=depth_bins, pose_bins=pose_bins,
                           use_igd_feature=use_igd_feature, igd_model=igd_model, depth_kind=depth_kind,
                           max_depth=max_depth, decoder_channels=decoder_channels, head_channels=head_channels,
                           igd_channels=igd_channels, head_stride=head_stride, dropout=dropout,
                           pose_hidden=pose_hidden, igd_feature_grad=igd_feature_grad)
        self.criterion = DAPMLoss(loss_weights, use_igd_loss=use_igd_loss and use_pose, igd_model=igd_model,
                                  depth_kind=depth_kind, max_depth=max_depth)
        self.predicted_share = 1.0
        self.metrics = torch.nn.ModuleDict()
        for stage in ("val", "test"):
            if use_depth:
                self.metrics[f"{stage}_depth"] = DepthMetrics(max_depth=max_depth)
                if log_space_metrics:
                    self.metrics[f"{stage}_depthlog"] = DepthMetrics(max_depth=max_depth, space="uapd_log")
            if use_pose:
                self.metrics[f"{stage}_pose"] = PoseMetrics(min_error=pose_auc_min_error)
        self._viewpoint_records: list[Tensor] = []
        self.nonfinite_steps = 0

    def forward(self, image: Tensor) -> DAPMOutput:
        """``image [B, 3, H, W]`` (uint8 or float in [0, 1]) -> :class:`DAPMOutput` (predictions only)."""
        return self.net(self._image(image))

    @staticmethod
    def _image(image: Tensor) -> Tensor:
        return image.float().div(255.0) if image.dtype == torch.uint8 else image

    def _shared_step(self, batch: dict[str, Any], stage: Stage) -> tuple[Tensor, DAPMOutput]:
        image = self._image(batch["image"])
        pose_norm_true = normalize_pose(batch["pose"]) if stage == "train" else None
        share = self.predicted_share if stage == "train" else 1.0
        out = self.net(image, pose_norm_true, share)
        sky, valid = depth_masks(batch["depth"], self.hparams["max_depth"])
        terms = self.criterion(out, {**batch, "sky": sky, "valid": valid})
        batch_size = image.shape[0]
        named = {f"{stage}_loss_{k}": v.detach() for k, v in terms.items() if k != "total"}
        self.log_dict(named, batch_size=batch_size, on_step=stage == "train", on_epoch=True,
                      sync_dist=stage != "train")
        self.log(f"{stage}_loss", terms["total"].detach(), batch_size=batch_size, prog_bar=True,
                 on_step=stage == "train", on_epoch=True, sync_dist=stage != "train")
        if stage != "train":
            self._update_metrics(out, batch, stage)
        return terms["total"], out

    def _update_metrics(self, out: DAPMOutput, batch: dict[str, Any], stage: str) -> None:
        if out.depth_m is not None:
            self.metrics[f"{stage}_depth"].update(out.depth_m, batch["depth"])
            if f"{stage}_depthlog" in self.metrics:
                self.metrics[f"{stage}_depthlog"].update(out.depth_m, batch["depth"])
        has_pose = batch["has_pose"]
        if out.pose is not None and has_pose.any():
            self.metrics[f"{stage}_pose"].update(out.pose[has_pose], batch["pose"][has_pose])
        if stage == "test":
            self._record_viewpoints(out, batch)

    def _log_metrics(self, stage: str) -> None:
        for name, metric in self.metrics.items():
            if name.startswith(stage + "_") and metric.update_called:
                self.log_dict({f"{name}_{k}": v for k, v in metric.compute().items()})
                metric.reset()

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> Tensor | None:
        loss, _ = self._shared_step(batch, "train")
        if torch.isfinite(loss) or not self.hparams["skip_nonfinite_loss"]:
            return loss
        self.nonfinite_steps += 1
        names = ", ".join(batch.get("name", [])[:8])
        rank_zero_warn(f"non-finite training loss at step {self.global_step} (batch {batch_idx}: {names}); "
                       f"step skipped, weights unchanged ({self.nonfinite_steps} so far)")
        self.log("train_nonfinite_steps", float(self.nonfinite_steps), on_step=True, on_epoch=False, batch_size=1)
        if self.trainer.world_size > 1:  # every process must run backward under DDP: a zero-gradient step
            return sum((p.sum() * 0.0 for p in self.parameters() if p.requires_grad), torch.zeros(()))
        return None  # Lightning skips backward and the optimiser step

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["dapm_rng_states"] = rng_states()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        check_architecture(checkpoint.get("hyper_parameters", {}), self.hparams, "the checkpoint")
        if self._trainer is not None and "dapm_rng_states" in checkpoint:
            set_rng_states(checkpoint["dapm_rng_states"])  # a resumed run draws what the uninterrupted one would

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        self._shared_step(batch, "val")

    def test_step(self, batch: dict[str, Any], batch_idx: int) -> None:
        self._shared_step(batch, "test")

    def on_validation_epoch_end(self) -> None:
        self._log_metrics("val")

    def on_test_epoch_start(self) -> None:
        self._viewpoint_records = []

    def on_test_epoch_end(self) -> None:
        self._log_metrics("test")
        self._finish_viewpoints()

    def predict_step(self, batch: dict[str, Any], batch_idx: int) -> dict[str, Any]:
        out = self(batch["image"])
        result: dict[str, Any] = {"name": batch.get("name")}
        if out.depth_m is not None:
            result["depth_m"] = out.depth_m
            if out.sky_logits is not None:
                result["sky_prob"] = torch.sigmoid(out.sky_logits)
        if out.pose is not None:
            result["pose"] = out.pose
        return result

    # --- per-viewpoint breakdown (paper's viewpoint figure) ---
    def _record_viewpoints(self, out: DAPMOutput, batch: dict[str, Any]) -> None:
        has_pose = batch["has_pose"]
        if not has_pose.any():
            return
        pose = batch["pose"].float()
        d1 = (per_image_depth_metrics(out.depth_m, batch["depth"], max_depth=self.hparams["max_depth"])["d1"]
              if out.depth_m is not None else torch.full((pose.shape[0],), math.nan, device=pose.device))
        error = ((out.pose - pose).abs() if out.pose is not None
                 else torch.full_like(pose, math.nan))
        self._viewpoint_records.append(torch.cat([pose, d1[:, None].to(pose), error.float()], 1)[has_pose])

    def _finish_viewpoints(self) -> None:
        if not self._viewpoint_records:
            return
        from dapm_lightning.viewpoints import viewpoint_table, plot_viewpoints

        records = torch.cat(self._viewpoint_records)
        gathered = self.all_gather(records)
        if gathered.ndim == 3:
            gathered = gathered.flatten(0, 1)
        table = viewpoint_table(gathered.cpu(), self.hparams["viewpoint_bins"])
        self.viewpoint_table = table
        if self.trainer.is_global_zero:
            values = {f"test_view_{r['component']}_bin{r['bin']}_{k}": r[k] for r in table for k in ("d1", "error")}
            for logger in self.loggers:  # to the loggers only: the console table stays readable
                logger.log_metrics(values, step=self.global_step)
            folder = Path(self.hparams["output_dir"] or self.trainer.log_dir or ".")
            folder.mkdir(parents=True, exist_ok=True)
            plot_viewpoints(table, folder / "viewpoints.png")

    def configure_optimizers(self) -> dict[str, Any]:
        optimizer = torch.optim.AdamW(self.parameters(), lr=self.hparams["lr"], betas=self.hparams["betas"],
                                      weight_decay=self.hparams["weight_decay"])
        total = max(1, int(self.trainer.estimated_stepping_batches))
        warmup, floor = self.hparams["warmup_fraction"], self.hparams["min_lr_ratio"]
        scheduler = torch.optim.lr_scheduler.LambdaLR(
            optimizer, lambda step: warmup_cosine(step, total, warmup, floor))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}


__all__ = ["DAPMModule", "warmup_cosine"]
