"""The one sample schema shared by every data set, transform, collate and the Lightning module."""

from __future__ import annotations

from typing import Any, TypedDict

from torch import Tensor


class Sample(TypedDict, total=False):
    """One image and its labels in physical units.

    Keys:
        image: ``[3, H, W]`` RGB, float32 in [0, 1] (or uint8 in [0, 255] when a data set is asked
            for ``uint8`` images, which the Lightning module normalises on the device).
        depth: ``[1, H, W]`` metres, float32; sky pixels hold ``max_depth``.
        sky: ``[1, H, W]`` bool, True where the depth is at or beyond ``max_depth``.
        valid: ``[1, H, W]`` bool, True where the depth label is usable (finite and positive).
        pose: ``[4]`` (height m, pitch deg, roll deg, fov deg); NaN when the data set has no pose.
        has_pose: ``[]`` bool.
        name: file stem.
        meta: other tokens of the file name.
    """

    image: Tensor
    depth: Tensor
    sky: Tensor
    valid: Tensor
    pose: Tensor
    has_pose: Tensor
    name: str
    meta: dict[str, Any]
