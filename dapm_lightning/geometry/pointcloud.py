"""Metric point clouds (the world frame of docs/conventions.md, "Camera") from a depth map and the camera's pose."""

from __future__ import annotations

import torch
from torch import Tensor

from dapm_lightning.geometry.camera import camera_rays
from dapm_lightning.geometry.constants import MAX_DEPTH_M
from dapm_lightning.geometry.igd import DepthKind


def depth_to_points(depth_m: Tensor, pose: Tensor, *, depth_kind: DepthKind = "range", stride: int = 1) -> Tensor:
    """World coordinates of every pixel's 3D point: origin on the ground under the camera, Z up.

    Args:
        depth_m: ``[B, 1, H, W]`` or ``[B, H, W]`` metres, of the kind ``depth_kind``.
        pose: ``[B, 4]`` (height m, pitch deg, roll deg, fov deg); the FoV spans the width ``W``.
        depth_kind: ``"range"`` (lens to point) or ``"planar"`` (along the optical axis).
        stride: only every ``stride``-th row and column: exactly those points of the full grid, computed alone
            (memory of the subsampled grid, not of the image).

    Returns:
        ``[B, H, W, 3]`` metres (X the horizontal direction of the optical axis, Y to its left, Z up).
        Pixels at or beyond the depth limit (sky) get points too; mask them with :func:`valid_points`.

    Convention:
        The camera sits at ``(0, 0, height)``. A nadir camera (pitch -90) at 50 m whose centre pixel
        reads 50 m puts that point at ``(0, 0, 0)``; a depth equal to the Ideal Ground Depth of the pose
        puts every ground pixel at ``z = 0``.
    """
    if depth_m.ndim == 4:
        if depth_m.shape[1] != 1:
            raise ValueError(f"depth_m must be [B, 1, H, W] or [B, H, W], got {tuple(depth_m.shape)}")
        depth_m = depth_m[:, 0]
    if depth_m.ndim != 3:
        raise ValueError(f"depth_m must be [B, 1, H, W] or [B, H, W], got {tuple(depth_m.shape)}")
    if pose.ndim != 2 or pose.shape != (depth_m.shape[0], 4):
        raise ValueError(f"pose must be [B, 4] with B = {depth_m.shape[0]}, got {tuple(pose.shape)}")
    if depth_kind not in ("range", "planar"):
        raise ValueError(f"depth_kind must be 'range' or 'planar', got {depth_kind!r}")
    pose = pose.to(depth_m.dtype)
    size = (int(depth_m.shape[1]), int(depth_m.shape[2]))
    rays = camera_rays(pose[:, 1], pose[:, 2], pose[:, 3], size, stride)  # [B, H, W, 3], 1 along the axis
    depth_m = depth_m[:, ::stride, ::stride]
    if depth_kind == "range":
        rays = rays / torch.linalg.vector_norm(rays, dim=-1, keepdim=True)
    camera = torch.zeros_like(pose[:, :3])
    camera[:, 2] = pose[:, 0]
    return camera[:, None, None, :] + depth_m[..., None] * rays


def camera_to_world(pose: Tensor) -> Tensor:
    """Pose of the camera in the world frame of docs/conventions.md ("Camera"), as a rigid transform.

    Args:
        pose: ``[B, 4]`` (height m, pitch deg, roll deg, fov deg).

    Returns:
        ``[B, 4, 4]``: maps camera coordinates (x right, y down, z forward; the frame of
        :func:`~dapm_lightning.geometry.camera.intrinsics_matrix`) to world coordinates (origin on the
        ground under the camera, Z up). Its rotation columns are ``R'``, ``D'`` and ``F``, its translation
        ``(0, 0, height)``.

    Convention:
        A nadir camera (pitch -90, roll 0) looks along ``-Z``; its image right is world ``-Y``.
    """
    if pose.ndim != 2 or pose.shape[1] != 4:
        raise ValueError(f"pose must be [B, 4] (height, pitch, roll, fov), got {tuple(pose.shape)}")
    p, r = torch.deg2rad(pose[:, 1]), torch.deg2rad(pose[:, 2])
    sp, cp, sr, cr = torch.sin(p), torch.cos(p), torch.sin(r), torch.cos(r)
    zero = torch.zeros_like(p)
    right = torch.stack((sr * sp, -cr, -sr * cp), -1)  # R' = cos r R + sin r D
    down = torch.stack((cr * sp, sr, -cr * cp), -1)  # D' = -sin r R + cos r D
    forward = torch.stack((cp, zero, sp), -1)
    transform = torch.zeros(pose.shape[0], 4, 4, dtype=pose.dtype, device=pose.device)
    transform[:, :3, 0], transform[:, :3, 1], transform[:, :3, 2] = right, down, forward
    transform[:, 2, 3], transform[:, 3, 3] = pose[:, 0], 1.0
    return transform


def valid_points(depth_m: Tensor, max_depth: float = MAX_DEPTH_M, min_depth: float = 0.0) -> Tensor:
    """``[B, H, W]`` bool: pixels whose depth is finite, above ``min_depth`` and below ``max_depth`` (not sky)."""
    if depth_m.ndim == 4:
        depth_m = depth_m[:, 0]
    return torch.isfinite(depth_m) & (depth_m > min_depth) & (depth_m < max_depth)


__all__ = ["camera_to_world", "depth_to_points", "valid_points"]
