"""Picture panels: RGB | true depth | predicted depth | IGD of the predicted pose | error."""

from __future__ import annotations

import numpy as np
from torch import Tensor

from dapm_lightning.data.pictures import colorize_depth, colorize_error
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.geometry.image import unit_image
from dapm_lightning.models.dapm import DAPMOutput


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
