"""Initial estimates: the FPN depth decoder and the pooled multi-level pose decoder (paper §Encoder and Decoder)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dapm_lightning.models.blocks import (
    ResidualConvBlock,
    ResidualMLPBlock,
    SqueezeExcite,
    adaptive_avg_pool2d,
    pool_cells,
)


class DepthDecoder(nn.Module):
    """FPN with 1x1 lateral convolutions + spatial dropout, residual top-down fusion, residual head.

    Args:
        in_channels: channels of the encoder stages it fuses, shallow to deep.
        channels: FPN width.
        dropout: spatial dropout (``Dropout2d``) on the laterals.
        squeeze_excite: channel attention (:class:`SqueezeExcite`) on each lateral before the dropout,
            as the authors' released code has (not in the paper's text).
        block_dropout: ``Dropout2d`` at the end of every residual conv block (authors: 0.1).

    Returns (forward):
        ``(feature [B, channels, h, w], depth_norm [B, 1, h, w])`` at the shallowest fused stage;
        ``depth_norm`` is the initial normalised log depth (sigmoid).
    """

    def __init__(self, in_channels: Sequence[int], channels: int = 128, dropout: float = 0.1,
                 squeeze_excite: bool = False, block_dropout: float = 0.0) -> None:
        super().__init__()
        self.laterals = nn.ModuleList(
            nn.Sequential(nn.Conv2d(c, channels, 1), *([SqueezeExcite(channels)] if squeeze_excite else []),
                          nn.Dropout2d(dropout)) for c in in_channels)
        self.fuse = nn.ModuleList(ResidualConvBlock(channels, dropout=block_dropout) for _ in in_channels)
        head_channels = max(channels // 2, 8)
        self.head = nn.Sequential(nn.Conv2d(channels, head_channels, 1),
                                  ResidualConvBlock(head_channels, dropout=block_dropout),
                                  nn.Conv2d(head_channels, 1, 1))

    def forward(self, features: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
        x = self.fuse[-1](self.laterals[-1](features[-1]))
        for level in range(len(features) - 2, -1, -1):
            lateral = self.laterals[level](features[level])
            x = F.interpolate(x, size=lateral.shape[-2:], mode="bilinear", align_corners=False) + lateral
            x = self.fuse[level](x)
        return x, torch.sigmoid(self.head(x))


class PoseDecoder(nn.Module):
    """Pose from pooled multi-level features: the initial normalised pose.

    Global average pooling of every encoder stage (shallow ones too) and of the initial depth,
    linear projections, a residual MLP, and a sigmoid.

    Args:
        in_channels: channels of all encoder stages used.
        projection: width of each pooled projection.
        hidden: width of the residual MLP (the pose feature).
        depth_grid: the initial depth is average-pooled to ``depth_grid x depth_grid`` (its layout
            carries the horizon); 0 for no depth input (DAPM(P)).
        projection_dropout: ``Dropout`` on each pooled vector before its projection (authors: 0.2).
        mlp_dropout: ``Dropout`` inside each residual MLP block (authors: 0.3).
        prior_features: width of the telemetry vector the decoder is told
            (:func:`~dapm_lightning.models.prior.prior_features`), projected like a pooled stage; 0: none.
        pool_grid: each stage is average-pooled to ``pool_grid x pool_grid`` cells (1: its global mean, the
            paper's), so that the projection sees where in the picture a feature lies.
    """

    def __init__(self, in_channels: Sequence[int], projection: int = 128, hidden: int = 256,
                 depth_grid: int = 8, mlp_blocks: int = 2, projection_dropout: float = 0.0,
                 mlp_dropout: float = 0.0, prior_features: int = 0, pool_grid: int = 1) -> None:
        super().__init__()
        self.depth_grid = depth_grid
        self.pool_grid = pool_grid
        self.projection_dropout = nn.Dropout(projection_dropout)
        self.projections = nn.ModuleList(nn.Linear(c * pool_grid ** 2, projection) for c in in_channels)
        self.depth_projection = nn.Linear(depth_grid * depth_grid, projection) if depth_grid else None
        self.prior_projection = nn.Linear(prior_features, projection) if prior_features else None
        inputs = projection * (len(in_channels) + (1 if depth_grid else 0) + (1 if prior_features else 0))
        self.mlp = nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(inplace=True),
                                 *[ResidualMLPBlock(hidden, mlp_dropout) for _ in range(mlp_blocks)])
        self.out = nn.Linear(hidden, 4)

    def forward(self, features: Sequence[Tensor], depth_norm: Tensor | None,
                prior: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
        """Returns ``(pose feature [B, hidden], initial pose_norm [B, 4], its logit [B, 4])``.

        ``prior``: the telemetry vector ``[B, prior_features]`` of a decoder built with one (zeros: nothing known).
        """
        drop = self.projection_dropout
        pooled = [proj(drop(pool_cells(f, self.pool_grid))) for proj, f in zip(self.projections, features)]
        if self.depth_projection is not None:
            if depth_norm is None:
                raise ValueError("this pose decoder was built with a depth input (depth_grid > 0) but got none")
            grid = adaptive_avg_pool2d(depth_norm, self.depth_grid).flatten(1)  # export-safe at any input size
            pooled.append(self.depth_projection(drop(grid)))
        if self.prior_projection is not None:
            if prior is None:
                raise ValueError("this pose decoder was built with a telemetry input (prior_features > 0) but got none")
            pooled.append(self.prior_projection(prior.to(pooled[0].dtype)))
        feature = self.mlp(torch.cat(pooled, dim=1))
        logit = self.out(feature)
        return feature, torch.sigmoid(logit), logit
