"""IGD module, feature side: an ideal ground depth map becomes convolutional features for the depth refinement."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from dapm_lightning.models.blocks import conv_bn_relu


class IGDFeature(nn.Module):
    """``IGD map [B, 1, h, w] -> [B, channels, h, w]`` through two 3x3 conv-BN-ReLU layers.

    ``prior_features > 0``: the map comes with a telemetry vector ``[B, prior_features]``
    (:func:`~dapm_lightning.models.prior.prior_features`), spread over the map as constant channels, so that the
    depth refinement knows which components of the pose behind the IGD are known and how well.
    """

    def __init__(self, channels: int = 16, prior_features: int = 0) -> None:
        super().__init__()
        self.prior_features = prior_features
        self.body = nn.Sequential(conv_bn_relu(1 + prior_features, channels), conv_bn_relu(channels, channels))

    def forward(self, igd_norm: Tensor, prior: Tensor | None = None) -> Tensor:
        if not self.prior_features:
            return self.body(igd_norm)
        if prior is None:
            raise ValueError("this IGD feature was built with a telemetry input (prior_features > 0) but got none")
        told = prior.to(igd_norm.dtype)[:, :, None, None].expand(-1, -1, *igd_norm.shape[-2:])
        return self.body(torch.cat([igd_norm, told], dim=1))
