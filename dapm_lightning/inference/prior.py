"""Telemetry in prediction: pose priors into the network (conditioning) and metric scale from a known pose.

Two ways to use what the drone knows, and both together (:data:`PriorMode`):

- ``condition``: the prior enters the network (:class:`~dapm_lightning.models.prior.PosePrior`): fused with its
  pose before the IGD feature, so the depth head sees the ground of the known pose;
- ``scale``: the network runs without it; its depth is then rescaled so that the pixels it sees as ground match
  the ideal ground depth of the known pose (:func:`ground_scale`, the exact ground of :func:`flat_ground`): works
  with any checkpoint, no retraining;
- ``both``: conditioning, then the scale fit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from dapm_lightning.geometry.constants import POSE_KEYS, SKY_PROBABILITY_THRESHOLD, pose_field
from dapm_lightning.geometry.depth_codec import sky_at_limit
from dapm_lightning.geometry.igd import IGDSpec, ideal_ground_depth
from dapm_lightning.inference.telemetry import PoseTelemetry, TelemetryError
from dapm_lightning.inference.telemetry.pose import limit_error
from dapm_lightning.models.dapm import InferenceOutput
from dapm_lightning.models.prior import EXACT_SIGMA, PRIOR_MODES, PosePrior, PriorMode, fuse_pose

GROUND_AGREEMENT = 0.25
"""A pixel is ground to the model where its depth is within 25 % of the flat ground of its own pose."""
MIN_GROUND_SHARE = 0.02
"""Below this share of ground pixels, the scale comes from the heights (known / predicted) instead."""


API_PROVENANCE = "Python API prior"
"""The provenance of a component given to the Python API as a dict or an array."""


def _checked(k: int, key: str, value: Any) -> float:
    """Prior ``k``'s component ``key`` as float: NaN / None = unknown; impossible values refused as in a CSV."""
    if value is None:
        return math.nan
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise TelemetryError(f"pose prior {k}: {pose_field(key)} = {value!r} is not a number") from None
    if not math.isnan(number) and (why := limit_error(key, number)) is not None:
        raise TelemetryError(f"pose prior {k}: {pose_field(key)} = {value!r} {why}; give NaN (or leave it out) for "
                             "unknown")
    return number


def prior_rows(values: Sequence[Any]) -> tuple[np.ndarray, list[tuple[str, ...]]]:
    """``[N, 4]`` priors (NaN where unknown) and per image the provenance of each known component.

    An entry: None; a ``[4]`` array / sequence (height m, pitch, roll, fov deg; NaN unknown); a mapping with
    any of ``height``/``height_m``, ``pitch``/``pitch_deg``, ``roll``/``roll_deg``, ``fov``/``fov_deg``; or a
    :class:`~dapm_lightning.inference.telemetry.PoseTelemetry` (its own provenance). Values are checked as the
    telemetry CSV's are: a height <= 0, |pitch| or |roll| > 180, a FoV outside (0, 180) or an infinite value is an
    error.

    Raises:
        TelemetryError: an impossible value or one that is not a number (a ``ValueError``). ValueError: an
            unknown key, an array of another size.
    """
    rows = np.full((len(values), 4), np.nan)
    provenance: list[tuple[str, ...]] = []
    for k, value in enumerate(values):
        if isinstance(value, PoseTelemetry):
            rows[k] = value.values()
            provenance.append(value.provenance)
            continue
        if value is None:
            pass
        elif isinstance(value, Mapping):
            unknown = set(value) - set(POSE_KEYS) - {pose_field(key) for key in POSE_KEYS}
            if unknown:
                raise ValueError(f"pose prior {k}: unknown key(s) {sorted(unknown)}; use height_m, pitch_deg, "
                                 "roll_deg, fov_deg (or height, pitch, roll, fov)")
            for i, key in enumerate(POSE_KEYS):
                rows[k, i] = _checked(k, key, value.get(key, value.get(pose_field(key))))
        else:
            row = np.asarray(value.cpu() if isinstance(value, Tensor) else value, dtype=np.float64).reshape(-1)
            if row.shape != (4,):
                raise ValueError(f"pose prior {k}: expected 4 values (height m, pitch, roll, fov deg), got {row.shape}")
            rows[k] = [_checked(k, key, v) for key, v in zip(POSE_KEYS, row.tolist())]
        provenance.append(tuple(API_PROVENANCE if np.isfinite(v) else "" for v in rows[k]))
    return rows, provenance


