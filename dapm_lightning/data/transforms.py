"""Albumentations pipelines; the pose-aware flip moves image, depth and roll together.

A data set calls its transform as ``transform(image=rgb [H,W,3] uint8, mask=depth grey [H,W], pose=[4])``
and reads back the same keys, so any ``albumentations.Compose`` works, with geometric ops limited to
:class:`PoseAwareHorizontalFlip` (vertical flips and rotations would change the pose).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import albumentations as A
import numpy as np
import torch

from dapm_lightning.geometry.pose import flip_pose


class PoseAwareHorizontalFlip(A.HorizontalFlip):
    """Horizontal flip of image and masks (the depth) that also negates the roll of a ``pose`` target.

    Mirroring an image left-right is the same camera with roll negated (design.md §1); height, pitch
    and FoV are kept. Use it inside any ``A.Compose`` and pass ``pose=`` (``[4]`` physical) with the image.
    """

    @property
    def targets(self) -> dict[str, Any]:
        return {**super().targets, "pose": self.apply_to_pose}

    def apply_to_pose(self, pose: np.ndarray, **params: Any) -> np.ndarray:
        """``[4]`` (height, pitch, roll, fov) -> roll negated."""
        return flip_pose(torch.as_tensor(np.asarray(pose, np.float32))).numpy()


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
    """

    brightness: float = 0.2
    contrast: float = 0.2
    saturation: float = 0.2
    color_jitter_p: float = 0.8
    noise_std: tuple[float, float] = (0.01, 0.04)
    noise_p: float = 0.3
    flip_p: float = 0.5

    def __post_init__(self) -> None:
        object.__setattr__(self, "noise_std", tuple(float(v) for v in self.noise_std))
        if len(self.noise_std) != 2 or not 0.0 <= self.noise_std[0] <= self.noise_std[1]:
            raise ValueError(f"data.init_args.augmentation.noise_std must be [low, high] with 0 <= low <= high, "
                             f"got {list(self.noise_std)}")
        for name in ("color_jitter_p", "noise_p", "flip_p"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"data.init_args.augmentation.{name} must be a probability in [0, 1], "
                                 f"got {getattr(self, name)}")
        for name in ("brightness", "contrast", "saturation"):
            if getattr(self, name) < 0:
                raise ValueError(f"data.init_args.augmentation.{name} must be >= 0, got {getattr(self, name)}")


AUTHORS_AUGMENTATION = Augmentation(brightness=0.5, contrast=0.5, saturation=0.5, color_jitter_p=1.0,
                                    noise_std=(0.05, 0.05), noise_p=0.5)
"""The authors' augmentation strengths (``train.py``); what the paper configs set."""


def train_transform(augmentation: Augmentation = Augmentation()) -> A.Compose:  # noqa: B008 (frozen)
    """Colour jitter (brightness, contrast, saturation), Gaussian noise, and the pose-aware horizontal flip.

    No vertical flips or rotations (they would change the pose).
    """
    a = augmentation
    return A.Compose([
        A.ColorJitter(brightness=a.brightness, contrast=a.contrast, saturation=a.saturation, hue=0.0,
                      p=a.color_jitter_p),
        A.GaussNoise(std_range=a.noise_std, p=a.noise_p),
        PoseAwareHorizontalFlip(p=a.flip_p),
    ])
