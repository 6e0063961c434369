"""Pose priors: what the drone already knows (telemetry: altitude, gimbal pitch and roll, focal length).

A :class:`PosePrior` holds per image and per component a value in physical units (NaN: unknown) and its
uncertainty σ. :func:`fuse_pose` combines it with the network's own estimate: σ = 0 replaces the component,
σ > 0 weighs the two by their inverse variances, the network's variance being the spread of its last pose
bins distribution (the PQB's own uncertainty; a fixed spread without pose bins). The fused pose is what the
IGD feature sees and what inference reports; the losses keep training the network's own estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.geometry.pose import pose_bounds
from dapm_lightning.options import EXACT_SIGMA as EXACT_SIGMA
from dapm_lightning.options import IGD_BOUND_MARGIN as IGD_BOUND_MARGIN
from dapm_lightning.options import PRIOR_MODES as PRIOR_MODES
from dapm_lightning.options import PriorMode as PriorMode

NETWORK_SPREAD_WITHOUT_BINS = 0.05
"""Normalised standard deviation assumed for a network without pose bins (about 4.5 m of height, 5.5° of pitch)."""
MIN_NETWORK_SPREAD = 1e-3
"""Lower bound of the network's normalised standard deviation (a bins distribution can be one-hot)."""


@dataclass(frozen=True)
class PriorSettings:
    """How one prediction run uses its pose priors: ``mode`` (:data:`PriorMode`), ``sigma`` and ``igd_bound``.

    ``sigma``: per component (height m, pitch, roll, fov deg) the telemetry's standard deviation where a prior
    gives none; 0 replaces the network's value, more fuses the two. ``igd_bound``: the margin of the IGD bound
    (:func:`~dapm_lightning.inference.prior.bound_by_ground`: images whose telemetry gives the height get no depth
    beyond ``1 + igd_bound`` times the flat ground of the pose used; on by default); None: no bound. All are checked
    here, once.
    """

    mode: PriorMode = "condition"
    sigma: tuple[float, float, float, float] = EXACT_SIGMA
    igd_bound: float | None = IGD_BOUND_MARGIN

    def __post_init__(self) -> None:
        if self.mode not in PRIOR_MODES:
            raise ValueError(f"telemetry_mode must be one of {', '.join(PRIOR_MODES)}, got {self.mode!r}")
        sigma = tuple(float(v) for v in self.sigma)
        if len(sigma) != 4 or min(sigma) < 0:
            raise ValueError(f"telemetry_sigma: four standard deviations >= 0 (height m, pitch, roll, fov deg), "
                             f"got {list(self.sigma)}")
        object.__setattr__(self, "sigma", sigma)
        if self.igd_bound is not None and not 0.0 <= float(self.igd_bound) < 10.0:
            raise ValueError(f"igd_bound: a margin in [0, 10) (0.1: 10 % beyond the flat ground), got {self.igd_bound}")

    @property
    def conditions(self) -> bool:
        """Whether the prior goes into the network (``condition`` or ``both``)."""
        return self.mode != "scale"


@dataclass(frozen=True)
class PosePrior:
    """Known pose components, per image.

    Args:
        value: ``[B, 4]`` (height m, pitch deg, roll deg, fov deg); NaN where unknown.
        sigma: ``[B, 4]`` standard deviation in the same units, >= 0 (0: exact, replaces the network's value);
            broadcastable (``[4]`` for one σ per component).
    """

    value: Tensor
    sigma: Tensor
    mask: Tensor | None = None
    """``[B, 4]`` bool: which components are known, when given apart from NaN (an exported graph holds no NaN)."""

    def __post_init__(self) -> None:
        if self.value.ndim != 2 or self.value.shape[-1] != 4:
            raise ValueError(f"a pose prior's value must be [B, 4], got {tuple(self.value.shape)}")
        sigma = torch.as_tensor(self.sigma, dtype=self.value.dtype, device=self.value.device)
        sigma = torch.nan_to_num(sigma, nan=0.0).expand_as(self.value)
        if not torch.compiler.is_exporting() and (sigma < 0).any():
            raise ValueError("a pose prior's sigma must be >= 0")
        object.__setattr__(self, "sigma", sigma)

    @classmethod
    def from_rows(cls, value: Tensor, sigma: Tensor | tuple[float, ...]) -> PosePrior | None:
        """A prior from ``[B, 4]`` rows (NaN where unknown), or None when nothing at all is known."""
        if not bool(torch.isfinite(value).any()):
            return None
        return cls(value.float(), torch.as_tensor(sigma, dtype=torch.float32, device=value.device))

    @property
    def known(self) -> Tensor:
        """``[B, 4]`` bool: which components are given."""
        return torch.isfinite(self.value) if self.mask is None else self.mask

    def to(self, device: torch.device | str) -> PosePrior:
        """The same prior on ``device``."""
        return PosePrior(self.value.to(device), self.sigma.to(device),
                         None if self.mask is None else self.mask.to(device))


