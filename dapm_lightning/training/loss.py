"""DAPM's composite loss (paper Eq. 16-19), each term returned by name."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TypedDict

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dapm_lightning.geometry.bins import quantize
from dapm_lightning.geometry.constants import MIN_DEPTH_M
from dapm_lightning.geometry.depth_codec import decode_log_depth, encode_log_depth
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.models.dapm import DAPMOutput, DepthPrediction, PosePrediction

IGNORE = -100
"""Class id of pixels that carry no bins target (invalid or sky)."""

PAPER_WEIGHTS: Mapping[str, float] = {"depth": 1.0, "pose": 10.0, "init_depth": 1.0, "init_pose": 1.0,
                                      "dq": 1.0, "pq": 1.0, "pd": 10.0}
"""Eq. 19: rho = 10 on the refined pose and on the IGD pose loss, 1 elsewhere."""


def _paper_weights() -> dict[str, float]:
    return dict(PAPER_WEIGHTS)


@dataclass(frozen=True)
class LossConfig:
    """Settings of :class:`DAPMLoss`; in configs under ``model.loss``.

    Args:
        weights: per-term weights (``depth, pose, init_depth, init_pose, dq, pq, pd``); the paper's by default.
        use_igd_loss: the IGD dense pose loss ``L_pd`` (MSE between the IGD of the predicted and of the
            true pose, normalised log space).
        variance_focus: lambda of Eq. 17 (0.85).
        silog_scale: alpha of Eq. 17 (10).
        igd_loss_stride: ``L_pd`` is computed at ``1 / igd_loss_stride`` of the image size.
    """

    weights: Mapping[str, float] = field(default_factory=_paper_weights)
    use_igd_loss: bool = True
    variance_focus: float = 0.85
    silog_scale: float = 10.0
    igd_loss_stride: int = 4

    def __post_init__(self) -> None:
        unknown = set(self.weights) - set(PAPER_WEIGHTS)
        if unknown:
            raise ValueError(f"unknown loss weight(s) {sorted(unknown)}; known: {sorted(PAPER_WEIGHTS)}")
        object.__setattr__(self, "weights", {**PAPER_WEIGHTS, **self.weights})


class LossTargets(TypedDict, total=False):
    """Targets in physical units.

    ``depth`` ``[B,1,H,W]`` m, ``sky``/``valid`` ``[B,1,H,W]`` bool, ``pose`` ``[B,4]``
    (m, deg, deg, deg), ``has_pose`` ``[B]`` bool.
    """

    depth: Tensor
    sky: Tensor
    valid: Tensor
    pose: Tensor
    has_pose: Tensor


def silog_loss(pred_m: Tensor, target_m: Tensor, mask: Tensor, *, variance_focus: float = 0.85,
               scale: float = 10.0, min_depth: float = MIN_DEPTH_M) -> Tensor:
    """Scale-invariant log loss (Eq. 17): ``alpha * sqrt(mean(g^2) - lambda * mean(g)^2)`` over ``mask``.

    ``g = log(pred) - log(target)`` on the valid pixels of the whole batch; 0 (with a graph) when none.
    """
    if not mask.any():
        return pred_m.sum() * 0.0
    g = torch.log(pred_m[mask].clamp(min=min_depth)) - torch.log(target_m[mask].clamp(min=min_depth))
    value = (g * g).mean() - variance_focus * g.mean() ** 2
    return scale * torch.sqrt(value.clamp(min=1e-8))


def _resize_nearest(x: Tensor, size: tuple[int, int]) -> Tensor:
    if x.shape[-2:] == size:
        return x
    return F.interpolate(x.float(), size=size, mode="nearest")


def _masked_mean(values: Tensor, mask: Tensor) -> Tensor:
    return (values * mask).sum() / mask.sum().clamp(min=1)


class DAPMLoss(nn.Module):
    """``L_total = (L_depth + rho L_pose) + (L_init-depth + L_init-pose) + L_dq + L_pq + rho L_pd`` (Eq. 19).

    Quantisation targets are derived here from the depth and pose targets (integer classes).
    Terms of switched-off parts are absent. ``forward`` returns ``{term: tensor}`` with keys
    ``depth, init_depth, pose, init_pose, dq, pq, pd`` (those that apply) and ``total``.

    Args:
        config: weights and switches (:class:`LossConfig`).
        igd: the IGD specification, the network's (``DAPMConfig.igd``).
    """

    def __init__(self, config: LossConfig | None = None, igd: IGDSpec | None = None) -> None:
        super().__init__()
        self.config = config or LossConfig()
        self.igd = igd or IGDSpec()

    def forward(self, out: DAPMOutput, targets: LossTargets) -> dict[str, Tensor]:
        terms: dict[str, Tensor] = {}
        if out.depth is not None:
            terms.update(self.depth_terms(out.depth, targets))
        if out.pose is not None:
            terms.update(self.pose_terms(out.pose, targets, out.depth))
        weights = self.config.weights
        terms["total"] = sum((weights[k] * v for k, v in terms.items()), torch.zeros(()))
        return terms

    def depth_terms(self, depth: DepthPrediction, targets: LossTargets) -> dict[str, Tensor]:
        """``init_depth`` (Eq. 17), and with a refinement ``depth`` (Eq. 17) and ``dq`` (Eq. 16)."""
        depth_m, valid, sky = targets["depth"], targets["valid"], targets["sky"]
        metric = valid & ~sky & (depth_m > MIN_DEPTH_M)
        config, max_depth = self.config, self.igd.max_depth
        silog = dict(variance_focus=config.variance_focus, scale=config.silog_scale)
        terms = {"init_depth": silog_loss(decode_log_depth(depth.depth_init_norm, max_depth), depth_m, metric,
                                          **silog)}
        if not depth.refined:
            return terms
        terms["depth"] = silog_loss(decode_log_depth(depth.depth_norm, max_depth), depth_m, metric, **silog)
        dq = depth.depth_norm.sum() * 0.0
        if depth.sky_logits is not None:
            bce = F.binary_cross_entropy_with_logits(depth.sky_logits, sky.float(), reduction="none")
            dq = dq + _masked_mean(bce, valid)
        depth_norm = encode_log_depth(depth_m, max_depth)
        for logits in depth.bin_logits:
            size = (logits.shape[-2], logits.shape[-1])
            classes = quantize(_resize_nearest(depth_norm, size), logits.shape[1])[:, 0]
            usable = _resize_nearest(metric, size)[:, 0] > 0.5
            if usable.any():
                dq = dq + F.cross_entropy(logits, torch.where(usable, classes, IGNORE), ignore_index=IGNORE)
        if depth.sky_logits is not None or depth.bin_logits:
            terms["dq"] = dq
        return terms

    def pose_terms(self, pose: PosePrediction, targets: LossTargets,
                   depth: DepthPrediction | None = None) -> dict[str, Tensor]:
        """``init_pose``, and ``pose`` + ``pq`` (Eq. 18) with P-PQB, ``pd`` with the IGD loss (MSE each)."""
        has_pose = targets.get("has_pose")
        if has_pose is None:
            has_pose = torch.isfinite(targets["pose"]).all(dim=1)
        keys = ["init_pose"] + (["pose", "pq"] if pose.refined else []) + (["pd"] if self.config.use_igd_loss else [])
        zero = pose.pose_norm.sum() * 0.0
        if not has_pose.any():
            return dict.fromkeys(keys, zero)
        true_norm = self.igd.normalize(targets["pose"][has_pose])
        terms = {"init_pose": F.mse_loss(pose.pose_init_norm[has_pose], true_norm)}
        if pose.refined:
            terms["pose"] = F.mse_loss(pose.pose_norm[has_pose], true_norm)
            terms["pq"] = sum((F.cross_entropy(logits[has_pose].flatten(0, 1),
                                               quantize(true_norm, logits.shape[-1]).flatten())
                               for logits in pose.bin_logits), zero)
        if self.config.use_igd_loss:
            size = self._igd_size(targets)
            predicted = self.igd.depth_norm(pose.pose_norm[has_pose], size)
            with torch.no_grad():
                true = self.igd.depth_norm(true_norm, size)
            terms["pd"] = F.mse_loss(predicted, true)
        return terms

    def _igd_size(self, targets: LossTargets) -> tuple[int, int]:
        stride = self.config.igd_loss_stride
        reference = targets.get("depth")
        if reference is None:
            return (64, 64)
        return (max(1, reference.shape[-2] // stride), max(1, reference.shape[-1] // stride))
