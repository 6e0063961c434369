"""The only home of UAPD's pose ranges and units, the depth limit, the sky threshold and grey (docs/conventions.md)."""

from __future__ import annotations

from typing import Final

POSE_KEYS: Final[tuple[str, str, str, str]] = ("height", "pitch", "roll", "fov")
"""Order of the pose vector ``[..., 4]``: height m, pitch deg, roll deg, fov deg (UAPD's order)."""

POSE_UNITS: Final[dict[str, str]] = {"height": "m", "pitch": "deg", "roll": "deg", "fov": "deg"}
"""Unit of each pose component."""


def pose_field(key: str) -> str:
    """File column / JSON key of a pose component: ``height_m``, ``pitch_deg``, ..."""
    return f"{key}_{POSE_UNITS[key]}"


POSE_FIELDS: Final[tuple[str, ...]] = tuple(pose_field(key) for key in POSE_KEYS)
"""Column names of the pose in files (telemetry CSV, poses table, camera.json): :func:`pose_field` of each key."""

POSE_RANGES: Final[dict[str, tuple[float, float]]] = {
    "height": (10.0, 100.0),
    "pitch": (-100.0, 10.0),
    "roll": (-30.0, 30.0),
    "fov": (30.0, 120.0),
}
"""UAPD ranges, used for normalisation ``(x - lo) / (hi - lo)`` and for sampling synthetic poses."""

MAX_DEPTH_M: Final[float] = 1000.0
"""Depth beyond which a pixel counts as sky ("beyond d_max"), paper Eq. 20."""

MIN_DEPTH_LIMIT_M: Final[float] = 1.0
"""A depth limit (``max_depth``: what grey 255 means, the sky, the clamp of every depth) must be finite and above
this: the log encoding needs a limit above 0, the metrics' valid depths lie between ``MIN_DEPTH_M`` and the limit, and a
camera metres above the ground sees nothing nearer than a metre as ground (synth, the data modules and
``model.net.igd.max_depth`` refuse less, :func:`~dapm_lightning.geometry.depth_codec.check_depth_limit`)."""

SKY_PROBABILITY_THRESHOLD: Final[float] = 0.5
"""A pixel is sky where the sky probability exceeds this (the network's own override: logit > 0, the same)."""

SKY_GREY: Final[int] = 255
"""8-bit grey level of the log depth encoding that means "at or beyond MAX_DEPTH_M"."""

MIN_DEPTH_M: Final[float] = 1e-3
"""Smallest depth treated as valid (metrics, loss masks, log guards): the toolbox's ``min_depth``."""
