"""Albumentations pipelines; the pose-aware flip moves image, depth and roll together.

:class:`GroundRecolour` recolours the flat ground of the pose and what stands on it apart, so that no colour tells
the one from the other; :class:`GroundPattern` paints stripes, tiles or patches on that ground, laid out in metres on
the ground plane, so that no texture does either.

A data set calls its transform as ``transform(image=rgb [H,W,3] uint8, mask=depth grey [H,W], pose=[4])``
and reads back the same keys, so any ``albumentations.Compose`` works, with geometric ops limited to
:class:`PoseAwareHorizontalFlip` and :class:`PoseAwareCentreZoom` (vertical flips and rotations would change the
pose).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import albumentations as A
import cv2
import numpy as np
import torch

from dapm_lightning.data.depth_kind import DepthKind, flat_ground_of_pose
from dapm_lightning.geometry.camera import camera_rays
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_RANGES, SKY_GREY
from dapm_lightning.geometry.pose import flip_pose


class PoseAwareHorizontalFlip(A.HorizontalFlip):
    """Horizontal flip of image and masks (the depth) that also negates the roll of a ``pose`` target.

    Mirroring an image left-right is the same camera with roll negated (docs/conventions.md, "Camera"); height, pitch
    and FoV are kept. Use it inside any ``A.Compose`` and pass ``pose=`` (``[4]`` physical) with the image.
    """

    @property
    def targets(self) -> dict[str, Any]:
        return {**super().targets, "pose": self.apply_to_pose}

    def apply_to_pose(self, pose: np.ndarray, **params: Any) -> np.ndarray:
        """``[4]`` (height, pitch, roll, fov) -> roll negated."""
        return flip_pose(torch.as_tensor(np.asarray(pose, np.float32))).numpy()


class PoseAwareCentreZoom(A.DualTransform):
    """Zoom into the image centre (image and depth alike) and narrow the FoV of a ``pose`` target to match.

    A pinhole camera with its principal point at the centre, its focal length ``zoom`` times longer, sees the
    centre ``1 / zoom`` of the picture over the whole frame: ``tan(fov' / 2) = tan(fov / 2) / zoom``; height, pitch
    and roll are kept, and every pixel keeps its depth (range or planar alike). So one scene is shown at several FoVs
    and object sizes, and the FoV must be read from the perspective, not from what is in the picture. ``zoom`` is
    drawn from ``[1, max_zoom]``, at most what keeps the FoV at or above ``min_fov`` (the FoV range's lower end).
    The image is resampled bilinearly, the depth by nearest neighbour (no depths blended across an edge). An image
    without a pose (NaN, e.g. Potsdam) is left as it is. Lens-distorted images are zoomed as pinhole ones are (their
    distortion then no longer matches its recorded strength): keep it off for those.
    """

    def __init__(self, max_zoom: float = 1.4, min_fov: float = POSE_RANGES["fov"][0], p: float = 0.5) -> None:
        super().__init__(p=p)
        if not max_zoom >= 1.0:
            raise ValueError(f"max_zoom must be >= 1, got {max_zoom}")
        self.max_zoom, self.min_fov = float(max_zoom), float(min_fov)

    @property
    def targets(self) -> dict[str, Any]:
        return {**super().targets, "pose": self.apply_to_pose}

    def get_params_dependent_on_data(self, params: dict[str, Any], data: dict[str, Any]) -> dict[str, Any]:
        draw = self.random_generator.uniform(0.0, 1.0)  # drawn always: the random stream does not depend on the pose
        pose = np.asarray(data.get("pose", np.full(4, np.nan)), np.float64)
        if pose.shape != (4,) or not np.isfinite(pose).all():
            return {"zoom": 1.0}
        limit = np.tan(np.radians(pose[3]) / 2) / np.tan(np.radians(self.min_fov) / 2)
        return {"zoom": float(1.0 + draw * (min(self.max_zoom, max(1.0, limit)) - 1.0))}

    @staticmethod
    def zoomed(array: np.ndarray, zoom: float, interpolation: int) -> np.ndarray:
        """The centre ``1 / zoom`` of ``array`` over its whole size (pixel centres at ``i + 0.5``)."""
        if zoom <= 1.0:
            return array
        height, width = array.shape[:2]
        matrix = np.array([[zoom, 0.0, (1.0 - zoom) * (width - 1) / 2],
                           [0.0, zoom, (1.0 - zoom) * (height - 1) / 2]])
        out = cv2.warpAffine(array, matrix, (width, height), flags=interpolation, borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(array.shape)

    def apply(self, img: np.ndarray, zoom: float = 1.0, **params: Any) -> np.ndarray:
        return self.zoomed(img, zoom, cv2.INTER_LINEAR)

    def apply_to_mask(self, mask: np.ndarray, zoom: float = 1.0, **params: Any) -> np.ndarray:
        return self.zoomed(mask, zoom, cv2.INTER_NEAREST)

    def apply_to_pose(self, pose: np.ndarray, zoom: float = 1.0, **params: Any) -> np.ndarray:
        """``[4]`` (height, pitch, roll, fov) -> the FoV narrowed by ``zoom``."""
        out = np.array(pose, dtype=np.float32, copy=True)
        out[3] = np.degrees(2 * np.arctan(np.tan(np.radians(float(pose[3])) / 2) / zoom))
        return out

    def get_transform_init_args_names(self) -> tuple[str, ...]:
        return ("max_zoom", "min_fov")


RGB_TO_YIQ = np.array([[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]])
"""Luma and the two chroma axes (NTSC YIQ): a hue turn is a rotation in the chroma plane, a saturation change its
scale."""


def colour_matrix(hue_deg: float, saturation: float, brightness: float) -> np.ndarray:
    """``[3, 3]`` RGB matrix: chroma turned by ``hue_deg``, scaled by ``saturation``; luma by ``brightness``."""
    turn = np.radians(hue_deg)
    chroma = saturation * np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    yiq = np.eye(3)
    yiq[0, 0] = brightness
    yiq[1:, 1:] = chroma
    return np.linalg.inv(RGB_TO_YIQ) @ yiq @ RGB_TO_YIQ


class FlatGroundTransform(A.DualTransform):
    """Base of the transforms that change the colours of the flat ground of the pose; depth and pose pass unchanged.

    The flat ground is read from the depth (the ``mask`` target, grey levels of ``depth_kind`` up to ``max_depth``)
    and the pose: the pixels within :data:`~dapm_lightning.data.depth_kind.AGREE_LEVELS` grey levels of its ideal
    ground depth.
    """

    def __init__(self, depth_kind: DepthKind, max_depth: float, p: float) -> None:
        super().__init__(p=p)
        self.depth_kind, self.max_depth = depth_kind, float(max_depth)

    @property
    def targets(self) -> dict[str, Any]:
        return {**super().targets, "pose": self.apply_to_pose}

    def flat_ground(self, data: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """``(depth grey, flat-ground mask, pose)`` of a sample, or None without a pose or grey-level depth."""
        grey, pose = data.get("mask"), np.asarray(data.get("pose", np.full(4, np.nan)), np.float64)
        if grey is None or grey.dtype != np.uint8 or grey.ndim != 2 or not np.isfinite(pose).all():
            return None
        return grey, flat_ground_of_pose(grey, pose.astype(np.float32), self.depth_kind, self.max_depth), pose

    def apply_to_mask(self, mask: np.ndarray, **params: Any) -> np.ndarray:
        return mask

    def apply_to_pose(self, pose: np.ndarray, **params: Any) -> np.ndarray:
        return pose


class GroundRecolour(FlatGroundTransform):
    """Recolours the flat ground of the pose and the rest below the horizon, each with its own random colour change.

    Which pixels are ground is read from the depth (the ``mask`` target, grey levels) and the pose: those within
    :data:`~dapm_lightning.data.depth_kind.AGREE_LEVELS` grey levels of the ideal ground depth. Each region's hue
    turns by up to ``hue`` degrees either way, its saturation and brightness are scaled by factors drawn from
    ``saturation`` and ``brightness``; the sky is kept. A model trained with it cannot tell the ground from what
    stands on it by colour, which differs from world to world, and must use the geometry (and the IGD it is
    given). Depth and pose are unchanged; an image without a pose (NaN, e.g. Potsdam) or whose depth is not grey
    levels is left as it is. The IGD is a pinhole camera's: on lens-distorted images the outer flat ground counts
    as objects.
    """

    def __init__(self, depth_kind: DepthKind = "range", max_depth: float = MAX_DEPTH_M, hue: float = 180.0,
                 saturation: tuple[float, float] = (0.3, 1.7), brightness: tuple[float, float] = (0.6, 1.4),
                 p: float = 0.5) -> None:
        super().__init__(depth_kind, max_depth, p)
        self.hue, self.saturation, self.brightness = float(hue), tuple(saturation), tuple(brightness)

    def get_params_dependent_on_data(self, params: dict[str, Any], data: dict[str, Any]) -> dict[str, Any]:
        matrices = [colour_matrix(self.random_generator.uniform(-self.hue, self.hue),
                                  self.random_generator.uniform(*self.saturation),
                                  self.random_generator.uniform(*self.brightness)) for _ in range(2)]
        found = self.flat_ground(data)
        if found is None:
            return {"regions": []}
        grey, ground, _ = found
        return {"regions": [(ground, matrices[0]), ((grey < SKY_GREY) & ~ground, matrices[1])]}

    def apply(self, img: np.ndarray, regions: list[tuple[np.ndarray, np.ndarray]], **params: Any) -> np.ndarray:
        if not regions:
            return img
        out = img.astype(np.float32)
        for region, matrix in regions:
            out[region] = out[region] @ matrix.T.astype(np.float32)
        return np.clip(out + 0.5, 0, 255).astype(img.dtype)

    def get_transform_init_args_names(self) -> tuple[str, ...]:
        return ("depth_kind", "max_depth", "hue", "saturation", "brightness")


PATTERNS = ("stripes", "tiles", "patches")
"""What :class:`GroundPattern` paints: parallel bands (fields, furrows, lanes), a chequerboard (paving, lots) or
blotches (soil and vegetation, the sum of four waves in random directions)."""

ALIAS_FADE_PERIODS_PX = (8.0, 3.0)
"""A wave of the pattern keeps its full contrast where its period on the image is at least 8 pixels and fades to
none at 3 (it would alias): far ground shows the pattern's mean colour, as real texture does."""


def ground_plane_xy(pose: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``[H, W, 2]`` world (X, Y) in metres where each pixel's ray meets the ground plane; NaN above the horizon.

    ``pose``: ``[4]`` (height m, pitch, roll, fov deg); the world frame of docs/conventions.md (origin under
    the camera).
    """
    height, pitch, roll, fov = (torch.tensor([float(v)], dtype=torch.float64) for v in pose)
    rays = camera_rays(pitch, roll, fov, size)[0].numpy()
    down = rays[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = np.where(down < -1e-9, -float(height[0]) / down, np.nan)
    return rays[..., :2] * reach[..., None]


class GroundPattern(FlatGroundTransform):
    """Paints a pattern on the flat ground of the pose, laid out in metres on the ground plane.

    The ground is found as :class:`GroundRecolour` finds it (the depth within a grey level or two of the pose's IGD).
    One of :data:`PATTERNS` (stripes, tiles or patches) is drawn with a period log-uniform in ``period`` metres, a
    random direction and edges from soft to sharp; a random colour change (the hue turned, saturation and
    brightness scaled, as in :class:`GroundRecolour`) is applied with a weight that follows the pattern, up to a
    strength drawn from ``strength``. Because the pattern lies on the ground plane it shrinks with distance and is
    foreshortened as the real ground's texture is; where it would alias it fades (:data:`ALIAS_FADE_PERIODS_PX`).
    What stands on the ground and the sky are kept; depth and pose unchanged; an image without a pose or grey-level
    depth is left as it is. Its aim: that the texture alone does not tell the ground from a roof or a canopy, as it
    does for a model trained on a generator's few ground textures (docs/transfer.md: measured, it changed nothing
    at the CPU's budgets).
    """

    def __init__(self, depth_kind: DepthKind = "range", max_depth: float = MAX_DEPTH_M,
                 period: tuple[float, float] = (2.0, 60.0), strength: tuple[float, float] = (0.4, 1.0),
                 hue: float = 180.0, saturation: tuple[float, float] = (0.3, 1.7),
                 brightness: tuple[float, float] = (0.5, 1.5), p: float = 0.5) -> None:
        super().__init__(depth_kind, max_depth, p)
        if not 0 < period[0] <= period[1]:
            raise ValueError(f"GroundPattern period must be [low, high] metres with 0 < low <= high, got {period}")
        self.period, self.strength = tuple(period), tuple(strength)
        self.hue, self.saturation, self.brightness = float(hue), tuple(saturation), tuple(brightness)

    def get_params_dependent_on_data(self, params: dict[str, Any], data: dict[str, Any]) -> dict[str, Any]:
        rng = self.random_generator
        kind = PATTERNS[int(rng.integers(len(PATTERNS)))]
        period = float(np.exp(rng.uniform(np.log(self.period[0]), np.log(self.period[1]))))
        angle = rng.uniform(0, np.pi)
        sharpness = float(np.exp(rng.uniform(0.0, np.log(8.0))))  # the edges: 1 soft (a sine) to 8 near-square
        strength = rng.uniform(*self.strength)
        waves = {"stripes": [(angle, period)], "tiles": [(angle, period), (angle + np.pi / 2, period)],
                 "patches": [(rng.uniform(0, np.pi), period * rng.uniform(0.6, 1.6)) for _ in range(4)]}[kind]
        phases = rng.uniform(0, 2 * np.pi, len(waves))
        matrix = colour_matrix(rng.uniform(-self.hue, self.hue), rng.uniform(*self.saturation),
                               rng.uniform(*self.brightness))
        found = self.flat_ground(data)
        if found is None or not found[1].any():
            return {"weight": None, "matrix": matrix}
        grey, ground, pose = found
        xy = ground_plane_xy(pose, grey.shape)
        signal = np.ones(grey.shape) if kind == "tiles" else np.zeros(grey.shape)
        full, none = (2 * np.pi / v for v in ALIAS_FADE_PERIODS_PX)  # phase steps per pixel
        for (direction, wave_period), phase0 in zip(waves, phases):
            along = xy[..., 0] * np.cos(direction) + xy[..., 1] * np.sin(direction)
            phase = 2 * np.pi * along / wave_period + phase0
            rows, cols = np.gradient(phase)
            fade = np.clip((none - np.hypot(rows, cols)) / (none - full), 0.0, 1.0)
            wave = np.nan_to_num(np.sin(phase) * fade)
            signal = signal * wave if kind == "tiles" else signal + wave / len(waves) ** 0.5
        pattern = 0.5 + 0.5 * np.tanh(sharpness * signal) / np.tanh(sharpness)
        weight = np.where(ground, strength * pattern, 0.0).astype(np.float32)
        return {"weight": weight, "matrix": matrix}

    def apply(self, img: np.ndarray, weight: np.ndarray | None, matrix: np.ndarray, **params: Any) -> np.ndarray:
        if weight is None:
            return img
        out = img.astype(np.float32)
        changed = out @ matrix.T.astype(np.float32)
        out += weight[..., None] * (changed - out)
        return np.clip(out + 0.5, 0, 255).astype(img.dtype)

    def get_transform_init_args_names(self) -> tuple[str, ...]:
        return ("depth_kind", "max_depth", "period", "strength", "hue", "saturation", "brightness")


@dataclass(frozen=True)
class Augmentation:
    """Strengths of the training augmentation; in configs under ``data.init_args.augmentation``.

    The defaults are this project's light augmentation. The authors' (``train.py``, the paper configs):
    ``ColorJitter(0.5, 0.5, 0.5)`` on every image, then Gaussian noise of σ 0.05 (of the [0, 1] range) with
    p = 0.5: ``brightness/contrast/saturation: 0.5``, ``color_jitter_p: 1.0``, ``noise_std: [0.05, 0.05]``,
    ``noise_p: 0.5``. Their noise is added to the float image without clipping; here the uint8 image is clipped.

    Args:
        brightness: colour jitter strength: the brightness factor is drawn from ``[1 - s, 1 + s]``.
        contrast: the same for the contrast.
        saturation: the same for the saturation.
        color_jitter_p: probability of the colour jitter.
        noise_std: range of the Gaussian noise's σ, as a share of the full intensity range (0.05 = 12.75 grey levels).
        noise_p: probability of the noise.
        flip_p: probability of the pose-aware horizontal flip (image, depth and roll together).
        ground_recolour_p: probability of :class:`GroundRecolour` (the ground and what stands on it recoloured
            apart; 0: off, the paper's).
        ground_pattern_p: probability of :class:`GroundPattern` (stripes, tiles or patches painted on the flat
            ground, in metres on the ground plane; 0: off, the paper's).
        zoom_p: probability of :class:`PoseAwareCentreZoom` (the centre zoomed, the FoV narrowed to match; 0: off,
            the paper's).
        max_zoom: the largest zoom it draws.
    """

    brightness: float = 0.2
    contrast: float = 0.2
    saturation: float = 0.2
    color_jitter_p: float = 0.8
    noise_std: tuple[float, float] = (0.01, 0.04)
    noise_p: float = 0.3
    flip_p: float = 0.5
    ground_recolour_p: float = 0.0
    ground_pattern_p: float = 0.0
    zoom_p: float = 0.0
    max_zoom: float = 1.4

    def __post_init__(self) -> None:
        object.__setattr__(self, "noise_std", tuple(float(v) for v in self.noise_std))
        if len(self.noise_std) != 2 or not 0.0 <= self.noise_std[0] <= self.noise_std[1]:
            raise ValueError(f"data.init_args.augmentation.noise_std must be [low, high] with 0 <= low <= high, "
                             f"got {list(self.noise_std)}")
        if not self.max_zoom >= 1.0:
            raise ValueError(f"data.init_args.augmentation.max_zoom must be >= 1 (1: no zoom), got {self.max_zoom}")
        for name in ("color_jitter_p", "noise_p", "flip_p", "ground_recolour_p", "ground_pattern_p", "zoom_p"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"data.init_args.augmentation.{name} must be a probability in [0, 1], "
                                 f"got {getattr(self, name)}")
        for name in ("brightness", "contrast", "saturation"):
            if getattr(self, name) < 0:
                raise ValueError(f"data.init_args.augmentation.{name} must be >= 0, got {getattr(self, name)}")


AUTHORS_AUGMENTATION = Augmentation(brightness=0.5, contrast=0.5, saturation=0.5, color_jitter_p=1.0,
                                    noise_std=(0.05, 0.05), noise_p=0.5)
"""The authors' augmentation strengths (``train.py``); what the paper configs set."""


def train_transform(augmentation: Augmentation = Augmentation(),  # noqa: B008 (frozen)
                    depth_kind: DepthKind = "range", max_depth: float = MAX_DEPTH_M) -> A.Compose:
    """The training pipeline: centre zoom, ground pattern, ground recolour (when on), colour jitter, noise, flip.

    The colour jitter changes brightness, contrast and saturation. No vertical flips or rotations (they would change
    the pose). ``depth_kind`` and ``max_depth`` say what the depth's grey levels are, for the flat ground the ground
    pattern and the ground recolour find.
    """
    a = augmentation
    zoom = [PoseAwareCentreZoom(a.max_zoom, p=a.zoom_p)] if a.zoom_p > 0 else []
    pattern = [GroundPattern(depth_kind, max_depth, p=a.ground_pattern_p)] if a.ground_pattern_p > 0 else []
    recolour = [GroundRecolour(depth_kind, max_depth, p=a.ground_recolour_p)] if a.ground_recolour_p > 0 else []
    return A.Compose([
        *zoom,
        *pattern,
        *recolour,
        A.ColorJitter(brightness=a.brightness, contrast=a.contrast, saturation=a.saturation, hue=0.0,
                      p=a.color_jitter_p),
        A.GaussNoise(std_range=a.noise_std, p=a.noise_p),
        PoseAwareHorizontalFlip(p=a.flip_p),
    ])
