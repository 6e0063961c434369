"""Ideal Ground Depth: the depth a camera of a given pose would see on a flat ground (docs/conventions.md)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

from dapm_lightning.geometry.camera import _plane_coords
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_RANGES
from dapm_lightning.geometry.depth_codec import check_depth_limit, encode_log_depth
from dapm_lightning.geometry.pose import denormalize_pose, normalize_pose
from dapm_lightning.geometry.precision import float32

IGDModel = Literal["pinhole", "paper"]
DepthKind = Literal["range", "planar"]

_MIN_DOWNWARD = 1e-6
"""Rays whose downward component is below this never meet the ground (they get ``max_depth``)."""


@float32
def ideal_ground_depth(pose: Tensor, size: tuple[int, int], *, model: IGDModel = "pinhole",
                       depth_kind: DepthKind = "range", max_depth: float = MAX_DEPTH_M) -> Tensor:
    """Depth of the flat ground ``Z = 0`` seen by a camera of the given pose, per pixel.

    Args:
        pose: ``[B, 4]`` or ``[4]`` (height m, pitch deg, roll deg, fov deg), float32 or float64.
        size: ``(H, W)`` of the output in pixels; the FoV spans the width.
        model: ``"pinhole"`` exact ray-plane intersection (default), or ``"paper"`` for the paper's
            separable approximation (Eq. 10-17), which agrees on the central column at roll 0.
        depth_kind: ``"range"`` (lens to ground point) or ``"planar"`` (along the optical axis).
        max_depth: value for rays that never meet the ground; all values are clamped to it.

    Returns:
        ``[B, 1, H, W]`` depth in metres, in ``[0, max_depth]``; finite with finite gradients for
        any pose (heights <= 0 give 0).

    Convention:
        A nadir camera (pitch -90) at 50 m sees the centre pixel at 50 m; at pitch -45 at
        ``50 * sqrt(2)`` m. Mirroring the output left-right equals negating the roll.
    """
    if pose.ndim == 1:
        pose = pose[None]
    if pose.ndim != 2 or pose.shape[1] != 4:
        raise ValueError(f"pose must be [B, 4] or [4] (height, pitch, roll, fov), got {tuple(pose.shape)}")
    if not pose.is_floating_point():
        raise ValueError(f"pose must be a floating point tensor, got {pose.dtype}")
    if model not in ("pinhole", "paper"):
        raise ValueError(f"model must be 'pinhole' or 'paper', got {model!r}")
    if depth_kind not in ("range", "planar"):
        raise ValueError(f"depth_kind must be 'range' or 'planar', got {depth_kind!r}")
    height = pose[:, 0, None, None].clamp(min=0.0)
    a, b = _plane_coords(pose[:, 3], size)  # [B, H, W]: u/f, v/f
    norm = torch.sqrt(1.0 + a * a + b * b)  # |d| / (component along the optical axis)
    if model == "pinhole":
        depth = _pinhole(height, pose[:, 1], pose[:, 2], a, b, norm, depth_kind, max_depth)
    else:
        depth = _paper(height, pose[:, 1], pose[:, 2], a, b, norm, depth_kind, max_depth)
    return depth[:, None]


def _pinhole(height: Tensor, pitch_deg: Tensor, roll_deg: Tensor, a: Tensor, b: Tensor,
             norm: Tensor, depth_kind: DepthKind, max_depth: float) -> Tensor:
    """Exact ray-plane intersection of docs/conventions.md ("Camera"), ``[B, H, W]``."""
    p = torch.deg2rad(pitch_deg)[:, None, None]
    r = torch.deg2rad(roll_deg)[:, None, None]
    downward = torch.cos(p) * (a * torch.sin(r) + b * torch.cos(r)) - torch.sin(p)  # -d_z
    hits = downward > _MIN_DOWNWARD
    t = height / torch.where(hits, downward, torch.ones_like(downward))  # z-depth to the ground
    depth = t * norm if depth_kind == "range" else t
    return torch.where(hits, depth.clamp(max=max_depth), torch.full_like(depth, max_depth))


def _paper(height: Tensor, pitch_deg: Tensor, roll_deg: Tensor, a: Tensor, b: Tensor,
           norm: Tensor, depth_kind: DepthKind, max_depth: float) -> Tensor:
    """The paper's separable model (Eq. 10-17), ``[B, H, W]``.

    The roll is undone on the pixel grid first, as the authors' ``pose_to_log_depth`` does, then the separable
    angles are taken (docs/conventions.md, "Ideal Ground Depth").
    """
    r = torch.deg2rad(roll_deg)[:, None, None]
    a_rolled = a * torch.cos(r) - b * torch.sin(r)  # u' / f = tan(theta_u)
    b_rolled = a * torch.sin(r) + b * torch.cos(r)  # v' / f; theta_v = atan(-v'/f)
    from_nadir = torch.deg2rad(pitch_deg)[:, None, None] + math.pi / 2 + torch.atan(-b_rolled)
    hits = from_nadir.abs() < math.pi / 2 - _MIN_DOWNWARD
    safe_angle = torch.where(hits, from_nadir, torch.zeros_like(from_nadir))
    depth = height * torch.sqrt(a_rolled * a_rolled + torch.tan(safe_angle) ** 2 + 1.0)
    if depth_kind == "planar":
        depth = depth / norm
    return torch.where(hits, depth.clamp(max=max_depth), torch.full_like(depth, max_depth))


def _uapd_ranges() -> dict[str, tuple[float, float]]:
    return dict(POSE_RANGES)


def _pose_range(key: str, value: object) -> tuple[float, float]:
    """``(lo, hi)`` of one pose component's normalisation range: two finite numbers, ``lo < hi``.

    Raises:
        ValueError: naming ``model.net.igd.pose_ranges.<key>`` and the fix (an empty range divides by 0: every pose
            target would be NaN, and training fails on its first step with a bins class id out of bounds).
    """
    try:
        lo, hi = (float(x) for x in value)  # type: ignore[attr-defined]
    except (TypeError, ValueError):
        lo = hi = math.nan
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        default = POSE_RANGES.get(key)
        fix = f"[{default[0]:g}, {default[1]:g}] (UAPD's)" if default else "[lo, hi] with lo < hi"
        raise ValueError(f"model.net.igd.pose_ranges.{key}: {value!r}, but a normalisation range must be two finite "
                         f"numbers [lo, hi] with lo < hi (a component that never varies still needs a range around "
                         f"its value).\nFix: model.net.igd.pose_ranges.{key}: {fix}")
    return lo, hi


@dataclass(frozen=True)
class IGDSpec:
    """How a pose becomes an ideal ground depth: one specification shared by the network and the loss.

    It also holds what every depth and pose of the model is measured against (the depth limit, what depth
    measures, the pose normalisation), so metrics and prediction read those from the model's ``net.igd``.

    Args:
        model: ``"pinhole"`` (exact) or ``"paper"`` (the paper's approximation), see :func:`ideal_ground_depth`.
        depth_kind: ``"range"`` or ``"planar"``; must be what the data set's depth maps hold.
        max_depth: metres; sky and the clamp of every depth (finite, above ``MIN_DEPTH_LIMIT_M``: refused otherwise,
            naming ``model.net.igd.max_depth``).
        pose_ranges: normalisation ranges of the pose, ``{key: (lo, hi)}``; a component not given keeps UAPD's.
    """

    model: IGDModel = "pinhole"
    depth_kind: DepthKind = "range"
    max_depth: float = MAX_DEPTH_M
    pose_ranges: Mapping[str, tuple[float, float]] = field(default_factory=_uapd_ranges)

    def __post_init__(self) -> None:
        unknown = {str(k) for k in self.pose_ranges} - set(POSE_RANGES)
        if unknown:
            raise ValueError(f"model.net.igd.pose_ranges: unknown component(s) {sorted(unknown)}; the pose's are "
                             f"{list(POSE_RANGES)}")
        given = {str(k): v for k, v in self.pose_ranges.items()}  # a component not given keeps UAPD's range
        ranges = {key: _pose_range(key, given.get(key, default)) for key, default in _uapd_ranges().items()}
        object.__setattr__(self, "pose_ranges", ranges)
        object.__setattr__(self, "max_depth", check_depth_limit(self.max_depth, "model.net.igd.max_depth"))

    def normalize(self, pose: Tensor) -> Tensor:
        """``[..., 4]`` physical pose -> ``[..., 4]`` in [0, 1] with :attr:`pose_ranges`."""
        return normalize_pose(pose, self.pose_ranges)

    def denormalize(self, pose_norm: Tensor) -> Tensor:
        """Inverse of :meth:`normalize`."""
        return denormalize_pose(pose_norm, self.pose_ranges)

    def depth(self, pose: Tensor, size: tuple[int, int]) -> Tensor:
        """IGD in metres ``[B, 1, H, W]`` of a physical pose ``[B, 4]``."""
        return ideal_ground_depth(pose, size, model=self.model, depth_kind=self.depth_kind,
                                  max_depth=self.max_depth)

    def depth_norm(self, pose_norm: Tensor, size: tuple[int, int]) -> Tensor:
        """IGD of a normalised pose ``[B, 4]`` in the normalised log space: ``[B, 1, H, W]`` in [0, 1]."""
        return encode_log_depth(self.depth(self.denormalize(pose_norm), size), self.max_depth)
