"""Depth and depth error as colour pictures: training panels, contact sheets and prediction files."""

from __future__ import annotations

import math

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


SKY_RGB = (150, 190, 230)
"""Sky in depth pictures: a pale blue that no depth colour (magma) takes."""
ROBUST_PERCENTILES = (2.0, 98.0)
"""A depth picture's own range: these percentiles of its ground (non-sky) depth."""
BAR_MIN_HEIGHT = 96
"""Pictures lower than this (pixels) get no colour bar: its labels would not be legible."""


def depth_range(depth_m: np.ndarray, sky: np.ndarray | None = None) -> tuple[float, float]:
    """A picture's own depth range in metres: the :data:`ROBUST_PERCENTILES` of its ground depth."""
    ground = depth_m[~sky] if sky is not None else depth_m.ravel()
    ground = ground[np.isfinite(ground) & (ground > 0)]
    if ground.size == 0:
        return MIN_DEPTH_M, MAX_DEPTH_M
    low, high = (float(v) for v in np.percentile(ground, ROBUST_PERCENTILES))
    low = max(low, MIN_DEPTH_M)
    return low, max(high, low * 1.01)


def depth_colours(depth_m: np.ndarray, low: float, high: float, sky: np.ndarray | None = None) -> np.ndarray:
    """``[H, W]`` metres -> ``[H, W, 3]`` uint8 RGB, log scale: ``low`` bright, ``high`` dark, sky pale blue."""
    span = math.log(high) - math.log(low)
    level = (np.log(np.clip(depth_m, low, high)) - math.log(low)) / span
    grey = np.round(255 * (1 - level)).astype(np.uint8)
    rgb = cv2.cvtColor(cv2.applyColorMap(grey, cv2.COLORMAP_MAGMA), cv2.COLOR_BGR2RGB)
    if sky is not None:
        rgb[sky] = SKY_RGB
    return rgb


def _label(value: float) -> str:
    return f"{value:.0f} m" if value >= 10 else f"{value:.1f} m"


def colour_bar(height: int, low: float, high: float, with_sky: bool = False) -> np.ndarray:
    """A colour bar ``height`` pixels high for :func:`depth_colours` of ``[low, high]`` m, labelled in metres.

    Far at the top, near at the bottom, five labels spaced as the log scale spaces them; with ``with_sky`` a sky
    swatch above the bar.
    """
    scale = min(3.0, max(0.35, height / 700))
    thickness = max(1, round(scale * 1.5))
    text_w, text_h = cv2.getTextSize(_label(max(high, 100.0)) + "0", cv2.FONT_HERSHEY_SIMPLEX, scale, thickness)[0]
    margin, strip = max(4, text_h // 2), max(8, round(1.2 * text_h))
    panel = np.full((height, margin * 3 + strip + text_w, 3), 255, np.uint8)
    top, bottom = margin + text_h, height - margin - text_h
    if with_sky:
        swatch = top + 2 * text_h
        panel[top:swatch - margin // 2, margin:margin + strip] = SKY_RGB
        cv2.putText(panel, "sky", (2 * margin + strip, top + text_h), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0),
                    thickness, cv2.LINE_AA)
        top = swatch
    if bottom - top < 2:
        return panel
    rows = np.linspace(0.0, 1.0, bottom - top)[:, None]  # 0 at the top: far
    ramp = np.exp(math.log(high) - rows * (math.log(high) - math.log(low)))
    panel[top:bottom, margin:margin + strip] = depth_colours(np.repeat(ramp, strip, axis=1), low, high)
    for k in range(5):
        y = top + round(k / 4 * (bottom - top - 1))
        value = math.exp(math.log(high) - k / 4 * (math.log(high) - math.log(low)))
        cv2.line(panel, (margin + strip, y), (margin + strip + margin // 2, y), (0, 0, 0), thickness)
        cv2.putText(panel, _label(value), (2 * margin + strip, y + text_h // 2), cv2.FONT_HERSHEY_SIMPLEX, scale,
                    (0, 0, 0), thickness, cv2.LINE_AA)
    return panel


def depth_picture(depth_m: np.ndarray, sky: np.ndarray | None = None,
                  fixed_range: tuple[float, float] | None = None, bar: bool = True) -> np.ndarray:
    """The depth as people read it, RGB, with a colour bar in metres.

    :func:`depth_colours` in the picture's own range (:func:`depth_range`), or ``fixed_range`` (metres, for maps
    to compare), with a :func:`colour_bar` on the right (``bar``, and the picture at least
    :data:`BAR_MIN_HEIGHT` pixels high).
    """
    low, high = fixed_range if fixed_range is not None else depth_range(depth_m, sky)
    picture = depth_colours(depth_m, low, high, sky)
    if not bar or depth_m.shape[0] < BAR_MIN_HEIGHT:
        return picture
    with_sky = sky is not None and bool(sky.any())
    return np.concatenate([picture, colour_bar(depth_m.shape[0], low, high, with_sky)], axis=1)