PRIOR_FEATURES = 12
"""Width of :func:`prior_features`: per component whether it is known, its normalised value and σ."""


def prior_features(prior: PosePrior | None, spec: IGDSpec, like: Tensor) -> Tensor:
    """What the network is told of the telemetry (``DAPMConfig.pose_prior_input``, ``depth_prior_input``): ``[B, 12]``.

    Per component (height, pitch, roll, fov): 1 where known, else 0; the normalised value (clamped to
    [-0.5, 1.5]) where known, else 0; the normalised σ where known, else 0. Zeros without a prior (``like``:
    ``[B, ...]``, gives the batch size and device), as when nothing is known, so an exported graph fed no telemetry
    computes what eager does.
    """
    batch = like.shape[0]
    if prior is None:
        return torch.zeros(batch, PRIOR_FEATURES, device=like.device)
    known = prior.known.to(like.device).expand(batch, 4)
    value = torch.where(known, prior.value.to(like.device).float(), torch.zeros((), device=like.device))
    _, ranges = pose_bounds(spec.pose_ranges, value)
    value_norm = spec.normalize(value).clamp(-0.5, 1.5)
    sigma_norm = prior.sigma.to(like.device).float().expand(batch, 4) / ranges
    zero = torch.zeros_like(value_norm)
    return torch.cat([known.float(), torch.where(known, value_norm, zero), torch.where(known, sigma_norm, zero)], 1)


def bins_spread(bin_logits: Tensor) -> Tensor:
    """``[B, 4, n]`` logits over ``n`` equal bins of [0, 1] -> ``[B, 4]`` standard deviation of the distribution."""
    n = bin_logits.shape[-1]
    centres = (torch.arange(n, device=bin_logits.device, dtype=torch.float32) + 0.5) / n
    probs = bin_logits.float().softmax(dim=-1)
    mean = (probs * centres).sum(-1, keepdim=True)
    variance = (probs * (centres - mean) ** 2).sum(-1)
    return variance.clamp_min(0).sqrt().clamp_min(MIN_NETWORK_SPREAD)


def fuse_pose(pose_norm: Tensor, prior: PosePrior, spec: IGDSpec, network_spread: Tensor | None) -> Tensor:
    """The network's normalised pose ``[B, 4]`` combined with a prior, normalised ``[B, 4]`` float32.

    Unknown components keep the network's value; σ = 0 takes the prior's; σ > 0 the inverse-variance mean
    of the two (``network_spread``: ``[B, 4]`` normalised standard deviation of the network's estimate).
    """
    known = prior.known.to(pose_norm.device)
    if not torch.compiler.is_exporting() and not known.any():
        return pose_norm
    own = pose_norm.float()  # float32 whatever the autocast: an exact prior comes back exact
    _, ranges = pose_bounds(spec.pose_ranges, own)
    prior_norm = spec.normalize(torch.nan_to_num(prior.value.to(own), nan=0.0))
    prior_spread = prior.sigma.to(own) / ranges
    spread = torch.full_like(own, NETWORK_SPREAD_WITHOUT_BINS) if network_spread is None else network_spread.to(own)
    weight = spread**2 / (spread**2 + prior_spread**2)  # 1 where the prior is exact
    fused = own + weight * (prior_norm - own)
    return torch.where(known, fused, own)
