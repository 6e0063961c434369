"""Progressive Quantization Bins (paper §PQB): coarse-to-fine per-pixel depth bins and per-component pose bins."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from dapm_lightning.geometry.bins import bin_centers
from dapm_lightning.models.blocks import PoolCells, ResidualConvBlock, ResidualLinear, conv_bn_relu, softmax

SKY_STAGE_BINS = 2
"""A depth stage of 2 bins is the binary "beyond d_max" (sky) map: one logit, trained with BCE."""


def stage_probabilities(logits: Tensor, dim: int = 1) -> Tensor:
    """Sigmoid for a one-logit (binary) stage, softmax otherwise."""
    return torch.sigmoid(logits) if logits.shape[dim] == 1 else softmax(logits, dim=dim)


def expected_value(logits: Tensor, dim: int = 1) -> Tensor:
    """Soft-argmax of a bins stage: the probability-weighted bin centre in [0, 1] (keeps ``dim`` as size 1)."""
    centres = bin_centers(logits.shape[dim], logits)
    shape = [1] * logits.ndim
    shape[dim] = -1
    return (softmax(logits, dim=dim) * centres.view(shape)).sum(dim=dim, keepdim=True)


MODE_SHARPNESS = 16.0
"""How sharply :func:`bins_mode` prefers the heaviest window: two windows blend only where their masses are within
about 15 % (``exp(-16 * 0.14) = 1/9``), where a hard argmax would be broken by rounding noise. Sharper amplifies
bf16 noise in an undertrained model's near-uniform bins (measured: 16 keeps bf16 within 1 % of float32 there)."""


def bins_mode(logits: Tensor, dim: int = 1, sharpness: float | None = None) -> Tensor:
    """The most probable part of a stage's distribution, in [0, 1]: a mode that stays continuous in the logits.

    Every bin's window (it and its two neighbours) has a mass and a local soft-argmax; the readout is the local
    soft-argmax of the heaviest window, chosen smoothly (weights ``mass ** sharpness``, :data:`MODE_SHARPNESS`).
    Where the distribution has two modes (ground, or an object standing on it), the full soft-argmax
    (:func:`expected_value`) lies between them; this stays at the stronger one with sub-bin precision, and where two
    windows are nearly tied it moves between them continuously, so an exported, bf16 or int8 model reads out what
    the eager one does (a hard argmax flips on rounding noise). ``[B, n, ...]`` logits -> ``[B, 1, ...]`` (``dim``
    kept as size 1).
    """
    probabilities = softmax(logits.movedim(dim, -1), dim=-1)
    centres = bin_centers(probabilities.shape[-1], probabilities)

    def window_sum(x: Tensor) -> Tensor:
        padded = nn.functional.pad(x, (1, 1))
        return padded[..., :-2] + padded[..., 1:-1] + padded[..., 2:]

    mass = window_sum(probabilities).clamp_min(torch.finfo(probabilities.dtype).tiny)
    local_mean = window_sum(probabilities * centres) / mass
    choice = softmax((MODE_SHARPNESS if sharpness is None else sharpness) * torch.log(mass), dim=-1)
    return (choice * local_mean).sum(dim=-1, keepdim=True).movedim(-1, dim)


class BinsBlock(nn.Module):
    """Concatenated inputs -> 1x1 then 3x3 conv-BN-ReLU (fuse, then spatial context) -> 1x1 conv to logits."""

    def __init__(self, in_channels: int, channels: int, num_outputs: int) -> None:
        super().__init__()
        self.body = nn.Sequential(conv_bn_relu(in_channels, channels, kernel_size=1),
                                  conv_bn_relu(channels, channels), nn.Conv2d(channels, num_outputs, 1))

    def forward(self, x: Tensor) -> Tensor:
        return self.body(x)


