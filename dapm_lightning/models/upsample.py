"""Learned convex upsampling: each full-resolution pixel is a softmax-weighted mix of its 3x3 coarse neighbours."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor, nn

from dapm_lightning.models.blocks import softmax


class ConvexUpsample(nn.Module):
    """Upsample a ``[B, 1, h, w]`` map by ``factor`` with weights predicted from a feature map.

    The output stays within the range of the input (a convex combination), so a normalised depth in
    [0, 1] stays in [0, 1], and edges stay sharp where bilinear would blur them.
    """

    def __init__(self, feature_channels: int, factor: int, hidden: int = 32) -> None:
        super().__init__()
        self.factor = factor
        self.mask = nn.Sequential(nn.Conv2d(feature_channels, hidden, 3, padding=1), nn.ReLU(inplace=True),
                                  nn.Conv2d(hidden, 9 * factor * factor, 1))

    def forward(self, values: Tensor, feature: Tensor, size: tuple[int, int]) -> Tensor:
        """``values [B, 1, h, w]``, ``feature [B, C, h, w]`` -> ``[B, 1, H, W]`` (cropped/resized to ``size``)."""
        batch, _, height, width = values.shape
        f = self.factor
        weights = softmax(self.mask(feature).view(batch, 9, f, f, height, width), dim=1)
        neighbours = F.unfold(F.pad(values, (1, 1, 1, 1), mode="replicate"), 3).view(batch, 9, 1, 1, height, width)
        up = (weights * neighbours).sum(dim=1)  # [B, f, f, h, w]
        up = up.permute(0, 3, 1, 4, 2).reshape(batch, 1, height * f, width * f)
        if up.shape[-2:] != size:
            up = F.interpolate(up, size=size, mode="bilinear", align_corners=False)
        return up
