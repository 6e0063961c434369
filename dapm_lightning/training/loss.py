"""DAPM's composite loss (paper Eq. 16-19), each term returned by name."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal, TypedDict

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dapm_lightning.geometry.bins import quantize
from dapm_lightning.geometry.constants import MIN_DEPTH_M
from dapm_lightning.geometry.depth_codec import decode_log_depth, encode_log_depth
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.geometry.precision import float32
from dapm_lightning.models.dapm import DAPMOutput, DepthPrediction, PosePrediction

IGNORE = -100
"""Class id of pixels that carry no bins target (invalid or sky)."""

PAPER_WEIGHTS: Mapping[str, float] = {"depth": 1.0, "pose": 10.0, "init_depth": 1.0, "init_pose": 1.0,
                                      "dq": 1.0, "pq": 1.0, "pd": 10.0}
"""Eq. 19: rho = 10 on the refined pose and on the IGD pose loss, 1 elsewhere."""

CODE_ONLY_WEIGHTS: Mapping[str, float] = {"grad": 10.0}
"""Terms only in the authors' released code (not in the paper's Eq. 19), with their weight there."""

DepthLossSpace = Literal["metric", "log_norm"]
AUTHORS_SILOG_EPS = 1e-3
"""The authors' scale-invariant loss clamps both maps at 1e-3 and adds 1e-3 under the square root."""


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
        depth_space: where Eq. 17 (``depth``, ``init_depth``) is computed. ``"metric"``: on depths in
            metres over the valid non-sky pixels of the whole batch (this project's default).
            ``"log_norm"``: the authors' released code: on the normalised log depth (grey / 255, the
            network's own output), per image over every pixel with a finite target >= 0 m, *sky and 0 m
            included* (Potsdam ground at height 0 is a target), both maps clamped
            at 1e-3 and ``alpha * sqrt(mean g^2 - lambda mean(g)^2 + 1e-3)``, then the mean over images.
            For the same relative error the metric space gives 1.4-3.4x larger values, which shifts
            the balance rho = 10 was chosen for; the paper configs use ``"log_norm"``.
        use_gradient_loss: the Laplacian-weighted gradient loss of the authors' released code (term
            ``grad``, weight ``weights["grad"]``, 10 there); not in the paper's Eq. 19, so off by default.
        sky_object_weight: weight of the sky stage's cross-entropy on the pixels that are not sky but lie above the
            horizon of the true pose (a tower, a tree or a mast standing against the sky), 1 elsewhere: the pixels the
            sky stage confuses, where calling them sky puts them at ``max_depth``. 1 (the paper's plain mean) by
            default.
    """

    weights: Mapping[str, float] = field(default_factory=_paper_weights)
    use_igd_loss: bool = True
    variance_focus: float = 0.85
    silog_scale: float = 10.0
    igd_loss_stride: int = 4
    depth_space: DepthLossSpace = "metric"
    use_gradient_loss: bool = False
    sky_object_weight: float = 1.0

    def __post_init__(self) -> None:
        known = {**PAPER_WEIGHTS, **CODE_ONLY_WEIGHTS}
        unknown = set(self.weights) - set(known)
        if unknown:
            raise ValueError(f"unknown loss weight(s) {sorted(unknown)}; known: {sorted(known)}")
        if self.depth_space not in ("metric", "log_norm"):
            raise ValueError(f"depth_space must be 'metric' or 'log_norm', got {self.depth_space!r}")
        if not self.sky_object_weight > 0:
            raise ValueError(f"model.loss.sky_object_weight must be above 0, got {self.sky_object_weight!r}")
        stride = self.igd_loss_stride
        if isinstance(stride, bool) or not (isinstance(stride, int) and stride >= 1):
            raise ValueError(f"model.loss.igd_loss_stride must be a whole number >= 1 (L_pd at 1 / stride of the image "
                             f"size; 4 by default), got {stride!r}")
        if not 0.0 <= self.variance_focus <= 1.0:  # above 1 the root's argument can be negative: clamped, no gradient
            raise ValueError(f"model.loss.variance_focus (lambda of Eq. 17) must be in [0, 1] (the paper's 0.85), "
                             f"got {self.variance_focus!r}")
        if not self.silog_scale > 0:
            raise ValueError(f"model.loss.silog_scale (alpha of Eq. 17) must be above 0 (the paper's 10), "
                             f"got {self.silog_scale!r}")
        object.__setattr__(self, "weights", {**known, **self.weights})


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


def silog_loss_per_image(pred: Tensor, target: Tensor, mask: Tensor, *, variance_focus: float = 0.85,
                         scale: float = 10.0, clamp: float = AUTHORS_SILOG_EPS, eps: float = AUTHORS_SILOG_EPS
                         ) -> Tensor:
    """Eq. 17 as the authors' code computes it: per image, then the mean over images.

    ``alpha * mean_b sqrt(mean(g^2) - lambda mean(g)^2 + eps)`` with ``g = log(max(pred, clamp)) -
    log(max(target, clamp))`` over the ``mask`` pixels of image ``b`` (``[B, 1, H, W]`` or ``[B, H, W]``,
    any units; the authors pass normalised log depth). Images without a masked pixel are left out;
    0 (with a graph) when none has one.
    """
    batch = pred.shape[0]
    pred, target, mask = pred.reshape(batch, -1), target.reshape(batch, -1), mask.reshape(batch, -1)
    g = torch.where(mask, torch.log(pred.clamp(min=clamp)) - torch.log(target.clamp(min=clamp)),
                    torch.zeros_like(pred))
    count = mask.sum(dim=1)
    used = count > 0
    if not used.any():
        return pred.sum() * 0.0
    n = count[used].to(pred.dtype)
    mean_sq, mean = (g[used] ** 2).sum(dim=1) / n, g[used].sum(dim=1) / n
    value = (mean_sq - variance_focus * mean ** 2).clamp(min=0.0) + eps
    return scale * torch.sqrt(value).mean()


def laplacian_gradient_loss(pred: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """The authors' code-only gradient loss on ``[B, 1, H, W]`` maps (normalised log depth there).

    With ``L(x) = 1 + laplace(x)`` (4-neighbour kernel, zero padding): ``mean((L(target) - L(pred))^2)
    + mean((target - pred)^2 * L(target))``, means over the ``mask`` pixels.
    """
    kernel = torch.tensor([[0.0, 1.0, 0.0], [1.0, -4.0, 1.0], [0.0, 1.0, 0.0]], dtype=pred.dtype,
                          device=pred.device).view(1, 1, 3, 3)
    lap_t = F.conv2d(target, kernel, padding=1) + 1.0
    lap_p = F.conv2d(pred, kernel, padding=1) + 1.0
    m = mask.to(pred.dtype)
    return _masked_mean((lap_t - lap_p) ** 2, m) + _masked_mean((target - pred) ** 2 * lap_t, m)


def _resize_nearest(x: Tensor, size: tuple[int, int]) -> Tensor:
    """``x`` at ``size``, each cell's top-left pixel: the coarse bins' targets.

    Centre pixels or each cell's shares of the bins measured no better at the quickstart's budget
    (docs/transfer.md, "Coarse bins supervised where their cells lie").
    """
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

    @float32
    def forward(self, out: DAPMOutput, targets: LossTargets) -> dict[str, Tensor]:
        terms: dict[str, Tensor] = {}
        if out.depth is not None:
            terms.update(self.depth_terms(out.depth, targets))
        if out.pose is not None:
            terms.update(self.pose_terms(out.pose, targets, out.depth))
        weights = self.config.weights
        terms["total"] = sum((weights[k] * v for k, v in terms.items()), torch.zeros(()))
        return terms

    def _eq17(self, pred_norm: Tensor, depth_m: Tensor, metric: Tensor, depth: DepthPrediction | None = None
              ) -> Tensor:
        """Eq. 17 of a normalised prediction: absolute log depth, or in the space of ``depth`` (its ``encode``)."""
        config, max_depth = self.config, self.igd.max_depth
        encode = encode_log_depth if depth is None else depth.encode
        decode = decode_log_depth if depth is None else depth.decode
        if config.depth_space == "log_norm":  # every finite target counts, 0 m (grey 0, e.g. Potsdam ground) too
            finite = torch.isfinite(depth_m) & (depth_m >= 0)
            target_norm = encode(torch.where(finite, depth_m, torch.zeros_like(depth_m)).clamp(0.0, max_depth),
                                 max_depth)
            return silog_loss_per_image(pred_norm, target_norm, finite, variance_focus=config.variance_focus,
                                        scale=config.silog_scale)
        return silog_loss(decode(pred_norm, max_depth), depth_m, metric,
                          variance_focus=config.variance_focus, scale=config.silog_scale)

    def depth_terms(self, depth: DepthPrediction, targets: LossTargets) -> dict[str, Tensor]:
        """``init_depth`` (Eq. 17), and with a refinement ``depth`` (Eq. 17) and ``dq`` (Eq. 16).

        Eq. 17 in the space :attr:`LossConfig.depth_space` names; ``grad`` (code-only) when enabled. The refined
        depth's terms and bins are in the network's depth parametrisation (``depth.encode``: absolute log depth,
        or the log ratio to the IGD of the pose it used); the initial depth is absolute.
        """
        depth_m, valid, sky = targets["depth"], targets["valid"], targets["sky"]
        metric = valid & ~sky & (depth_m > MIN_DEPTH_M)
        max_depth = self.igd.max_depth
        terms = {"init_depth": self._eq17(depth.depth_init_norm, depth_m, metric)}
        if not depth.refined:
            return terms
        terms["depth"] = self._eq17(depth.depth_norm, depth_m, metric, depth)
        if self.config.use_gradient_loss:
            target_norm = torch.where(valid, depth.encode(depth_m.clamp(0.0, max_depth), max_depth),
                                      torch.zeros_like(depth_m))
            terms["grad"] = laplacian_gradient_loss(depth.depth_norm, target_norm, valid)
        dq = depth.depth_norm.sum() * 0.0
        # the authors' space counts 0 m targets (Potsdam ground) in the bins too; sky stays out of the classes
        counted = (torch.isfinite(depth_m) & (depth_m >= 0) if self.config.depth_space == "log_norm" else valid)
        if depth.sky_logits is not None:
            bce = F.binary_cross_entropy_with_logits(depth.sky_logits, sky.float(), reduction="none")
            if self.config.sky_object_weight != 1.0:
                bce = bce * self._sky_weights(targets, metric)
            dq = dq + _masked_mean(bce, counted)
        depth_norm = depth.encode(torch.where(counted, depth_m, torch.zeros_like(depth_m)), max_depth)
        binned = counted & ~sky if self.config.depth_space == "log_norm" else metric
        for logits in depth.bin_logits:
            size = (logits.shape[-2], logits.shape[-1])
            classes = quantize(_resize_nearest(depth_norm, size), logits.shape[1])[:, 0]
            usable = _resize_nearest(binned, size)[:, 0] > 0.5
            if usable.any():
                dq = dq + F.cross_entropy(logits, torch.where(usable, classes, IGNORE), ignore_index=IGNORE)
        if depth.sky_logits is not None or depth.bin_logits:
            terms["dq"] = dq
        return terms

    def _sky_weights(self, targets: LossTargets, objects: Tensor) -> Tensor:
        """``[B, 1, H, W]`` weights of the sky stage's cross-entropy.

        :attr:`LossConfig.sky_object_weight` on ``objects`` (valid, not sky) above the horizon of the true pose (its IGD
        at the depth limit), 1 elsewhere and on images without a pose.
        """
        pose = targets["pose"]
        known = torch.isfinite(pose).all(dim=1)
        above = torch.zeros_like(objects)
        if known.any():
            size = (objects.shape[-2], objects.shape[-1])
            above[known] = self.igd.depth(pose[known].float(), size) >= self.igd.max_depth
        return 1.0 + (self.config.sky_object_weight - 1.0) * (above & objects).float()

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