class DepthPQB(nn.Module):
    """Depth PQB: stages of per-pixel bins, then a depth head fusing all of them.

    Each stage sees ``cat(depth feature, previous stage output, IGD feature)``; the first stage's
    "previous output" is the initial depth. ``bins=(2, 16, 64)`` is the paper's: a binary sky map,
    then 16 and 64 classes over the normalised log depth [0, 1].

    Args:
        feature_channels: channels of the depth feature.
        igd_channels: channels of the IGD feature (0 without it).
        bins: bins per stage; a 2 is only allowed first (the sky map).
        channels: width of the bins blocks and the head.
    """

    def __init__(self, feature_channels: int, igd_channels: int, bins: Sequence[int], channels: int) -> None:
        super().__init__()
        self.bins = tuple(bins)
        for k, n in enumerate(self.bins):
            if n < 2 or (n == SKY_STAGE_BINS and k > 0):
                raise ValueError(f"depth bins must be >= 2 with 2 (the sky map) only first, got {self.bins}")
        outputs = [1 if n == SKY_STAGE_BINS else n for n in self.bins]
        previous = [1, *outputs[:-1]]
        self.blocks = nn.ModuleList(BinsBlock(feature_channels + p + igd_channels, channels, o)
                                    for p, o in zip(previous, outputs))
        expectations = sum(1 for n in self.bins if n != SKY_STAGE_BINS)
        head_in = feature_channels + 1 + sum(outputs) + expectations + igd_channels
        self.head = nn.Sequential(conv_bn_relu(head_in, channels, kernel_size=1), conv_bn_relu(channels, channels),
                                  nn.Conv2d(channels, 1, 1))

    def forward(self, feature: Tensor, depth_init: Tensor, igd_feature: Tensor | None
                ) -> tuple[Tensor, Tensor | None, list[Tensor]]:
        """``(refined depth logit [B,1,h,w], sky logit [B,1,h,w] or None, bin logits [B,n,h,w] per stage)``."""
        extra = [] if igd_feature is None else [igd_feature]
        previous, sky_logit = depth_init, None
        bin_logits: list[Tensor] = []
        fused = [feature, depth_init]
        for n, block in zip(self.bins, self.blocks):
            logits = block(torch.cat([feature, previous, *extra], dim=1))
            previous = stage_probabilities(logits)
            fused.append(previous)
            if n == SKY_STAGE_BINS:
                sky_logit = logits
            else:
                bin_logits.append(logits)
                fused.append(expected_value(logits))
        return self.head(torch.cat([*fused, *extra], dim=1)), sky_logit, bin_logits


class PosePQB(nn.Module):
    """Pose PQB: per-component bins stages (16 then 64 by default) and a linear refinement head.

    Each stage sees ``cat(pose feature, previous output)`` (the initial pose first, then the previous
    stage's probabilities) and emits ``[B, 4, n]`` logits; the head fuses the pose feature, the
    initial pose, every stage's probabilities and soft-argmax into the final normalised pose.
    """

    def __init__(self, feature_size: int, bins: Sequence[int], hidden: int = 256) -> None:
        super().__init__()
        self.bins = tuple(bins)
        if any(n < 2 for n in self.bins):
            raise ValueError(f"pose bins must be >= 2, got {self.bins}")
        previous = [4, *[4 * n for n in self.bins[:-1]]]
        self.stages = nn.ModuleList(
            nn.Sequential(nn.Linear(feature_size + p, hidden), nn.LayerNorm(hidden), nn.ReLU(inplace=True),
                          nn.Linear(hidden, 4 * n)) for p, n in zip(previous, self.bins))
        head_in = feature_size + 4 + sum(4 * n + 4 for n in self.bins)
        self.head = nn.Sequential(nn.Linear(head_in, hidden), nn.LayerNorm(hidden), nn.ReLU(inplace=True),
                                  nn.Linear(hidden, hidden), nn.LayerNorm(hidden), nn.ReLU(inplace=True),
                                  nn.Linear(hidden, 4))

    def forward(self, feature: Tensor, pose_init: Tensor) -> tuple[Tensor, list[Tensor]]:
        """``(refined pose logit [B, 4], bin logits [B, 4, n] per stage)``."""
        previous, fused, all_logits = pose_init, [feature, pose_init], []
        for n, stage in zip(self.bins, self.stages):
            logits = stage(torch.cat([feature, previous], dim=1)).view(-1, 4, n)
            probs = torch.softmax(logits, dim=-1)
            previous = probs.flatten(1)
            fused += [previous, expected_value(logits, dim=-1).flatten(1)]
            all_logits.append(logits)
        return self.head(torch.cat(fused, dim=1)), all_logits


