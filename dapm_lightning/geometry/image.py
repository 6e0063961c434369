"""Image tensors: the one conversion from 8-bit pixels to the network's [0, 1] input."""

from __future__ import annotations

import torch
from torch import Tensor


def unit_image(image: Tensor) -> Tensor:
    """``uint8`` pixels ``[0, 255]`` to float32 in ``[0, 1]``; a float image is returned as it is."""
    return image.float().div(255.0) if image.dtype == torch.uint8 else image