def as_prior(values: Sequence[Any], sigma: Sequence[float] | Tensor = EXACT_SIGMA) -> PosePrior | None:
    """A :class:`PosePrior` from one entry per image (:func:`prior_rows`), or None when nothing is known.

    Raises:
        TelemetryError: an impossible value (height <= 0, |pitch| or |roll| > 180, FoV outside (0, 180), inf).
    """
    rows, _ = prior_rows(values)
    return PosePrior.from_rows(torch.from_numpy(rows).float(), torch.as_tensor(sigma, dtype=torch.float32))


def pose_sources(prior: PosePrior | None, batch: int) -> list[dict[str, str]]:
    """Per image and component where the pose used comes from: ``telemetry`` (σ = 0), ``fused`` or ``network``."""
    if prior is None:
        return [dict.fromkeys(POSE_KEYS, "network") for _ in range(batch)]
    known, exact = prior.known.cpu(), (prior.sigma == 0).cpu()
    return [{key: ("telemetry" if exact[b, i] else "fused") if known[b, i] else "network"
             for i, key in enumerate(POSE_KEYS)} for b in range(batch)]


def ground_scale(depth_m: Tensor, sky: Tensor, igd_used: Tensor, igd_network: Tensor | None, height_ratio: Tensor,
                 max_depth: float) -> tuple[Tensor, list[str]]:
    """Per image the factor that puts the depth on the metric scale of the known pose, and how it was found.

    Args:
        depth_m, sky: ``[B, 1, h, w]`` the network's depth and sky mask.
        igd_used: ``[B, 1, h, w]`` the flat ground of the pose used (telemetry where known).
        igd_network: ``[B, 1, h, w]`` the flat ground of the pose the depth was made with; None (a model
            without a pose): ground is where the depth has the shape of ``igd_used`` up to one scale.
        height_ratio: ``[B]`` known / predicted height (NaN where the height is unknown).

    Returns:
        ``([B] scale, [B] method)``: the median of ``igd_used / depth`` over the pixels the model sees as ground
        (its depth within :data:`GROUND_AGREEMENT` of its own pose's ground, and both grounds in view) when they
        are at least :data:`MIN_GROUND_SHARE` of the image (``"ground"``); else the height ratio (``"height"``);
        else 1 (``"none"``).
    """
    scales, methods = [], []
    band = math.log1p(GROUND_AGREEMENT)
    for b in range(depth_m.shape[0]):
        depth, igd_known = depth_m[b].double().clamp_min(1e-6), igd_used[b].double()
        ground = (~sky[b]) & (igd_known < max_depth)
        if igd_network is not None:
            igd_own = igd_network[b].double()
            ground &= (igd_own < max_depth) & ((depth / igd_own.clamp_min(1e-6)).log().abs() < band)
        elif ground.any():
            ratio = (igd_known / depth).log()
            ground &= (ratio - ratio[ground].median()).abs() < band
        if ground.float().mean() >= MIN_GROUND_SHARE:
            scales.append(float((igd_known[ground] / depth[ground]).median()))
            methods.append("ground")
        elif math.isfinite(float(height_ratio[b])):
            scales.append(float(height_ratio[b]))
            methods.append("height")
        else:
            scales.append(1.0)
            methods.append("none")
    return torch.tensor(scales, dtype=depth_m.dtype, device=depth_m.device), methods


def flat_ground(spec: IGDSpec, pose: Tensor, size: tuple[int, int]) -> Tensor:
    """``[B, 1, h, w]`` metres: the true flat ground of ``pose``, the exact ray-plane intersection (pinhole IGD).

    Of the model's depth kind and limit, whatever IGD formula the model's feature uses: a model with the paper's
    approximation (``model.net.igd.model: paper``, the paper configs) still predicts real depth, and that
    approximation is 0.45-1.51 times the true ground over the UAPD ranges (most at wide FoV), so the scale fit and
    the IGD bound measure against this one.
    """
    return ideal_ground_depth(pose, size, model="pinhole", depth_kind=spec.depth_kind, max_depth=spec.max_depth)


class PriorApplied(NamedTuple):
    """What :func:`apply_pose_prior` returns: the outputs with the prior applied, and how, per image."""

    output: InferenceOutput
    sources: list[dict[str, str]]
    """Per image and component: ``network``, ``telemetry`` or ``fused`` (:func:`pose_sources`)."""
    scale_from: list[str]
    """Per image, how the scale fit found its factor: ``ground``, ``height`` or ``none``."""


