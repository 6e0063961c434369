"""The one sample schema shared by every data set, transform, collate and the Lightning module."""

from __future__ import annotations

from typing import Any, TypedDict

import torch
from torch import Tensor

from dapm_lightning.geometry.constants import MAX_DEPTH_M


class Sample(TypedDict, total=False):
    """One image and its labels in physical units.

    Keys:
        image: ``[3, H, W]`` RGB, float32 in [0, 1] (or uint8 in [0, 255] when a data set is asked
            for ``uint8`` images, which the Lightning module normalises on the device).
        depth: ``[1, H, W]`` metres, float32; sky pixels (grey 255) hold exactly ``max_depth``, so the
            sky mask is ``depth >= max_depth`` and the valid mask ``isfinite(depth) & (depth > 0)``;
            both are derived on the device (:func:`depth_masks`), not shipped by the loader.
        pose: ``[4]`` (height m, pitch deg, roll deg, fov deg); NaN when the data set has no pose.
        has_pose: ``[]`` bool.
        name: file stem.
        meta: other tokens of the file name.
    """

    image: Tensor
    depth: Tensor
    pose: Tensor
    has_pose: Tensor
    name: str
    meta: dict[str, Any]


def depth_masks(depth_m: Tensor, max_depth: float = MAX_DEPTH_M) -> tuple[Tensor, Tensor]:
    """``(sky, valid)`` bool masks of a depth map in metres: at/beyond ``max_depth``; finite and positive."""
    return depth_m >= max_depth, torch.isfinite(depth_m) & (depth_m > 0)
