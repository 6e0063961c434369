"""Albumentations pipelines; the pose-aware flip moves image, depth and roll together.

A data set calls its transform as ``transform(image=rgb [H,W,3] uint8, mask=depth grey [H,W], pose=[4])``
and reads back the same keys, so any ``albumentations.Compose`` works, with geometric ops limited to
:class:`PoseAwareHorizontalFlip` (vertical flips and rotations would change the pose).
"""

from __future__ import annotations

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


def train_transform(*, flip_p: float = 0.5, color_jitter_p: float = 0.8, noise_p: float = 0.3,
                    brightness: float = 0.2, contrast: float = 0.2, saturation: float = 0.2) -> A.Compose:
    """The paper's light augmentation.

    Colour jitter (brightness, contrast, saturation), Gaussian noise, and the pose-aware horizontal
    flip. No vertical flips or rotations.
    """
    return A.Compose([
        A.ColorJitter(brightness=brightness, contrast=contrast, saturation=saturation, hue=0.0, p=color_jitter_p),
        A.GaussNoise(std_range=(0.01, 0.04), p=noise_p),
        PoseAwareHorizontalFlip(p=flip_p),
    ])
