"""Uniform quantisation of [0, 1] values into class ids, for the Progressive Quantization Bins."""

from __future__ import annotations

import torch
from torch import Tensor

from dapm_lightning.geometry.precision import float32


@float32
def quantize(x_norm: Tensor, num_bins: int) -> Tensor:
    """Class id ``floor(x * n)`` clamped to ``[0, n - 1]`` (long), for ``x`` in [0, 1]."""
    if num_bins < 1:
        raise ValueError(f"num_bins must be >= 1, got {num_bins}")
    return (x_norm.detach() * num_bins).floor().clamp(0, num_bins - 1).long()


def bin_centers(num_bins: int, like: Tensor) -> Tensor:
    """Centres ``(k + 0.5) / n`` of the ``n`` uniform bins in [0, 1], as ``[n]`` on ``like``'s device/dtype."""
    return (torch.arange(num_bins, device=like.device, dtype=like.dtype) + 0.5) / num_bins
