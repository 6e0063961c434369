"""Small convolutional and MLP building blocks shared by the decoders and the bins modules."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def relu_dropout(p: float) -> nn.Module:
    """``ReLU``, then ``Dropout(p)`` when ``p > 0``; parameter-free, so state-dict keys stay the same either way."""
    return nn.Sequential(nn.ReLU(inplace=True), nn.Dropout(p)) if p > 0 else nn.ReLU(inplace=True)


def conv_bn_relu(in_channels: int, out_channels: int, kernel_size: int = 3) -> nn.Sequential:
    """``Conv(k) -> BatchNorm -> ReLU`` keeping the spatial size."""
    return nn.Sequential(nn.Conv2d(in_channels, out_channels, kernel_size, padding=kernel_size // 2, bias=False),
                         nn.BatchNorm2d(out_channels), nn.ReLU(inplace=True))


class ResidualConvBlock(nn.Module):
    """Two 3x3 conv-BN layers with a skip: ``relu(shortcut(x) + f(x))``.

    The skip is the identity when ``out_channels`` equals ``channels`` (the default), a 1x1
    convolution otherwise. ``dropout > 0`` ends the body with ``Dropout2d(dropout)``, as the authors'
    block (0.1).
    """

    def __init__(self, channels: int, out_channels: int | None = None, dropout: float = 0.0) -> None:
        super().__init__()
        out = out_channels or channels
        self.body = nn.Sequential(
            nn.Conv2d(channels, out, 3, padding=1, bias=False), nn.BatchNorm2d(out), nn.ReLU(inplace=True),
            nn.Conv2d(out, out, 3, padding=1, bias=False), nn.BatchNorm2d(out),
            *([nn.Dropout2d(dropout)] if dropout > 0 else []))
        self.shortcut: nn.Module = nn.Identity() if out == channels else nn.Conv2d(channels, out, 1)
        self.act = nn.ReLU(inplace=True)

    def forward(self, x: Tensor) -> Tensor:
        return self.act(self.shortcut(x) + self.body(x))


class ResidualMLPBlock(nn.Module):
    """``x + Linear(Dropout(ReLU(LayerNorm(Linear(x)))))``: any batch size, including 1 (no dropout by default)."""

    def __init__(self, features: int, dropout: float = 0.0) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Linear(features, features), nn.LayerNorm(features), relu_dropout(dropout),
                                  nn.Linear(features, features))

    def forward(self, x: Tensor) -> Tensor:
        return x + self.body(x)


class ResidualLinear(nn.Module):
    """``relu(shortcut(x) + LN(Linear(ReLU(LN(Linear(x))))))`` from ``in_features`` to ``out_features``.

    The authors' residual linear block with LayerNorm in place of BatchNorm1d (same parameter count;
    a batch of one works); the skip is a linear map when the widths differ. ``activate=False`` drops
    the final ReLU, for blocks whose output is a logit or a signed correction. ``dropout > 0`` puts
    ``Dropout(dropout)`` after the inner ReLU, as the authors' block (0.3).
    """

    def __init__(self, in_features: int, out_features: int, activate: bool = True, dropout: float = 0.0) -> None:
        super().__init__()
        self.activate = activate
        self.body = nn.Sequential(nn.Linear(in_features, out_features), nn.LayerNorm(out_features),
                                  relu_dropout(dropout), nn.Linear(out_features, out_features),
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


def adaptive_avg_pool2d(x: Tensor, output_size: int | tuple[int, int]) -> Tensor:
    """``F.adaptive_avg_pool2d``; while exporting (ONNX, ``torch.export``), the same windows in size-symbolic ops.

    PyTorch's own decomposition bakes the example input's window indices into an exported graph, which then
    fails at any other input size. The export form takes PyTorch's windows (``floor(i H / n)`` to
    ``ceil((i + 1) H / n)``) from prefix sums, so one exported model runs at every size.
    """
    if not torch.compiler.is_exporting():
        return F.adaptive_avg_pool2d(x, output_size)
    return adaptive_avg_pool2d_symbolic(x, output_size)


def adaptive_avg_pool2d_symbolic(x: Tensor, output_size: int | tuple[int, int]) -> Tensor:
    """:func:`adaptive_avg_pool2d`'s export form: PyTorch's windows from prefix sums (numerically the same)."""
    n_h, n_w = (output_size, output_size) if isinstance(output_size, int) else output_size

    def pool(values: Tensor, dim: int, n: int) -> Tensor:
        size = values.shape[dim]
        index = torch.arange(n, device=values.device)
        start, end = (index * size) // n, ((index + 1) * size + n - 1) // n
        sums = torch.cat([torch.zeros_like(values.narrow(dim, 0, 1)), values.cumsum(dim)], dim)
        shape = [1] * values.ndim
        shape[dim] = n
        counts = (end - start).to(values.dtype).view(shape)
        return (sums.index_select(dim, end) - sums.index_select(dim, start)) / counts

    return pool(pool(x, x.ndim - 1, n_w), x.ndim - 2, n_h)


def pool_cells(x: Tensor, grid: int) -> Tensor:
    """``[B, C, H, W]`` -> ``[B, C * grid * grid]``: the mean of each of ``grid x grid`` cells, channel-major.

    ``grid`` 1 is the global average (the exact ``mean`` over the map, as before this option existed).
    """
    if grid == 1:
        return x.mean(dim=(2, 3))
    return adaptive_avg_pool2d(x, grid).flatten(1)


class PoolCells(nn.Module):
    """:func:`pool_cells` as a module."""

    def __init__(self, grid: int) -> None:
        super().__init__()
        self.grid = grid

    def forward(self, x: Tensor) -> Tensor:
        return pool_cells(x, self.grid)


def softmax(x: Tensor, dim: int) -> Tensor:
    """``torch.softmax``; while exporting, the same arithmetic spelt out (max, exp, sum, divide).

    ONNX Runtime's ``Softmax`` over any axis but the last transposes its input there and back: on the convex
    upsampling's ``[B, 9, f, f, h, w]`` weights at 512² that is 4x slower than the reductions along the axis.
    """
    if not torch.compiler.is_exporting():
        return torch.softmax(x, dim=dim)
    exp = (x - x.amax(dim=dim, keepdim=True)).exp()
    return exp / exp.sum(dim=dim, keepdim=True)
