"""Optional radial lens distortion applied to a pinhole render, to RGB and depth alike.

An output pixel at offset ``r`` from the image centre (in units of the half-diagonal) shows what
the pinhole render shows at ``r (1 + k r^2 + kcube r^3)``, along the same direction: ``k > 0``
pulls the periphery in (pincushion), ``k < 0`` pushes it out (barrel). The depth map is warped
with the same map (nearest neighbour, so every depth value is a real surface's range): depth and
image stay **consistent with each other**, and both leave the pinhole model (the IGD of the pose
no longer holds at the periphery). Samples from outside the render repeat its border.
"""

from __future__ import annotations

import cv2
import numpy as np

K_RANGE = (-0.5, 0.5)
KCUBE_RANGE = (-0.2, 0.2)
"""Coefficient ranges, those of UAPD's parameter table (lens k, kcube)."""


def sample_lens(rng: np.random.Generator) -> tuple[float, float]:
    """``(k, kcube)`` uniform in their ranges, rounded to 3 decimals (as written in the file name)."""
    return round(float(rng.uniform(*K_RANGE)), 3), round(float(rng.uniform(*KCUBE_RANGE)), 3)


def distortion_maps(size: tuple[int, int], k: float, kcube: float) -> tuple[np.ndarray, np.ndarray]:
    """Source coordinates (``cv2.remap`` maps, float32 pixels) of every output pixel."""
    height, width = size
    v, u = np.meshgrid(np.arange(height) + 0.5 - height / 2, np.arange(width) + 0.5 - width / 2, indexing="ij")
    r = np.hypot(u, v) / (0.5 * np.hypot(height, width))
    factor = 1 + k * r ** 2 + kcube * r ** 3
    return ((u * factor + width / 2 - 0.5).astype(np.float32), (v * factor + height / 2 - 0.5).astype(np.float32))


def distort(rgb: np.ndarray, depth_m: np.ndarray, hit: np.ndarray, k: float, kcube: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Warp RGB (bilinear), depth and hit map (nearest) with the same distortion."""
    map_x, map_y = distortion_maps(depth_m.shape, k, kcube)
    warped_rgb = cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    finite = np.where(np.isfinite(depth_m), depth_m, -1.0).astype(np.float64)
    warped = cv2.remap(finite, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    warped_hit = cv2.remap(hit, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    return warped_rgb, np.where(warped < 0, np.inf, warped), warped_hit
