"""Which depth a UAPD-format set holds, range or planar, read from its files against their own poses.

Range depth (lens to point) and planar depth (along the optical axis, CARLA's depth camera) agree on the optical
axis only. Pixels that see flat ground match the Ideal Ground Depth of the file's pose to the grey level in the
right kind, and off the centre not in the other: exact data of either kind score about 0.95 with their own kind
and 0.3 with the other (median share of non-sky pixels). ``dapm-lightning doctor`` reports this per split;
training warns at start-up from a sample of the training files.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
import torch

from dapm_lightning.geometry.constants import MAX_DEPTH_M, SKY_GREY
from dapm_lightning.geometry.depth_codec import depth_to_grey
from dapm_lightning.geometry.igd import DepthKind, ideal_ground_depth

AGREE_LEVELS = 2
"""A pixel agrees with the flat ground of a pose when its grey level is within 2 of the grey level of the
pose's IGD (one 8-bit level is a depth factor of 1.027: about 5 %)."""
DEPTH_KIND_GAIN = 0.3
"""The other depth kind is named when its median agreement exceeds the kind in use by this much (and is at least
twice it)."""
CHECK_WIDTH = 128
"""Depth maps are compared at this width at most (nearest-neighbour downsampling keeps grey levels)."""


def other_kind(depth_kind: DepthKind) -> DepthKind:
    """The depth kind that is not ``depth_kind``."""
    return "planar" if depth_kind == "range" else "range"


def at_check_width(depth_grey: np.ndarray) -> np.ndarray:
    """``depth_grey`` narrowed to :data:`CHECK_WIDTH` by taking the pixel at each new pixel's centre."""
    if depth_grey.shape[1] <= CHECK_WIDTH:
        return depth_grey
    scale = CHECK_WIDTH / depth_grey.shape[1]
    return cv2.resize(depth_grey, (CHECK_WIDTH, max(1, round(depth_grey.shape[0] * scale))),
                      interpolation=cv2.INTER_NEAREST_EXACT)


def on_flat_ground(depth_grey: np.ndarray, igd_grey: np.ndarray) -> np.ndarray:
    """The non-sky pixels of ``depth_grey`` (``[H, W]`` uint8) within :data:`AGREE_LEVELS` grey levels of a ground.

    ``igd_grey``: the grey levels (int16) of the IGD of one pose ``[H, W]`` or of several ``[K, H, W]``; where it is
    sky no pixel agrees. Returns a bool mask of ``igd_grey``'s shape.
    """
    above = depth_grey.astype(np.int16) - igd_grey
    return (np.abs(above) <= AGREE_LEVELS) & (igd_grey < SKY_GREY) & (depth_grey < SKY_GREY)


def flat_ground_of_pose(depth_grey: np.ndarray, pose: np.ndarray, depth_kind: DepthKind,
                        max_depth: float = MAX_DEPTH_M) -> np.ndarray:
    """:func:`on_flat_ground` against the ``depth_kind`` IGD of one ``pose`` (height, pitch, roll, fov).

    ``pose``: ``[4]``, computed in its own floating dtype; ``max_depth``: the metres grey 255 means.
    """
    igd = ideal_ground_depth(torch.from_numpy(np.asarray(pose)), depth_grey.shape, depth_kind=depth_kind,
                             max_depth=max_depth)[0, 0].numpy()
    return on_flat_ground(depth_grey, depth_to_grey(igd, max_depth).astype(np.int16))


def flat_ground_agreement(depth_grey: np.ndarray, pose: np.ndarray, depth_kind: DepthKind,
                          max_depth: float = MAX_DEPTH_M) -> float:
    """Share of the non-sky pixels of ``depth_grey`` that lie on the flat ground of ``pose``; 0 when all is sky.

    ``depth_grey``: ``[H, W]`` uint8, grey 255 at ``max_depth`` metres; a pixel counts within :data:`AGREE_LEVELS`
    grey levels of the ``depth_kind`` IGD of ``pose`` (height, pitch, roll, fov).
    """
    agree = flat_ground_of_pose(depth_grey, np.asarray(pose, np.float64), depth_kind, max_depth)
    return float(agree.sum() / max(int((depth_grey < SKY_GREY).sum()), 1))


def depth_kind_mismatch(depth_kind: DepthKind, agreement: float, agreement_other: float) -> str | None:
    """What to change when the files fit the other kind's flat ground far better than ``depth_kind``, else None.

    Args:
        agreement, agreement_other: median :func:`flat_ground_agreement` with ``depth_kind`` and with the other.
    """
    if agreement_other < max(2.0 * agreement, agreement + DEPTH_KIND_GAIN):
        return None
    other = other_kind(depth_kind)
    return (f"the depth maps agree with the {other} IGD of their poses ({agreement_other:.2f} of the non-sky "
            f"pixels, median) far more than with the {depth_kind} IGD ({agreement:.2f}): they look {other}. Set "
            f"data.init_args.depth_kind and model.net.igd.depth_kind to {other} (`dapm-lightning doctor ROOT "
            f"--depth_kind {other}` checks the set)")


def sampled_mismatch(read_grey: Callable[[int], np.ndarray], poses: np.ndarray, depth_kind: DepthKind,
                     count: int = 32, max_depth: float = MAX_DEPTH_M) -> str | None:
    """:func:`depth_kind_mismatch` over ``count`` files spread evenly over a set.

    Args:
        read_grey: ``index -> [H, W] uint8`` depth grey of sample ``index`` (an unreadable file raises: it is skipped).
        poses: ``[N, 4]`` the set's poses.
        max_depth: the metres grey 255 means.
    """
    agreements: list[tuple[float, float]] = []
    for index in np.unique(np.linspace(0, len(poses) - 1, min(count, len(poses))).round().astype(int)):
        try:
            grey = at_check_width(read_grey(int(index)))
        except (OSError, ValueError):
            continue
        agreements.append((flat_ground_agreement(grey, poses[index], depth_kind, max_depth),
                           flat_ground_agreement(grey, poses[index], other_kind(depth_kind), max_depth)))
    if not agreements:
        return None
    own, other = np.median(np.array(agreements), axis=0)
    return depth_kind_mismatch(depth_kind, float(own), float(other))
