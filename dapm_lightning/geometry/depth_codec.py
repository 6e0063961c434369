"""Log depth encoding of UAPD (paper Eq. 20): metres <-> [0, 1] <-> 8-bit grey."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from dapm_lightning.geometry.constants import MAX_DEPTH_M, MIN_DEPTH_LIMIT_M, SKY_GREY
from dapm_lightning.geometry.precision import float32


def check_depth_limit(max_depth: float, setting: str) -> float:
    """``max_depth`` as a float when it can be a depth limit (finite, above ``MIN_DEPTH_LIMIT_M``).

    Raises:
        ValueError: naming ``setting`` (``data.init_args.max_depth``, ``model.net.igd.max_depth``) and the fix.
    """
    value = float(max_depth)
    if not (math.isfinite(value) and value > MIN_DEPTH_LIMIT_M):
        raise ValueError(f"{setting}: {max_depth!r}, but a depth limit must be a number of metres above "
                         f"{MIN_DEPTH_LIMIT_M:g}: the distance grey 255 of the depth files means, beyond which a pixel "
                         f"is sky (UAPD: {MAX_DEPTH_M:g}).\nFix: --{setting} {MAX_DEPTH_M:g}, or the limit the data "
                         "set was written with (`dapm-lightning synth --max_depth`), in the data's and the model's "
                         "settings alike")
    return value


@float32
def encode_log_depth(depth_m: Tensor, max_depth: float = MAX_DEPTH_M) -> Tensor:
    """Metres to normalised log depth ``log2(d + 1) / log2(max_depth + 1)`` in [0, 1].

    Depths are clamped to ``[0, max_depth]`` first, so sky (beyond ``max_depth``) encodes to 1.

    Convention:
        ``encode_log_depth(1000.0) == 1``; ``encode_log_depth(0.0) == 0``; one 8-bit grey step is a
        depth factor of about ``1001 ** (1 / 255) ≈ 1.027``.
    """
    return torch.log2(depth_m.clamp(0.0, max_depth) + 1.0) / math.log2(max_depth + 1.0)


@float32
def decode_log_depth(depth_norm: Tensor, max_depth: float = MAX_DEPTH_M) -> Tensor:
    """Inverse of :func:`encode_log_depth`: normalised log depth in [0, 1] to metres."""
    return torch.exp2(depth_norm.clamp(0.0, 1.0) * math.log2(max_depth + 1.0)) - 1.0


def log_depth_grey(depth_m: Tensor, max_depth: float = MAX_DEPTH_M) -> Tensor:
    """Metres to continuous grey levels ``SKY_GREY * encode_log_depth(d)`` in [0, 255] (the authors' metric space)."""
    return SKY_GREY * encode_log_depth(depth_m, max_depth)


def norm_to_grey(depth_norm: Tensor) -> np.ndarray:
    """Normalised log depth ``[...]`` in [0, 1] to uint8 grey ``round(SKY_GREY * x)`` (for pictures of maps)."""
    return (depth_norm.detach().float().clamp(0, 1) * SKY_GREY).round().to(torch.uint8).cpu().numpy()


def depth_to_grey(depth_m: np.ndarray, max_depth: float = MAX_DEPTH_M) -> np.ndarray:
    """Metres to UAPD's 8-bit grey ``floor(255 * encode_log_depth(d))`` (uint8; 255 = at or beyond max_depth)."""
    clamped = np.clip(np.nan_to_num(depth_m, nan=0.0, posinf=max_depth), 0.0, max_depth)
    scaled = SKY_GREY * np.log2(clamped + 1.0) / math.log2(max_depth + 1.0)
    grey: np.ndarray = np.floor(scaled + 1e-9).astype(np.uint8)
    return grey


def grey_to_depth(grey: np.ndarray, max_depth: float = MAX_DEPTH_M) -> np.ndarray:
    """UAPD 8-bit grey to metres (float32), decoding ``g / 255``; grey 255 decodes to exactly ``max_depth``."""
    norm = grey.astype(np.float64) / SKY_GREY
    depth = (np.exp2(norm * math.log2(max_depth + 1.0)) - 1.0).astype(np.float32)
    return np.where(grey == SKY_GREY, np.float32(max_depth), depth)  # exact, so sky = (depth >= max_depth)


def sky_at_limit(depth_m: Tensor, sky: Tensor, max_depth: float = MAX_DEPTH_M) -> Tensor:
    """``depth_m`` exactly ``max_depth`` where ``sky``, strictly below it (the float32 just under) elsewhere.

    So that ``depth >= max_depth`` is the sky mask again, whatever the interpolation or a scale did to the ground.
    """
    below = float(np.nextafter(np.float32(max_depth), np.float32(0)))
    return torch.where(sky, torch.full_like(depth_m, max_depth), depth_m.clamp(max=below))


IGD_RATIO_RANGE = (2.0**-10, 1.25)
"""What the ``igd_ratio`` parametrisation covers by default: depth / IGD from 1/1024 (1 m at the 1000 m horizon, a
mast close to the lens) to 1.25 (ground up to 25 % farther than the flat ground of the pose used: terrain below the
take-off level, or a pose whose height is too low). Above the horizon the IGD is ``max_depth``, so the ratio is of
the depth limit and the range spans 1 m to the limit, as the absolute depth does. The upper end is a network setting
(``model.net.igd_ratio_max``); the lower end is fixed."""
GROUND_CENTRED_RATIO_MAX = 2.0 ** (10 * 64 / 62.5 - 10)
"""The upper end (about 1.181) that puts the flat ground (ratio 1) at the centre of a bin of a 64-bin stage (the
63rd), not on the edge between two as 1.25 does: a mode read from the bins then finds the ground where it is, not
half a bin (6 %) short. A value of ``model.net.igd_ratio_max`` (not the default: docs/transfer.md)."""


def _ratio_log2(ratio_max: float) -> tuple[float, float]:
    return math.log2(IGD_RATIO_RANGE[0]), math.log2(ratio_max)


def flat_ground_norm(ratio_max: float = IGD_RATIO_RANGE[1]) -> float:
    """The normalised log ratio of a depth equal to the IGD (the flat ground itself): about 0.969 for 1.25."""
    lo, hi = _ratio_log2(ratio_max)
    return -lo / (hi - lo)


def flat_ground_logit(ratio_max: float = IGD_RATIO_RANGE[1]) -> float:
    """The logit of :func:`flat_ground_norm`.

    The ``igd_ratio`` head's output is a correction to it, so an untrained head predicts the flat ground (a sigmoid at
    0 would start at a ratio of 0.035, far from every target).
    """
    norm = flat_ground_norm(ratio_max)
    return math.log(norm / (1.0 - norm))


@float32
def encode_igd_ratio(depth_m: Tensor, igd_m: Tensor, max_depth: float = MAX_DEPTH_M,
                     ratio_max: float = IGD_RATIO_RANGE[1]) -> Tensor:
    """Metres to the normalised log ratio ``(log2(d / igd) - log2 lo) / (log2 hi - log2 lo)`` in [0, 1].

    ``igd_m``: the ideal ground depth of the pose the network uses; ``lo`` is ``IGD_RATIO_RANGE[0]``, ``hi`` is
    ``ratio_max`` (:data:`IGD_RATIO_RANGE`); depths are clamped to ``[0, max_depth]`` and ratios outside the range to
    its ends.
    """
    ratio = depth_m.clamp(1e-6, max_depth) / igd_m.clamp(1e-3, max_depth)
    lo, hi = _ratio_log2(ratio_max)
    return ((torch.log2(ratio) - lo) / (hi - lo)).clamp(0.0, 1.0)


@float32
def decode_igd_ratio(ratio_norm: Tensor, igd_m: Tensor, max_depth: float = MAX_DEPTH_M,
                     ratio_max: float = IGD_RATIO_RANGE[1]) -> Tensor:
    """Inverse of :func:`encode_igd_ratio`: metres in ``[0, max_depth]``."""
    lo, hi = _ratio_log2(ratio_max)
    ratio = torch.exp2(lo + ratio_norm.clamp(0.0, 1.0) * (hi - lo))
    return (ratio * igd_m.clamp(1e-3, max_depth)).clamp(max=max_depth)
