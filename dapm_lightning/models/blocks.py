"""Small convolutional and MLP building blocks shared by the decoders and the bins modules."""

from __future__ import annotations

from torch import Tensor, nn


def conv_bn_relu(in_channels: int, out_channels: int, kernel_size: int = 3) -> nn.Sequential:
    """``Conv(k) -> BatchNorm -> ReLU`` keeping the spatial size."""
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2, bias=False),
                         nn.BatchNorm2d(out_channels), nn.ReLU(inplace=True))


class ResidualConvBlock(nn.Module):
    """Two 3x3 conv-BN layers with a skip: ``relu(shortcut(x) + f(x))``.

    The skip is the identity when ``out_channels`` equals ``channels`` (the default), a 1x1
    convolution otherwise.
    """

    def __init__(self, channels: int, out_channels: int | None = None) -> None:
        super().__init__()
        out = out_channels or channels
        self.body = nn.Sequential(
            nn.Conv2d(channels, out, 3, padding=1, bias=False), nn.BatchNorm2d(out), nn.ReLU(inplace=True),
            nn.Conv2d(out, out, 3, padding=1, bias=False), nn.BatchNorm2d(out))
        self.shortcut: nn.Module = nn.Identity() if out == channels else nn.Conv2d(channels, out, 1)
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.act(self.shortcut(x) + self.body(x))


class ResidualMLPBlock(nn.Module):
    """``x + Linear(ReLU(LayerNorm(Linear(x))))``: works for any batch size, including 1."""

    def __init__(self, features: int) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Linear(features, features), nn.LayerNorm(features), nn.ReLU(inplace=True),
                                  nn.Linear(features, features))

    def forward(self, x: Tensor) -> Tensor:
        return x + self.body(x)


class ResidualLinear(nn.Module):
    """``relu(shortcut(x) + LN(Linear(ReLU(LN(Linear(x))))))`` from ``in_features`` to ``out_features``.

    The authors' residual linear block with LayerNorm in place of BatchNorm1d (same parameter count;
    a batch of one works); the skip is a linear map when the widths differ. ``activate=False`` drops
    the final ReLU, for blocks whose output is a logit or a signed correction.
    """

    def __init__(self, in_features: int, out_features: int, activate: bool = True) -> None:
        super().__init__()
        self.activate = activate
        self.body = nn.Sequential(nn.Linear(in_features, out_features), nn.LayerNorm(out_features),
                                  nn.ReLU(inplace=True), nn.Linear(out_features, out_features),
                                  nn.LayerNorm(out_features))
        self.shortcut: nn.Module = (nn.Identity() if in_features == out_features
                                    else nn.Linear(in_features, out_features))

    def forward(self, x: Tensor) -> Tensor:
        y = self.shortcut(x) + self.body(x)
        return y.relu() if self.activate else y


class SqueezeExcite(nn.Module):
    """Channel attention ``x * sigmoid(W2 relu(W1 avgpool(x)))`` with a ``channels // 16`` bottleneck (>= 4)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        hidden = max(channels // 16, 4)
        self.gate = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(channels, hidden, 1), nn.ReLU(inplace=True),
                                  nn.Conv2d(hidden, channels, 1), nn.Sigmoid())

    def forward(self, x: Tensor) -> Tensor:
        return x * self.gate(x)
