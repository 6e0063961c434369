"""Depth and depth error as colour pictures: training panels, contact sheets and prediction files."""

from __future__ import annotations

import cv2
import numpy as np
from torch import Tensor

from dapm_lightning.geometry.constants import MAX_DEPTH_M, MIN_DEPTH_M
from dapm_lightning.geometry.depth_codec import encode_log_depth


def colorize_depth(depth_m: Tensor, max_depth: float = MAX_DEPTH_M) -> np.ndarray:
    """``[H, W]`` metres -> ``[H, W, 3]`` uint8 RGB (log scale, near = bright, sky = dark)."""
    grey = (255 * (1 - encode_log_depth(depth_m.float(), max_depth))).clamp(0, 255).byte().cpu().numpy()
    return cv2.cvtColor(cv2.applyColorMap(grey, cv2.COLORMAP_MAGMA), cv2.COLOR_BGR2RGB)


def colorize_error(pred_m: Tensor, true_m: Tensor, max_depth: float = MAX_DEPTH_M) -> np.ndarray:
    """Absolute relative error, 0 (black) to >= 50 % (white); invalid and sky pixels blue."""
    valid = (true_m > MIN_DEPTH_M) & (true_m < max_depth)
    rel = ((pred_m - true_m).abs() / true_m.clamp(min=MIN_DEPTH_M)).clamp(0, 0.5) / 0.5
    grey = (rel * 255).byte().cpu().numpy()
    rgb = cv2.cvtColor(cv2.applyColorMap(grey, cv2.COLORMAP_INFERNO), cv2.COLOR_BGR2RGB)
    rgb[~valid.cpu().numpy()] = (40, 60, 140)
    return rgb
