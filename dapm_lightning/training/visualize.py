"""Picture panels: RGB | true depth | predicted depth | IGD of the predicted pose | error."""

from __future__ import annotations

import cv2
import numpy as np
from torch import Tensor

from dapm_lightning.geometry.constants import MAX_DEPTH_M, MIN_DEPTH_M
from dapm_lightning.geometry.depth_codec import encode_log_depth
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.geometry.image import unit_image
from dapm_lightning.models.dapm import DAPMOutput


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


def depth_panel(image: Tensor, depth_true: Tensor | None, out: DAPMOutput, max_images: int = 4,
                igd: IGDSpec | None = None, min_tile: int = 128) -> np.ndarray:
    """Stack rows ``RGB | true depth | predicted depth | IGD(predicted pose) | error`` for up to ``max_images``.

    Args:
        image: ``[B, 3, H, W]`` in [0, 1] or uint8. depth_true: ``[B, 1, H, W]`` metres or None.
        out: predictions for the same batch.
        igd: the model's IGD specification (for the IGD column and the depth limit).

    Returns:
        ``[rows * H, columns * W, 3]`` uint8 RGB.
    """
    rows = []
    size = (image.shape[-2], image.shape[-1])
    igd = igd or IGDSpec()
    max_depth = igd.max_depth
    igd_m = None
    if out.pose_physical is not None:
        igd_m = igd.depth(out.pose_physical.detach().float(), size)  # [B, 1, H, W] metres
    for b in range(min(max_images, image.shape[0])):
        rgb = unit_image(image[b]).float()
        tiles = [(rgb.clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255).astype(np.uint8)]
        blank = np.zeros_like(tiles[0])
        tiles.append(colorize_depth(depth_true[b, 0], max_depth) if depth_true is not None else blank)
        tiles.append(colorize_depth(out.depth_m[b, 0].detach(), max_depth) if out.depth_m is not None else blank)
        tiles.append(colorize_depth(igd_m[b, 0], max_depth) if igd_m is not None else blank)
        tiles.append(colorize_error(out.depth_m[b, 0].detach(), depth_true[b, 0], max_depth)
                     if out.depth_m is not None and depth_true is not None else blank)
        rows.append(np.concatenate(tiles, axis=1))
    panel = np.concatenate(rows, axis=0)
    scale = max(1, -(-min_tile // size[0]))  # small images are enlarged (nearest) to be seen
    return np.repeat(np.repeat(panel, scale, axis=0), scale, axis=1) if scale > 1 else panel
