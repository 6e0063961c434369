"""Test-time outputs for the paper's figures: per-stage depth bins maps and a per-image results CSV."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

import cv2
import lightning as L
import numpy as np
import torch
from torch import Tensor

from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_KEYS, SKY_GREY
from dapm_lightning.geometry.depth_codec import encode_log_depth, norm_to_grey
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.metrics.depth import DEPTH_METRIC_NAMES, per_image_depth_metrics
from dapm_lightning.models.dapm import DAPMOutput


def depth_limit(pl_module: L.LightningModule) -> float:
    """The model's depth limit in metres (``model.net.igd.max_depth``), as the logged depth metrics use it."""
    return float(getattr(getattr(getattr(pl_module, "net_config", None), "igd", None), "max_depth", MAX_DEPTH_M))


def stage_maps(out: DAPMOutput, index: int, max_depth: float = MAX_DEPTH_M) -> dict[str, np.ndarray]:
    """The per-stage maps of image ``index`` as uint8 grey images, keyed by folder name.

    ``sky``: the binary stage thresholded at 0.5 (255 = beyond max depth); ``bins_<n>``: the arg-max class
    of each ``n``-bin stage scaled to ``255 * k / (n - 1)`` (the authors' figure); ``depth_init`` and
    ``depth``: the initial and refined normalised log depth (grey = 255 x). Stages at their own resolution.
    """
    depth = out.depth
    if depth is None:
        return {}
    maps = {"depth_init": norm_to_grey(depth.depth_init_norm[index, 0]),
            "depth": norm_to_grey(depth.log_depth_norm(max_depth)[index, 0])}
    if depth.sky_logits is not None:
        maps["sky"] = ((depth.sky_logits[index, 0] > 0).to(torch.uint8) * SKY_GREY).cpu().numpy()
    seen: dict[int, int] = {}
    for logits in depth.bin_logits:
        n = logits.shape[1]
        seen[n] = seen.get(n, 0) + 1
        key = f"bins_{n}" if seen[n] == 1 else f"bins_{n}_{seen[n]}"
        maps[key] = norm_to_grey(logits[index].argmax(dim=0).float() / max(1, n - 1))
    return maps


def igd_maps(out: DAPMOutput, batch: Any, igd: IGDSpec) -> dict[str, Tensor]:
    """The IGD of the predicted and of the true pose at the image size, ``[B, H, W]`` uint8 grey, by folder name.

    ``igd_pred`` and ``igd_true`` (the authors' ``p2d_pred`` / ``p2d_gt`` figure): ``255 x`` the normalised log
    IGD of the model's IGD specification. ``igd_true`` only for a batch whose images all have a pose.
    """
    if out.pose is None:
        return {}
    size = (int(batch["image"].shape[-2]), int(batch["image"].shape[-1]))
    maps = {"igd_pred": igd.depth_norm(out.pose.pose_norm.detach().double(), size)[:, 0]}
    has_pose = batch.get("has_pose")
    if has_pose is not None and bool(has_pose.all()):
        maps["igd_true"] = igd.depth_norm(igd.normalize(batch["pose"].double()), size)[:, 0]
    return {key: (value.float().clamp(0, 1) * 255.0).round().to(torch.uint8).cpu() for key, value in maps.items()}


