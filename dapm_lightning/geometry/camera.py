"""Pinhole camera of docs/conventions.md ("Camera"): pixel offsets, intrinsics, per-pixel rays in the world frame."""

from __future__ import annotations

import torch
from torch import Tensor

FOV_EPS_DEG = 1e-3
"""FoV is clamped to ``[FOV_EPS_DEG, 180 - FOV_EPS_DEG]`` so that ``tan(fov / 2)`` stays finite."""


def pixel_offsets(size: tuple[int, int], *, device: torch.device | None = None,
                  dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
    """Image-plane offsets of the pixel centres from the principal point.

    Args:
        size: ``(H, W)`` in pixels.

    Returns:
        ``(u, v)``, each ``[H, W]``: ``u = j + 0.5 - W/2`` (right), ``v = i + 0.5 - H/2`` (down).
    """
    height, width = size
    if height < 1 or width < 1:
        raise ValueError(f"image size must be positive, got {size}")
    v = torch.arange(height, device=device, dtype=dtype) + 0.5 - height / 2
    u = torch.arange(width, device=device, dtype=dtype) + 0.5 - width / 2
    return u.expand(height, width), v[:, None].expand(height, width)


def inverse_focal(fov_deg: Tensor, width: int) -> Tensor:
    """``1 / f = 2 tan(fov / 2) / W`` in 1/pixels, for a horizontal FoV across ``width`` pixels.

    The FoV is clamped to (0, 180) degrees first so the result is finite for any input.
    """
    fov = fov_deg.clamp(FOV_EPS_DEG, 180.0 - FOV_EPS_DEG)
    return 2.0 * torch.tan(torch.deg2rad(fov) / 2.0) / width


def intrinsics_matrix(fov_deg: Tensor, size: tuple[int, int]) -> Tensor:
    """Pinhole intrinsics ``K`` of docs/conventions.md ("Camera") for a horizontal FoV across the image width.

    Args:
        fov_deg: ``[B]`` horizontal field of view in degrees.
        size: ``(H, W)`` in pixels.

    Returns:
        ``[B, 3, 3]``: ``fx = fy = W / (2 tan(fov / 2))`` (square pixels), principal point at the image
        centre ``(W / 2, H / 2)`` in the convention where pixel ``(i, j)`` has its centre at ``(j + 0.5, i + 0.5)``.

    Convention:
        FoV 90 deg over 512 px: ``fx = 256``, ``cx = cy = 256``.
    """
    height, width = size
    focal = 1.0 / inverse_focal(fov_deg, width)
    k = torch.zeros(*fov_deg.shape, 3, 3, dtype=fov_deg.dtype, device=fov_deg.device)
    k[..., 0, 0], k[..., 1, 1] = focal, focal
    k[..., 0, 2], k[..., 1, 2], k[..., 2, 2] = width / 2.0, height / 2.0, 1.0
    return k


def camera_rays(pitch_deg: Tensor, roll_deg: Tensor, fov_deg: Tensor,
                size: tuple[int, int], stride: int = 1) -> Tensor:
    """Per-pixel ray directions ``d = (u/f) R' + (v/f) D' + F`` in the world frame (not unit length).

    Args:
        pitch_deg, roll_deg, fov_deg: ``[B]`` each.
        size: ``(H, W)``. stride: only every ``stride``-th row and column (exactly those of the full grid).

    Returns:
        ``[B, H, W, 3]`` (``[B, ceil(H/stride), ceil(W/stride), 3]``) world (X forward-horizontal, Y left,
        Z up); the component along the optical axis is exactly 1, so ``|d| = sqrt(1 + (u/f)^2 + (v/f)^2)``.

    Convention:
        At pitch -90 (nadir) the centre ray is ``(0, 0, -1)``; positive roll tilts the horizon right end up.
    """
    a, b = _plane_coords(fov_deg, size, stride)  # [B, H, W] each: u/f, v/f
    p, r = torch.deg2rad(pitch_deg)[:, None, None], torch.deg2rad(roll_deg)[:, None, None]
    sp, cp, sr, cr = torch.sin(p), torch.cos(p), torch.sin(r), torch.cos(r)
    # R' = (sr sp, -cr, -sr cp),  D' = (cr sp, sr, -cr cp),  F = (cp, 0, sp)
    x = a * sr * sp + b * cr * sp + cp
    y = -a * cr + b * sr
    z = -a * sr * cp - b * cr * cp + sp
    return torch.stack((x, y, z), dim=-1)


def _plane_coords(fov_deg: Tensor, size: tuple[int, int], stride: int = 1) -> tuple[Tensor, Tensor]:
    """``(u/f, v/f)`` as ``[B, H, W]`` each (every ``stride``-th row and column)."""
    u, v = pixel_offsets(size, device=fov_deg.device, dtype=fov_deg.dtype)
    u, v = u[::stride, ::stride], v[::stride, ::stride]
    inv_f = inverse_focal(fov_deg, size[1])[:, None, None]
    return u * inv_f, v * inv_f


def horizon_segment(pitch_deg: float, roll_deg: float, fov_deg: float,
                    size: tuple[int, int]) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The horizon (rays with ``d_z = 0``) across an image: ``((x0, y0), (x1, y1))`` in pixel coordinates.

    With §1's frame, ``d_z = 0`` is the line ``u sin r + v cos r = f tan p``. The points lie on the image's left
    and right edges (``x`` = 0 and W), or on its top and bottom edges when the roll is near 90 degrees; ``y`` may
    be outside the image (the horizon is not in view). None when the optical axis is vertical (no horizon).
    """
    import math

    height, width = size
    p, r = math.radians(pitch_deg), math.radians(roll_deg)
    if abs(math.cos(p)) < 1e-9:
        return None
    f = width / (2 * math.tan(math.radians(min(max(fov_deg, FOV_EPS_DEG), 180 - FOV_EPS_DEG)) / 2))
    c = f * math.tan(p)
    if abs(math.cos(r)) >= abs(math.sin(r)):
        u0, u1 = -width / 2, width / 2
        v0, v1 = (c - u0 * math.sin(r)) / math.cos(r), (c - u1 * math.sin(r)) / math.cos(r)
    else:
        v0, v1 = -height / 2, height / 2
        u0, u1 = (c - v0 * math.cos(r)) / math.sin(r), (c - v1 * math.cos(r)) / math.sin(r)
    return (u0 + width / 2, v0 + height / 2), (u1 + width / 2, v1 + height / 2)