def apply_pose_prior(output: InferenceOutput, prior: PosePrior | None, mode: PriorMode,
                     spec: IGDSpec) -> PriorApplied:
    """Network outputs with a prior applied as ``mode`` says.

    Args:
        output: at the network size, with ``pose_spread`` (the network's pose-bins spread, for fusing here;
            without it a fixed spread); with ``condition`` or ``both`` the network has already fused the prior
            (``pose`` the pose used, ``pose_network`` its own). Without ``pose`` (a depth-only model), a prior
            that knows all four components is the pose.
        prior: the batch's prior (None: nothing known; the outputs come back unchanged).

    The scale fit compares the depth with the ground of the pose it was made with: the network's own pose
    in ``scale`` mode, the pose used in ``both`` (there it corrects only what conditioning left).

    Returns:
        with ``scale``/``both``, ``depth_m`` rescaled to the pose used (sky kept at the limit); ``pose`` and
        ``pose_network`` the pose used and the network's own.
    """
    batch = output.batch_size
    if prior is None:
        return PriorApplied(output, pose_sources(None, batch), ["none"] * batch)
    if mode not in PRIOR_MODES:
        raise ValueError(f"unknown telemetry mode {mode!r}; choose from {', '.join(PRIOR_MODES)}")
    device = output.device
    prior = prior.to(device)
    made_with: Tensor | None
    if output.pose is None:  # a depth-only model: a fully known pose is the pose, for K, points and the scale
        if not bool(prior.known.all()):
            return PriorApplied(output, pose_sources(None, batch), ["none"] * batch)
        output = output.replace(pose=prior.value.to(device))
        made_with = None
    elif output.pose_network is not None:  # the network was given the prior: its depth is made with the pose used
        made_with = output.pose
    else:  # the network ran without the prior: fuse here, with its bins spread when given
        network = output.pose
        used = spec.denormalize(fuse_pose(spec.normalize(network.float()), prior, spec,
                                          output.pose_spread)).to(network.dtype)
        output = output.replace(pose=used, pose_network=network)
        made_with = network
    methods = ["none"] * batch
    if mode in ("scale", "both") and output.depth_m is not None and output.pose is not None:
        depth = output.depth_m
        size = (depth.shape[-2], depth.shape[-1])
        sky = (output.sky_prob > SKY_PROBABILITY_THRESHOLD) if output.sky_prob is not None \
            else depth >= spec.max_depth
        used_pose = output.pose.float()
        ratio = torch.full_like(used_pose[:, 0], float("nan"))
        if made_with is not None:
            made_with = made_with.float()
            ratio = torch.where(prior.known[:, 0], used_pose[:, 0] / made_with[:, 0].clamp_min(1e-3), ratio)
        scale, methods = ground_scale(depth, sky, flat_ground(spec, used_pose, size),
                                      None if made_with is None else flat_ground(spec, made_with, size), ratio,
                                      spec.max_depth)
        output = output.replace(depth_m=sky_at_limit(depth * scale.view(-1, 1, 1, 1), sky, spec.max_depth))
    return PriorApplied(output, pose_sources(prior, batch), methods)


def bound_by_ground(output: InferenceOutput, prior: PosePrior | None, spec: IGDSpec, margin: float) -> InferenceOutput:
    """Each pixel's depth capped at ``1 + margin`` times the ideal ground depth of the pose used.

    That ground is the exact one (:func:`flat_ground`), also for a model whose IGD feature uses the paper's
    approximation, which lies up to 44 % short of the true ground and would cap a correct flat-ground depth there.

    The assumption: a flat ground at the known height, so nothing visible below the horizon lies farther than the
    ground along its ray; ``margin`` allows terrain below the take-off level and the height's own error. Applied to
    the images whose prior knows the height (the IGD's scale; with the other components from the pose used,
    telemetry or fused); where the IGD is at the depth limit (above the horizon) nothing is capped. A pixel the
    bound reaches cannot be sky: its ``sky_prob`` becomes 0. For models trained in absolute depth (an ``igd_ratio``
    model bounds itself at ``model.net.igd_ratio_max``, 1.25 by default, times the ground of the pose it uses).
    """
    if prior is None or output.depth_m is None or output.pose is None:
        return output
    applies = prior.known[:, 0].to(output.device)
    if not bool(applies.any()):
        return output
    depth = output.depth_m
    igd = flat_ground(spec, output.pose.float(), (depth.shape[-2], depth.shape[-1]))
    cap = igd * (1.0 + margin)
    reached = applies.view(-1, 1, 1, 1) & (igd < spec.max_depth) & (cap < spec.max_depth)
    bounded = torch.where(reached, torch.minimum(depth, cap.to(depth.dtype)), depth)
    sky_prob = output.sky_prob
    if sky_prob is not None:
        sky_prob = torch.where(reached, torch.zeros_like(sky_prob), sky_prob)
    return output.replace(depth_m=bounded, sky_prob=sky_prob)
