"""Small convolutional and MLP building blocks shared by the decoders and the bins modules."""

from __future__ import annotations

from torch import Tensor, nn


def conv_bn_relu(in_channels: int, out_channels: int, kernel_size: int = 3) -> nn.Sequential:
    """``Conv(k) -> BatchNorm -> ReLU`` keeping the spatial size."""
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2, bias=False),
                         nn.BatchNorm2d(out_channels), nn.ReLU(inplace=True))


class ResidualConvBlock(nn.Module):
    """Two 3x3 conv-BN layers with an identity skip: ``relu(x + f(x))``."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(channels, channels, 3, padding=1, bias=False), nn.BatchNorm2d(channels), nn.ReLU(inplace=True),
            nn.Conv2d(channels, channels, 3, padding=1, bias=False), nn.BatchNorm2d(channels))
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.act(x + self.body(x))


class ResidualMLPBlock(nn.Module):
    """``x + Linear(ReLU(LayerNorm(Linear(x))))``: works for any batch size, including 1."""

    def __init__(self, features: int) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Linear(features, features), nn.LayerNorm(features), nn.ReLU(inplace=True),
                                  nn.Linear(features, features))

    def forward(self, x: Tensor) -> Tensor:
        return x + self.body(x)
