"""Pose metrics as ``torchmetrics.Metric`` subclasses (docs/model.md, "Pose metrics").

:class:`PoseMetrics`: median error and GeoCalib's AUC per component; :class:`AuthorsPoseMetrics`: the authors'
protocol (3-point AUC, MAE).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch import Tensor
from torchmetrics import Metric
from torchmetrics.utilities import dim_zero_cat
from torchmetrics.utilities.distributed import gather_all_tensors

from dapm_lightning.geometry.constants import POSE_KEYS


def auc_of_recall(errors: Tensor, threshold: float, min_error: float | None = None) -> Tensor:
    """Area under the recall-vs-error curve up to ``threshold``, divided by it (GeoCalib's ``compute_auc``).

    The curve joins ``(0, 0)`` and ``(e_i, i / n)`` for the sorted errors; the recall at ``threshold`` counts the
    errors equal to it. ``min_error``: as GeoCalib's option, the errors at or below it count as perfect: the curve
    starts at their share ``m`` and runs ``(0, m)``, ``(min_error, m)``, then on through the larger errors.
    """
    device = errors.device
    errors = torch.sort(errors.detach().double().cpu()).values
    count = errors.numel()
    if count == 0:
        return torch.tensor(math.nan, device=device)
    recall = torch.arange(1, count + 1, dtype=torch.float64) / count
    if min_error is None:
        start_error, start_recall = torch.zeros(1, dtype=torch.float64), torch.zeros(1, dtype=torch.float64)
    else:
        below = int(torch.searchsorted(errors, torch.tensor(min_error, dtype=torch.float64), right=True))
        errors, recall = errors[below:], recall[below:]
        start_error = torch.tensor([0.0, min_error], dtype=torch.float64)
        start_recall = torch.full((2,), below / count, dtype=torch.float64)
    errors, recall = torch.cat([start_error, errors]), torch.cat([start_recall, recall])
    last = int(torch.searchsorted(errors, torch.tensor(threshold, dtype=torch.float64), right=True))
    curve_recall = torch.cat([recall[:last], recall[last - 1:last]])
    curve_error = torch.cat([errors[:last], torch.tensor([threshold], dtype=torch.float64)])
    return (torch.trapezoid(curve_recall, curve_error) / threshold).to(device)


class PoseMetrics(Metric):
    """Per component (height m; pitch, roll, fov deg): median absolute error and AUC@thresholds.

    Keys ``<component>_median`` and ``<component>_auc<t>`` (e.g. ``roll_auc5``). All errors are kept
    (``cat`` state), so the median and AUC under DDP are those of the whole set.

    Args:
        thresholds: AUC thresholds (degrees, metres for height).
        min_error: GeoCalib's ``compute_auc`` option (its evaluation passes 1): errors at or below it count as
            perfect in the AUC (:func:`auc_of_recall`); the median is of the errors as they are. Off by default.
    """

    full_state_update = False
    higher_is_better = None
    errors: list[Tensor] | Tensor  # a list of [B, 4] before a DDP sync, one tensor after

    def __init__(self, thresholds: Sequence[float] = (1.0, 5.0, 10.0), min_error: float | None = None,
                 **kwargs: object) -> None:
        super().__init__(**kwargs)
        self.thresholds, self.min_error = tuple(thresholds), min_error
        self.add_state("errors", default=[], dist_reduce_fx="cat")

    def update(self, pred: Tensor, target: Tensor) -> None:
        """``pred``, ``target``: ``[B, 4]`` (height m, pitch deg, roll deg, fov deg)."""
        if pred.shape != target.shape or pred.shape[-1:] != (4,):
            raise ValueError(f"pred {tuple(pred.shape)} and target {tuple(target.shape)} must both be [B, 4]")
        assert isinstance(self.errors, list)
        self.errors.append((pred.detach().double() - target.double()).abs())

    def _sync_dist(self, dist_sync_fn: Callable[..., Any] = gather_all_tensors,
                   process_group: Any | None = None) -> None:
        """Gather the errors (DDP), a process without any (no image with a pose) taking part with ``[0, 4]``.

        torchmetrics' own stand-in for an empty list is a 1-D float32 tensor, which the others' ``[B, 4]`` float64
        errors do not gather with.
        """
        if isinstance(self.errors, list) and not self.errors:
            self.errors = [torch.zeros(0, 4, dtype=torch.float64, device=self.device)]
        super()._sync_dist(dist_sync_fn, process_group)

    def compute(self) -> dict[str, Tensor]:
        errors = self.errors
        if isinstance(errors, list):
            errors = dim_zero_cat(errors) if errors else torch.zeros(0, 4, dtype=torch.float64, device=self.device)
        result: dict[str, Tensor] = {}
        for k, key in enumerate(POSE_KEYS):
            component = errors[:, k]
            result[f"{key}_median"] = (torch.quantile(component, 0.5) if component.numel()
                                       else torch.tensor(math.nan, device=self.device)).float()
            for t in self.thresholds:
                result[f"{key}_auc{t:g}"] = auc_of_recall(component, t, self.min_error).float()
        return result


def authors_auc(recalls: Sequence[float] | Tensor, thresholds: Sequence[float]) -> list[Tensor]:
    """The authors' AUC (``test.py``'s ``compute_auc``): the trapezoid through (0, 0) and (t_k, recall at t_k).

    With thresholds (1, 5, 10) the curve has only the points (0, 0), (1, r1), (5, r5), (10, r10); AUC@t is the
    area up to t divided by t. Coarser than :func:`auc_of_recall`, which follows every error.
    """
    xs = [0.0, *(float(t) for t in thresholds)]
    ys = [torch.zeros((), dtype=torch.float64), *(torch.as_tensor(r, dtype=torch.float64) for r in recalls)]
    areas, area = [], torch.zeros((), dtype=torch.float64)
    for k in range(1, len(xs)):
        area = area + 0.5 * (ys[k - 1] + ys[k]) * (xs[k] - xs[k - 1])
        areas.append(area / xs[k])
    return areas


class AuthorsPoseMetrics(Metric):
    """The authors' pose protocol (``test.py``): per component the 3-point AUC and the mean absolute error.

    Keys ``<component>_auc<t>`` (:func:`authors_auc`, recall = share of errors ``<= t``) and
    ``<component>_mae``; logged as ``<stage>_poseauthors_*``. The paper's Table 8 AUC figures come from this
    protocol. Sum states (counts and sums), so the values under DDP are those of the whole set.

    Args:
        thresholds: increasing AUC thresholds (degrees, metres for height); the authors' (1, 5, 10).
    """

    full_state_update = False
    higher_is_better = None
    within: Tensor
    abs_sum: Tensor
    count: Tensor

    def __init__(self, thresholds: Sequence[float] = (1.0, 5.0, 10.0), **kwargs: object) -> None:
        super().__init__(**kwargs)
        self.thresholds = tuple(float(t) for t in thresholds)
        if not self.thresholds or any(b <= a for a, b in zip(self.thresholds, self.thresholds[1:])) \
                or self.thresholds[0] <= 0:
            raise ValueError(f"thresholds must be positive and increasing, got {list(thresholds)}")
        self.add_state("within", default=torch.zeros(4, len(self.thresholds), dtype=torch.float64),
                       dist_reduce_fx="sum")
        self.add_state("abs_sum", default=torch.zeros(4, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", default=torch.zeros((), dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, pred: Tensor, target: Tensor) -> None:
        """``pred``, ``target``: ``[B, 4]`` (height m, pitch deg, roll deg, fov deg)."""
        if pred.shape != target.shape or pred.shape[-1:] != (4,):
            raise ValueError(f"pred {tuple(pred.shape)} and target {tuple(target.shape)} must both be [B, 4]")
        errors = (pred.detach().double() - target.double()).abs()
        thresholds = torch.tensor(self.thresholds, dtype=torch.float64, device=errors.device)
        self.within += (errors[:, :, None] <= thresholds).sum(dim=0).double()
        self.abs_sum += errors.sum(dim=0)
        self.count += errors.shape[0]

    def compute(self) -> dict[str, Tensor]:
        result: dict[str, Tensor] = {}
        count = self.count
        for k, key in enumerate(POSE_KEYS):
            recalls = self.within[k] / count
            for t, auc in zip(self.thresholds, authors_auc(recalls, self.thresholds)):
                result[f"{key}_auc{t:g}"] = auc.float()
            result[f"{key}_mae"] = (self.abs_sum[k] / count).float()
        return result
