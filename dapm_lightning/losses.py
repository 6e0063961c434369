"""DAPM's composite loss (paper Eq. 16-19), each term returned by name."""

from __future__ import annotations

from collections.abc import Mapping
from typing import TypedDict

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dapm_lightning.geometry.bins import quantize
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_RANGES
from dapm_lightning.geometry.depth_codec import decode_log_depth, encode_log_depth
from dapm_lightning.geometry.igd import DepthKind, IGDModel
from dapm_lightning.geometry.pose import normalize_pose
from dapm_lightning.models.dapm import DAPMOutput
from dapm_lightning.models.igd_branch import igd_norm_from_pose

IGNORE = -100
"""Class id of pixels that carry no bins target (invalid or sky)."""


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
               scale: float = 10.0, min_depth: float = 1e-3) -> Tensor:
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
    Terms of switched-off branches are absent. ``forward`` returns ``{term: tensor}`` with keys
    ``depth, init_depth, pose, init_pose, dq, pq, pd`` (those that apply) and ``total``.

    Args:
        weights: per-term weights; defaults are the paper's (rho = 10 on ``pose`` and ``pd``).
        use_igd_loss: the IGD dense pose loss ``L_pd``: MSE between the IGD of the predicted and the
            true pose in the normalised log space, computed at ``1 / igd_loss_stride`` of the image size.
        variance_focus, silog_scale: lambda = 0.85 and alpha = 10 of Eq. 17.
    """

    default_weights: Mapping[str, float] = {"depth": 1.0, "pose": 10.0, "init_depth": 1.0, "init_pose": 1.0,
                                            "dq": 1.0, "pq": 1.0, "pd": 10.0}

    def __init__(self, weights: Mapping[str, float] | None = None, *, use_igd_loss: bool = True,
                 igd_model: IGDModel = "pinhole", depth_kind: DepthKind = "range", max_depth: float = MAX_DEPTH_M,
                 variance_focus: float = 0.85, silog_scale: float = 10.0, igd_loss_stride: int = 4,
                 pose_ranges: Mapping[str, tuple[float, float]] = POSE_RANGES) -> None:
        super().__init__()
        unknown = set(weights or {}) - set(self.default_weights)
        if unknown:
            raise ValueError(f"unknown loss weight(s) {sorted(unknown)}; known: {sorted(self.default_weights)}")
        self.weights = {**self.default_weights, **(weights or {})}
        self.use_igd_loss = use_igd_loss
        self.igd_model, self.depth_kind, self.max_depth = igd_model, depth_kind, max_depth
        self.variance_focus, self.silog_scale = variance_focus, silog_scale
        self.igd_loss_stride = igd_loss_stride
        self.pose_ranges = dict(pose_ranges)

    def forward(self, out: DAPMOutput, targets: LossTargets) -> dict[str, Tensor]:
        terms: dict[str, Tensor] = {}
        if out.depth_norm is not None:
            self._depth_terms(out, targets, terms)
        if out.pose_norm is not None:
            self._pose_terms(out, targets, terms)
        terms["total"] = sum((self.weights[k] * v for k, v in terms.items()), torch.zeros(()))
        return terms

    def _depth_terms(self, out: DAPMOutput, targets: LossTargets, terms: dict[str, Tensor]) -> None:
        depth, valid, sky = targets["depth"], targets["valid"], targets["sky"]
        metric = valid & ~sky & (depth > 1e-3)
        silog = dict(variance_focus=self.variance_focus, scale=self.silog_scale)
        assert out.depth_init_norm is not None and out.depth_norm is not None
        terms["init_depth"] = silog_loss(decode_log_depth(out.depth_init_norm, self.max_depth), depth, metric, **silog)
        if out.sky_logits is None and not out.depth_bin_logits:
            return  # no D-PQB: the refined depth is the initial one
        terms["depth"] = silog_loss(decode_log_depth(out.depth_norm, self.max_depth), depth, metric, **silog)
        dq = out.depth_norm.sum() * 0.0
        if out.sky_logits is not None:
            bce = F.binary_cross_entropy_with_logits(out.sky_logits, sky.float(), reduction="none")
            dq = dq + _masked_mean(bce, valid)
        depth_norm = encode_log_depth(depth, self.max_depth)
        for logits in out.depth_bin_logits:
            size = (logits.shape[-2], logits.shape[-1])
            classes = quantize(_resize_nearest(depth_norm, size), logits.shape[1])[:, 0]
            usable = _resize_nearest(metric, size)[:, 0] > 0.5
            if usable.any():
                dq = dq + F.cross_entropy(logits, torch.where(usable, classes, IGNORE), ignore_index=IGNORE)
        terms["dq"] = dq

    def _pose_terms(self, out: DAPMOutput, targets: LossTargets, terms: dict[str, Tensor]) -> None:
        assert out.pose_norm is not None and out.pose_init_norm is not None
        has_pose = targets.get("has_pose")
        if has_pose is None:
            has_pose = torch.isfinite(targets["pose"]).all(dim=1)
        zero = out.pose_norm.sum() * 0.0
        if not has_pose.any():
            for key in ("pose", "init_pose", "pq", "pd"):
                terms[key] = zero
            return
        true_norm = normalize_pose(targets["pose"][has_pose], self.pose_ranges)
        terms["init_pose"] = F.mse_loss(out.pose_init_norm[has_pose], true_norm)
        if out.pose_bin_logits:
            terms["pose"] = F.mse_loss(out.pose_norm[has_pose], true_norm)
            terms["pq"] = sum((F.cross_entropy(logits[has_pose].flatten(0, 1),
                               quantize(true_norm, logits.shape[-1]).flatten()) for logits in out.pose_bin_logits),
                              zero)
        if self.use_igd_loss:
            size = self._igd_size(out, targets)
            kwargs = dict(model=self.igd_model, depth_kind=self.depth_kind, max_depth=self.max_depth,
                          pose_ranges=self.pose_ranges)
            predicted = igd_norm_from_pose(out.pose_norm[has_pose], size, **kwargs)
            with torch.no_grad():
                true = igd_norm_from_pose(true_norm, size, **kwargs)
            terms["pd"] = F.mse_loss(predicted, true)

    def _igd_size(self, out: DAPMOutput, targets: LossTargets) -> tuple[int, int]:
        reference = targets.get("depth", out.depth_norm)
        if reference is None:
            return (64, 64)
        stride = self.igd_loss_stride
        return (max(1, reference.shape[-2] // stride), max(1, reference.shape[-1] // stride))