class EncoderPosePQB(nn.Module):
    """Pose PQB on the last encoder stage, the authors' released layout (``pose_bins_source="encoder"``).

    Stage ``k`` runs a residual conv block (``in_channels -> channels``) on the deepest encoder
    feature map, global-average-pools it and maps it by a residual linear block to ``[B, 4, n_k]``
    logits; from the second stage on, a residual linear block fuses the previous stage's logits with
    this stage's. The head is a residual linear block over ``cat(initial pose logit, every stage's
    logits)``, whose output is a correction added to the initial pose logit when ``residual_init``
    (the authors' ``sigmoid(head + initial)``), or the pose logit itself otherwise.

    With ``in_channels=2048`` (ResNet-50), ``channels=256`` and bins ``(16, 64)`` this has the
    authors' parameter count (11.84 M + 0.23 M + 2.6 k); their residual linear blocks use
    BatchNorm1d and a final ReLU, here LayerNorm (batch of one) and no ReLU on logits/corrections.
    ``block_dropout``/``linear_dropout``: dropout in the residual conv / linear blocks (authors: 0.1 / 0.3).
    ``prior_features``: width of a telemetry vector the head also reads (0: none), so that what is known of the
    pose reaches the refined pose and not only the initial one. ``pool_grid``: each stage pools its conv block's
    output to ``pool_grid x pool_grid`` cells instead of the global mean (1).
    """

    def __init__(self, in_channels: int, bins: Sequence[int], channels: int = 256,
                 residual_init: bool = True, block_dropout: float = 0.0, linear_dropout: float = 0.0,
                 prior_features: int = 0, pool_grid: int = 1) -> None:
        super().__init__()
        self.bins = tuple(bins)
        if any(n < 2 for n in self.bins):
            raise ValueError(f"pose bins must be >= 2, got {self.bins}")
        self.residual_init = residual_init
        self.stages = nn.ModuleList(
            # the Identity keeps the linear at index 3, where checkpoints from before the grid (pool, flatten) have it
            nn.Sequential(ResidualConvBlock(in_channels, channels, dropout=block_dropout), PoolCells(pool_grid),
                          nn.Identity(),
                          ResidualLinear(channels * pool_grid ** 2, 4 * n, activate=False, dropout=linear_dropout))
            for n in self.bins)
        self.fuse = nn.ModuleList(ResidualLinear(4 * p + 4 * n, 4 * n, activate=False, dropout=linear_dropout)
                                  for p, n in zip(self.bins[:-1], self.bins[1:]))
        self.prior_features = prior_features
        self.head = ResidualLinear(4 + sum(4 * n for n in self.bins) + prior_features, 4, activate=False,
                                   dropout=linear_dropout)

    def forward(self, feature: Tensor, pose_init_logit: Tensor,
                prior: Tensor | None = None) -> tuple[Tensor, list[Tensor]]:
        """``feature [B, C, h, w]`` (deepest encoder stage) -> ``(pose logit [B, 4], bin logits [B, 4, n] each)``.

        ``prior``: the telemetry vector ``[B, prior_features]`` of a head built with one.
        """
        flat: list[Tensor] = []
        for k, stage in enumerate(self.stages):
            logits = stage(feature)
            if k > 0:
                logits = self.fuse[k - 1](torch.cat([flat[-1], logits], dim=1))
            flat.append(logits)
        told = []
        if self.prior_features:
            if prior is None:
                raise ValueError("this pose head was built with a telemetry input (prior_features > 0) but got none")
            told = [prior.to(pose_init_logit.dtype)]
        correction = self.head(torch.cat([pose_init_logit, *told, *flat], dim=1))
        pose_logit = correction + pose_init_logit if self.residual_init else correction
        return pose_logit, [f.view(-1, 4, n) for f, n in zip(flat, self.bins)]
