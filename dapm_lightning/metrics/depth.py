"""Depth metrics as ``torchmetrics.Metric`` subclasses (docs/model.md, "Depth metrics"), two protocols.

- :class:`DepthMetrics`: the Monocular-Depth-Estimation-Toolbox protocol the paper cites, per image over
  valid non-sky pixels, in metres (primary; ``space="uapd_log"`` runs the same protocol on grey levels).
- :class:`AuthorsDepthMetrics`: the authors' released evaluation, on grey levels of their 8-bit log
  encoding, every pixel including sky, pixels pooled; the only one comparable with the paper's Table 4.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor
from torchmetrics import Metric

from dapm_lightning.geometry.constants import MAX_DEPTH_M, MIN_DEPTH_M, SKY_GREY
from dapm_lightning.geometry.depth_codec import log_depth_grey

DEPTH_METRIC_NAMES = ("d1", "d2", "d3", "abs_rel", "sq_rel", "rmse", "rmse_log", "log10", "silog")


def per_image_depth_metrics(pred: Tensor, target: Tensor, *, min_depth: float = MIN_DEPTH_M,
                            max_depth: float = MAX_DEPTH_M, space: Literal["metric", "uapd_log"] = "metric"
                            ) -> dict[str, Tensor]:
    """Toolbox depth metrics of each image over its valid pixels.

    Args:
        pred, target: ``[B, 1, H, W]`` or ``[B, H, W]`` metres.
        min_depth, max_depth: valid pixels have ``min_depth < target < max_depth`` (strict);
            predictions are clamped to ``[min_depth, max_depth]``.
        space: ``"metric"`` (metres) or ``"uapd_log"``: both maps are first converted to grey levels of
            the 8-bit log encoding ``255 * encode_log_depth(d)`` (continuous); still the toolbox protocol
            (per image, sky excluded), so *not* the authors' evaluation: see :class:`AuthorsDepthMetrics`.

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
        pred = log_depth_grey(pred, max_depth)
        target = log_depth_grey(target.clamp(min=0.0), max_depth)
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

    The Monocular-Depth-Estimation-Toolbox protocol the paper cites (docs/model.md, "Depth metrics"). Images
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
                else torch.tensor(math.nan, device=self.device) for name in DEPTH_METRIC_NAMES}


AUTHORS_DEPTH_METRIC_NAMES = ("d1", "d2", "d3", "abs_rel", "sq_rel", "rmse_grey", "rmse_unit", "rmse_log",
                              "log10", "silog")
"""Keys of :class:`AuthorsDepthMetrics`: RMS in grey levels (0-255) and in [0, 1] units (grey / 255)."""

_POOLED_SUMS = ("d1", "d2", "d3", "abs_rel", "sq_rel", "sq_err", "log_sq", "log", "log10")


class AuthorsDepthMetrics(Metric):
    """The authors' released depth evaluation (docs/model.md, "Depth metrics"), for comparison with the paper's Table 4.

    Both maps become grey levels of the 8-bit log encoding (``255 * encode_log_depth(d)``, continuous),
    clamped at ``1e-3``; every pixel with a finite target counts, sky (grey 255) included; pixels are
    pooled over the whole evaluation rather than averaged per image. Ratios (``d1-d3``, ``abs_rel``,
    ``log10``, ``rmse_log``, ``silog``) are the same in grey levels and in [0, 1] units; RMS is not and is
    reported in both: ``rmse_grey`` (grey levels, what the authors' code prints) and ``rmse_unit``
    (``rmse_grey / 255``; the paper's Table 4 RMS of 0.103 fits these units only). ``sq_rel`` is in grey
    levels. States are sums and a pixel count (exact under DDP). (The authors' script reports the last
    image only; this pools all of them, as their training-time validation does.)

    Example:
        >>> m = AuthorsDepthMetrics()
        >>> m.update(torch.full((1, 1, 2, 2), 1000.0), torch.full((1, 1, 2, 2), 1000.0))
        >>> m.compute()["d1"].item(), m.compute()["rmse_grey"].item()
        (1.0, 0.0)
    """

    full_state_update = False
    higher_is_better = None
    pixels: Tensor

    def __init__(self, max_depth: float = MAX_DEPTH_M, clamp: float = 1e-3, **kwargs: object) -> None:
        super().__init__(**kwargs)
        self.max_depth, self.clamp = max_depth, clamp
        for name in _POOLED_SUMS:
            self.add_state(f"sum_{name}", default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("pixels", default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")

    def grey(self, depth_m: Tensor) -> Tensor:
        """Metres -> grey levels (:func:`log_depth_grey` of ``clamp(d, 0, max_depth)``), clamped at ``clamp``."""
        return log_depth_grey(depth_m.double().clamp(0.0, self.max_depth), self.max_depth).clamp(min=self.clamp)

    def update(self, pred: Tensor, target: Tensor) -> None:
        """``pred``, ``target``: ``[B, 1, H, W]`` or ``[B, H, W]`` metres (sky at ``max_depth``)."""
        if pred.shape != target.shape:
            raise ValueError(f"pred {tuple(pred.shape)} and target {tuple(target.shape)} must have the same shape")
        mask = torch.isfinite(target)
        p, t = self.grey(pred)[mask], self.grey(target)[mask]
        ratio = torch.maximum(p / t, t / p)
        diff, log_diff = t - p, torch.log(p) - torch.log(t)
        values = {"d1": (ratio < 1.25).double(), "d2": (ratio < 1.25 ** 2).double(),
                  "d3": (ratio < 1.25 ** 3).double(), "abs_rel": diff.abs() / t, "sq_rel": diff ** 2 / t,
                  "sq_err": diff ** 2, "log_sq": log_diff ** 2, "log": log_diff,
                  "log10": (torch.log10(p) - torch.log10(t)).abs()}
        for name, value in values.items():
            setattr(self, f"sum_{name}", getattr(self, f"sum_{name}") + value.sum())
        self.pixels = self.pixels + mask.sum()

    def compute(self) -> dict[str, Tensor]:
        if self.pixels == 0:
            return {name: torch.tensor(math.nan, device=self.device) for name in AUTHORS_DEPTH_METRIC_NAMES}
        mean = {name: getattr(self, f"sum_{name}") / self.pixels for name in _POOLED_SUMS}
        rmse_grey = torch.sqrt(mean["sq_err"])
        result = {"d1": mean["d1"], "d2": mean["d2"], "d3": mean["d3"], "abs_rel": mean["abs_rel"],
                  "sq_rel": mean["sq_rel"], "rmse_grey": rmse_grey, "rmse_unit": rmse_grey / SKY_GREY,
                  "rmse_log": torch.sqrt(mean["log_sq"]), "log10": mean["log10"],
                  "silog": 100.0 * torch.sqrt((mean["log_sq"] - mean["log"] ** 2).clamp(min=0.0))}
        return {k: v.float() for k, v in result.items()}
