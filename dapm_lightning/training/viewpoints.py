"""Per-viewpoint breakdown (paper's viewpoint figure): depth d1 and pose error per bin of each pose component."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, cast

import lightning as L
import torch
from torch import Tensor

from dapm_lightning.geometry.constants import POSE_KEYS, POSE_RANGES, POSE_UNITS
from dapm_lightning.metrics import per_image_depth_metrics
from dapm_lightning.models.dapm import DAPMOutput
from dapm_lightning.training.evaluation_outputs import depth_limit


def viewpoint_table(records: Tensor, bins: int = 5) -> list[dict[str, Any]]:
    """Bin test images by each true pose component (uniform bins over the UAPD range).

    Args:
        records: ``[N, 9]``: true pose (4), per-image d1 (1), absolute pose errors (4).
        bins: bins per component.

    Returns:
        Rows ``{component, bin, low, high, count, d1 (mean), error (median of that component's error;
        of an even count the mean of the two middle values)}``.
    """
    rows = []
    for k, key in enumerate(POSE_KEYS):
        lo, hi = POSE_RANGES[key]
        edges = torch.linspace(lo, hi, bins + 1)
        which = torch.bucketize(records[:, k].clamp(lo, hi), edges[1:-1], right=True)
        for b in range(bins):
            chosen = records[which == b]
            d1 = chosen[:, 4][torch.isfinite(chosen[:, 4])]
            err = chosen[:, 5 + k][torch.isfinite(chosen[:, 5 + k])]
            rows.append({"component": key, "bin": b, "low": float(edges[b]), "high": float(edges[b + 1]),
                         "count": int(chosen.shape[0]),
                         "d1": float(d1.mean()) if d1.numel() else math.nan,
                         # numpy's median, as PoseMetrics (torch.median takes the lower middle value)
                         "error": float(torch.quantile(err.double(), 0.5)) if err.numel() else math.nan})
    return rows


def plot_viewpoints(rows: list[dict[str, Any]], path: str | Path) -> Path:
    """Save a 1x4 figure (pitch, height, roll, fov): d1 and median pose error per bin."""
    from matplotlib.figure import Figure  # no pyplot: the caller's plotting backend and state stay as they are

    fig = Figure(figsize=(16, 3.6), constrained_layout=True)
    axes = fig.subplots(1, 4)
    for ax, key in zip(axes, ("pitch", "height", "roll", "fov")):
        sel = [r for r in rows if r["component"] == key]
        centres = [(r["low"] + r["high"]) / 2 for r in sel]
        ax.plot(centres, [r["d1"] for r in sel], "o-", color="tab:blue", label="depth δ1")
        ax.set_ylim(0, 1.02)
        ax.set_xlabel(f"true {key} [{POSE_UNITS[key]}]")
        ax.set_ylabel("δ1", color="tab:blue")
        twin = ax.twinx()
        twin.plot(centres, [r["error"] for r in sel], "s--", color="tab:red", label=f"{key} error")
        twin.set_ylabel(f"median {key} error [{POSE_UNITS[key]}]", color="tab:red")
        for c, r in zip(centres, sel):
            ax.annotate(f"n={r['count']}", (c, 0.03), ha="center", fontsize=7)
    fig.suptitle("Accuracy per viewpoint (test set)")
    path = Path(path)
    fig.savefig(path, dpi=90)
    return path


class ViewpointBreakdown(L.Callback):
    """At test time, depth d1 and pose error per bin of each true pose component (the paper's viewpoint figure).

    Logs ``test_view_<component>_bin<k>_{d1,error}`` to the loggers, keeps the rows in :attr:`table`
    and writes ``viewpoints.png`` into ``output_dir`` (default: the trainer's log directory). The d1 of an image is
    ``test_depth_d1``'s: valid pixels below the model's depth limit (``model.net.igd.max_depth``), sky excluded.

    Args:
        bins: uniform bins per component over the UAPD range.
        output_dir: folder of the figure; None: the trainer's log directory.
    """

    def __init__(self, bins: int = 5, output_dir: str | None = None) -> None:
        self.bins, self.output_dir = bins, output_dir
        self.records: list[Tensor] = []
        self.table: list[dict[str, Any]] = []
        self.figure: Path | None = None

    def on_test_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.records = []

    def on_test_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                          batch_idx: int, dataloader_idx: int = 0) -> None:
        if not isinstance(outputs, DAPMOutput) or not batch["has_pose"].any():
            return
        has_pose, pose = batch["has_pose"], batch["pose"].float()
        nan = torch.full((pose.shape[0],), math.nan, device=pose.device)
        depth_m, pose_pred = outputs.depth_m, outputs.pose_physical
        # the model's depth limit, as test_depth_d1 (its sky is excluded: a data set's grey 255 may mean 500 m)
        max_depth = depth_limit(pl_module)
        d1 = nan if depth_m is None else per_image_depth_metrics(depth_m, batch["depth"],
                                                                 max_depth=max_depth)["d1"].to(pose)
        error = torch.full_like(pose, math.nan) if pose_pred is None else (pose_pred - pose).abs().float()
        self.records.append(torch.cat([pose, d1[:, None], error], 1)[has_pose])

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        local = torch.cat(self.records) if self.records else torch.zeros(0, 9, device=pl_module.device)
        # every rank joins both collectives, with or without records; rows padded with NaN to a common count
        most = int(cast(Tensor, pl_module.all_gather(torch.tensor(local.shape[0], device=local.device))).max())
        padded = torch.cat([local, local.new_full((most - local.shape[0], 9), math.nan)])
        gathered = cast(Tensor, pl_module.all_gather(padded))
        records = gathered.flatten(0, 1) if gathered.ndim == 3 else gathered
        records = records[torch.isfinite(records[:, 0])]
        if records.shape[0] == 0:
            return
        self.table = viewpoint_table(records.cpu(), self.bins)
        log_dir = trainer.log_dir  # a broadcast under DDP: every rank asks, or rank 0 waits for the others forever
        if trainer.is_global_zero:
            values = {f"test_view_{r['component']}_bin{r['bin']}_{k}": r[k]
                      for r in self.table for k in ("d1", "error")}
            for logger in trainer.loggers:  # to the loggers only: the console table stays readable
                logger.log_metrics(values, step=trainer.global_step)
            folder = Path(self.output_dir or log_dir or ".")
            folder.mkdir(parents=True, exist_ok=True)
            self.figure = plot_viewpoints(self.table, folder / "viewpoints.png")