class EvaluationOutputWriter(L.Callback):
    """Writes, during ``dapm-lightning test``, what the paper's PQB figure and a worst-image search need.

    - ``<dirpath>/maps/<stage>/<name>.png`` for every test image (``write_maps``): the sky map, each depth
      bins stage's arg-max class, the initial and the refined depth (:func:`stage_maps`), and the IGD of the
      predicted and of the true pose (``igd_pred``, ``igd_true``: :func:`igd_maps`);
    - ``<dirpath>/per_image.csv`` (``write_csv``), one row per image: ``name``, the true pose
      (``height, pitch, roll, fov``), the predicted pose (``pred_*``), its absolute errors (``err_*``) and the
      toolbox depth metrics of the image in metres (``depth_d1``, ``depth_abs_rel``, ...; NaN without a
      valid pixel). Sort it by ``depth_abs_rel`` to find the worst images.

    Under DDP each process writes its own ``per_image.rank<k>.csv`` (the maps do not collide: names differ).
    ``dirpath`` None: ``<trainer.log_dir or default_root_dir>/test_outputs``. ``max_depth`` (metres of grey 255,
    the limit of the per-image metrics' valid pixels) None: the model's ``model.net.igd.max_depth``, as the logged
    ``test_depth_*`` use.
    """

    __test__ = False  # not a pytest test class, whatever its name

    def __init__(self, dirpath: str | None = None, write_maps: bool = True, write_csv: bool = True,
                 max_depth: float | None = None) -> None:
        self.dirpath, self.write_maps, self.write_csv = dirpath, write_maps, write_csv
        self.limit = max_depth
        """``max_depth`` as given (None: the model's)."""
        self.max_depth = MAX_DEPTH_M if max_depth is None else max_depth
        """The limit in use: set from the model when a test starts."""
        self._rows: list[dict[str, Any]] = []
        self._root: Path | None = None

    def on_test_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        base = self.dirpath or str(Path(trainer.log_dir or trainer.default_root_dir) / "test_outputs")
        self._root, self._rows = Path(base), []
        self.max_depth = self.limit if self.limit is not None else depth_limit(pl_module)
        self._root.mkdir(parents=True, exist_ok=True)

    def on_test_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                          batch_idx: int, dataloader_idx: int = 0) -> None:
        if not isinstance(outputs, DAPMOutput) or self._root is None:
            return
        names = list(batch.get("name", [])) or [f"b{batch_idx:06d}_{i}" for i in range(batch["image"].shape[0])]
        metrics = (per_image_depth_metrics(outputs.depth_m, batch["depth"], max_depth=self.max_depth)
                   if outputs.depth_m is not None else {})
        config = getattr(pl_module, "net_config", None)
        igd_images = igd_maps(outputs, batch, config.igd) if self.write_maps and config is not None else {}
        for i, name in enumerate(names):
            stem = str(name).replace("/", "_").replace("\\", "_")  # sample names are stems already
            if self.write_maps:
                maps = {**stage_maps(outputs, i, self.max_depth),
                        **{key: value[i].numpy() for key, value in igd_images.items()}}
                for stage, image in maps.items():
                    folder = self._root / "maps" / stage
                    folder.mkdir(parents=True, exist_ok=True)
                    cv2.imwrite(str(folder / f"{stem}.png"), image)
            if self.write_csv:
                self._rows.append(self._row(stem, outputs, batch, metrics, i))

    def _row(self, name: str, out: DAPMOutput, batch: Any, metrics: dict[str, Tensor], i: int) -> dict[str, Any]:
        row: dict[str, Any] = {"name": name}
        has_pose = bool(batch["has_pose"][i]) if "has_pose" in batch else False
        true = batch["pose"][i].tolist() if has_pose else [math.nan] * 4
        pred = out.pose_physical[i].tolist() if out.pose_physical is not None else [math.nan] * 4
        for k, key in enumerate(POSE_KEYS):
            row[key], row[f"pred_{key}"], row[f"err_{key}"] = true[k], pred[k], abs(pred[k] - true[k])
        for metric in DEPTH_METRIC_NAMES:
            row[f"depth_{metric}"] = float(metrics[metric][i]) if metrics else math.nan
        if out.depth is not None:
            target = encode_log_depth(batch["depth"][i].double().clamp(0, self.max_depth), self.max_depth)
            refined = out.depth.log_depth_norm(self.max_depth)[i].double()
            row["depth_mae_grey"] = float((refined - target).abs().mean() * SKY_GREY)
        return row

    def on_test_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self.write_csv or self._root is None or not self._rows:
            return
        name = "per_image.csv" if trainer.world_size == 1 else f"per_image.rank{trainer.global_rank}.csv"
        with open(self._root / name, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(self._rows[0]))
            writer.writeheader()
            writer.writerows(self._rows)


__all__ = ["EvaluationOutputWriter", "igd_maps", "stage_maps"]
