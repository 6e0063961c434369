"""Depth metrics as a ``torchmetrics.Metric`` (design.md §5): the toolbox protocol, per image, in metres."""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor
from torchmetrics import Metric

from dapm_lightning.geometry.constants import MAX_DEPTH_M, MIN_DEPTH_M
from dapm_lightning.geometry.depth_codec import encode_log_depth

DEPTH_METRIC_NAMES = ("d1", "d2", "d3", "abs_rel", "sq_rel", "rmse", "rmse_log", "log10", "silog")


def per_image_depth_metrics(pred: Tensor, target: Tensor, *, min_depth: float = MIN_DEPTH_M,
                            max_depth: float = MAX_DEPTH_M, space: Literal["metric", "uapd_log"] = "metric"
                            ) -> dict[str, Tensor]:
    """Toolbox depth metrics of each image over its valid pixels.

    Args:
        pred, target: ``[B, 1, H, W]`` or ``[B, H, W]`` metres.
        min_depth, max_depth: valid pixels have ``min_depth < target < max_depth`` (strict);
            predictions are clamped to ``[min_depth, max_depth]``.
        space: ``"metric"`` (metres) or ``"uapd_log"``: both maps are first converted to the paper's
            8-bit log scale ``255 * encode_log_depth(d)`` (continuous), as the paper's Table 4 did.

    Returns:
        ``{name: [B]}`` for :data:`DEPTH_METRIC_NAMES`; NaN for an image without valid pixels.
    """
    if pred.shape != target.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and target {tuple(target.shape)} must have the same shape")
    batch = pred.shape[0]
    pred = pred.reshape(batch, -1).double().clamp(min_depth, max_depth)
    target = target.reshape(batch, -1).double()
    mask = (target > min_depth) & (target < max_depth) & torch.isfinite(target)
    if space == "uapd_log":
        pred = 255.0 * encode_log_depth(pred, max_depth)
        target = 255.0 * encode_log_depth(target.clamp(min=0.0), max_depth)
        mask &= target > 0
        pred = pred.clamp(min=1e-6)
    elif space != "metric":
        raise ValueError(f"space must be 'metric' or 'uapd_log', got {space!r}")
    safe_target = torch.where(mask, target, torch.ones_like(target))
    safe_pred = torch.where(mask, pred, torch.ones_like(pred))
    count = mask.sum(dim=1).double()

    def mean(x: Tensor) -> Tensor:
        return torch.where(mask, x, torch.zeros_like(x)).sum(dim=1) / count

    ratio = torch.maximum(safe_target / safe_pred, safe_pred / safe_target)
    diff = safe_target - safe_pred
    log_diff = torch.log(safe_pred) - torch.log(safe_target)
    result = {
        "d1": mean((ratio < 1.25).double()), "d2": mean((ratio < 1.25 ** 2).double()),
        "d3": mean((ratio < 1.25 ** 3).double()),
        "abs_rel": mean(diff.abs() / safe_target), "sq_rel": mean(diff ** 2 / safe_target),
        "rmse": torch.sqrt(mean(diff ** 2)), "rmse_log": torch.sqrt(mean(log_diff ** 2)),
        "log10": mean((torch.log10(safe_target) - torch.log10(safe_pred)).abs()),
        "silog": 100.0 * torch.sqrt((mean(log_diff ** 2) - mean(log_diff) ** 2).clamp(min=0.0)),
    }
    return {k: torch.where(count > 0, v, torch.full_like(v, math.nan)).float() for k, v in result.items()}


class DepthMetrics(Metric):
    """``d1 d2 d3 abs_rel sq_rel rmse rmse_log log10 silog``: per image, then the mean over images.

    The Monocular-Depth-Estimation-Toolbox protocol of the paper's Table 4 (design.md §5). Images
    without a valid pixel are skipped; with none at all every value is NaN. States are sums and a
    count, so the DDP reduction is exact.

    Example:
        >>> m = DepthMetrics()
        >>> m.update(torch.full((1, 1, 2, 2), 10.0), torch.full((1, 1, 2, 2), 8.0))
        >>> round(m.compute()["abs_rel"].item(), 3)
        0.25
    """

    full_state_update = False
    higher_is_better = None
    images: Tensor

    def __init__(self, min_depth: float = MIN_DEPTH_M, max_depth: float = MAX_DEPTH_M,
                 space: Literal["metric", "uapd_log"] = "metric", **kwargs: object) -> None:
        super().__init__(**kwargs)
        self.min_depth, self.max_depth, self.space = min_depth, max_depth, space
        for name in DEPTH_METRIC_NAMES:
            self.add_state(f"sum_{name}", default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("images", default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, pred: Tensor, target: Tensor) -> None:
        """``pred``, ``target``: ``[B, 1, H, W]`` or ``[B, H, W]`` metres."""
        values = per_image_depth_metrics(pred, target, min_depth=self.min_depth, max_depth=self.max_depth,
                                         space=self.space)
        counted = torch.isfinite(values["d1"])
        for name in DEPTH_METRIC_NAMES:
            setattr(self, f"sum_{name}", getattr(self, f"sum_{name}") + values[name][counted].double().sum())
        self.images = self.images + counted.sum()

    def compute(self) -> dict[str, Tensor]:
        return {name: (getattr(self, f"sum_{name}") / self.images).float() if self.images > 0
                else torch.tensor(math.nan) for name in DEPTH_METRIC_NAMES}
