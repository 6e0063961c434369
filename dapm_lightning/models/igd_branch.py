"""IGD module, feature side: an ideal ground depth map becomes convolutional features for the depth refinement."""

from __future__ import annotations

from torch import Tensor, nn

from dapm_lightning.models.blocks import conv_bn_relu


class IGDFeature(nn.Module):
    """``IGD map [B, 1, h, w] -> [B, channels, h, w]`` through two 3x3 conv-BN-ReLU layers."""

    def __init__(self, channels: int = 16) -> None:
        super().__init__()
        self.body = nn.Sequential(conv_bn_relu(1, channels), conv_bn_relu(channels, channels))

    def forward(self, igd_norm: Tensor) -> Tensor:
        return self.body(igd_norm)
