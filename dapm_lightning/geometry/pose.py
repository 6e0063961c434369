"""Pose normalisation to [0, 1] per component and the left-right flip of a pose."""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from torch import Tensor

from dapm_lightning.geometry.constants import POSE_KEYS, POSE_RANGES
from dapm_lightning.geometry.precision import float32

PoseRanges = Mapping[str, tuple[float, float]]


def impossible_pose_value(key: str, value: float) -> str | None:
    """Why ``value`` cannot be pose component ``key`` of any camera (``None`` when it can): ``"must be > 0 m ..."``.

    Height at or below the ground (<= 0 m), |pitch| or |roll| above 180 degrees, a field of view outside (0, 180)
    degrees, or a value that is not finite. Values outside the UAPD ranges (``POSE_RANGES``) are possible.
    """
    if not math.isfinite(value):
        return "is not finite"
    if key == "height" and value <= 0:
        return "must be > 0 m (metres above the ground under the camera)"
    if key in ("pitch", "roll") and abs(value) > 180:
        return "must be within [-180, 180] degrees"
    if key == "fov" and not 0 < value < 180:
        return "must be within (0, 180) degrees (horizontal field of view)"
    return None


def _check_pose(pose: Tensor) -> None:
    if pose.shape[-1:] != (4,):
        raise ValueError(f"pose must have shape [..., 4] (height, pitch, roll, fov), got {tuple(pose.shape)}")


def pose_bounds(ranges: PoseRanges, like: Tensor) -> tuple[Tensor, Tensor]:
    """Return ``(lo, span)`` as ``[4]`` tensors on the device and dtype of ``like``."""
    lo = torch.tensor([ranges[k][0] for k in POSE_KEYS], dtype=like.dtype, device=like.device)
    hi = torch.tensor([ranges[k][1] for k in POSE_KEYS], dtype=like.dtype, device=like.device)
    return lo, hi - lo


@float32
def normalize_pose(pose: Tensor, ranges: PoseRanges = POSE_RANGES) -> Tensor:
    """Map a physical pose to ``[0, 1]`` per component (values outside the ranges map outside [0, 1]).

    Args:
        pose: ``[..., 4]`` (height m, pitch deg, roll deg, fov deg).
        ranges: ``{key: (lo, hi)}`` per component; UAPD's by default.

    Returns:
        ``[..., 4]`` normalised pose ``(x - lo) / (hi - lo)``.
    """
    _check_pose(pose)
    lo, span = pose_bounds(ranges, pose)
    return (pose - lo) / span


@float32
def denormalize_pose(pose_norm: Tensor, ranges: PoseRanges = POSE_RANGES) -> Tensor:
    """Inverse of :func:`normalize_pose`: ``[..., 4]`` in [0, 1] to (m, deg, deg, deg)."""
    _check_pose(pose_norm)
    lo, span = pose_bounds(ranges, pose_norm)
    return pose_norm * span + lo


def flip_pose(pose: Tensor) -> Tensor:
    """Pose of the left-right mirrored image: roll negated, height, pitch and fov kept.

    Args:
        pose: ``[..., 4]`` physical pose.
    """
    _check_pose(pose)
    sign = torch.tensor([1.0, 1.0, -1.0, 1.0], dtype=pose.dtype, device=pose.device)
    return pose * sign
