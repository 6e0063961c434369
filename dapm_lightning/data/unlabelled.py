"""Unlabelled images for prediction: one image (:class:`PredictInput`) and a batch of them (:class:`PredictBatch`).

Every way to predict (the one-line command, the Lightning ``predict`` subcommand, the Python API) feeds the
network a :class:`PredictBatch`: the images at the network size, each image's name and original size, and the
pose prior of the batch (telemetry) with the run's :class:`~dapm_lightning.models.prior.PriorSettings`.
Unlike a training :class:`~dapm_lightning.data.sample.Sample`, nothing here is a label.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from dapm_lightning.models.prior import PosePrior, PriorMode, PriorSettings


@dataclass
class PredictInput:
    """One image to predict.

    Attributes:
        image: ``[3, h, w]`` uint8 RGB at the network size.
        name: what its files are called (the file stem, ``STEM_f<frame>`` for a video frame).
        size: ``(H, W)`` of the original image: predictions come back at this size.
        source: the file it came from (``VIDEO#frame`` for a video frame).
        prior: ``[4]`` what telemetry knows of its pose (height m, pitch, roll, fov deg; NaN where unknown).
        rgb: the original ``[H, W, 3]`` uint8 pixels when asked for (point colours, the contact sheet).
        provenance: per pose component (height, pitch, roll, fov), where its prior came from (``flight.csv line
            12``, ``DJI_0001.JPG XMP drone-dji:RelativeAltitude``, ``DJI_0005.SRT subtitle 215 rel_alt``);
            ``""`` where unknown.
    """

    image: Tensor
    name: str
    size: tuple[int, int]
    source: str = ""
    prior: Tensor = field(default_factory=lambda: torch.full((4,), float("nan")))
    rgb: np.ndarray | None = None
    provenance: tuple[str, ...] = ("", "", "", "")
    time_s: float | None = None
    """A video frame's time in the video (seconds); None for an image."""


@dataclass
class PredictBatch:
    """A batch of :class:`PredictInput` of one network size, with its pose prior.

    Attributes:
        images: ``[B, 3, h, w]`` uint8 (or float in [0, 1]) at the network size.
        names, sizes, sources, rgb, provenance: per image, as in :class:`PredictInput`.
        prior: the batch's :class:`PosePrior` (σ from the run's settings), None when nothing is known.
        mode: how the prior is used (:data:`~dapm_lightning.models.prior.PriorMode`).
        igd_bound: the margin of the IGD bound on the depth (None: no bound), from the run's settings.
    """

    images: Tensor
    names: list[str]
    sizes: list[tuple[int, int]]
    sources: list[str] = field(default_factory=list)
    prior: PosePrior | None = None
    mode: PriorMode = "condition"
    rgb: list[np.ndarray | None] = field(default_factory=list)
    provenance: list[tuple[str, ...]] = field(default_factory=list)
    times: list[float | None] = field(default_factory=list)
    igd_bound: float | None = None

    @classmethod
    def collate(cls, items: Sequence[PredictInput], settings: PriorSettings = PriorSettings()) -> PredictBatch:  # noqa: B008
        """One batch of ``items`` (all of one network size), their priors used as ``settings`` say."""
        if len({tuple(item.image.shape) for item in items}) > 1:
            raise ValueError("a predict batch holds images of one network size; batch them by size "
                             "(SizeBatchSampler)")
        prior = PosePrior.from_rows(torch.stack([item.prior.float() for item in items]), settings.sigma)
        return cls(torch.stack([item.image for item in items]), [item.name for item in items],
                   [item.size for item in items], [item.source for item in items], prior, settings.mode,
                   [item.rgb for item in items], [item.provenance for item in items], [item.time_s for item in items],
                   settings.igd_bound)

    def __len__(self) -> int:
        return len(self.names)

    @property
    def network_prior(self) -> PosePrior | None:
        """The prior given to the network: the batch's, unless the mode applies it only afterwards (``scale``)."""
        return self.prior if self.mode != "scale" else None

    def to(self, device: torch.device | str, non_blocking: bool = False) -> PredictBatch:
        """The batch with its tensors on ``device`` (what Lightning calls to move a batch)."""
        return dataclasses.replace(self, images=self.images.to(device, non_blocking=non_blocking),
                                   prior=None if self.prior is None else self.prior.to(device))

    def pin_memory(self) -> PredictBatch:
        """The batch with its images in pinned memory (``DataLoader(pin_memory=True)``)."""
        return dataclasses.replace(self, images=self.images.pin_memory())


@dataclass(frozen=True)
class PredictCollate:
    """``DataLoader`` ``collate_fn`` making :class:`PredictBatch` with one run's prior settings (picklable)."""

    settings: PriorSettings = PriorSettings()

    def __call__(self, items: Sequence[PredictInput]) -> PredictBatch:
        return PredictBatch.collate(items, self.settings)
