"""``PredictDataModule``: images, folders, glob patterns or a video for ``dapm-lightning predict``."""

from __future__ import annotations

import warnings
from typing import Any, Literal

from torch.utils.data import DataLoader

from dapm_lightning.data.datamodules import DAPMDataModule
from dapm_lightning.inference.inputs import (
    DEFAULT_BATCH_SIZE,
    NetworkSize,
    PredictSource,
    checkpoint_network_size,
    predict_loaders,
)
from dapm_lightning.inference.sources import Sources
from dapm_lightning.models.prior import EXACT_SIGMA, IGD_BOUND_MARGIN, PriorMode, PriorSettings


class PredictDataModule(DAPMDataModule):
    """Predict on images or a video of any size and aspect; no depth or pose needed.

    Args:
        source: a folder of images (sub-folders included), a glob pattern ('flight/**/*.jpg', quoted), an image,
            a video file (.mp4, .avi, .mov, ...), a .txt list of paths, or a list of those.
        image_width: network input width (height from each image's aspect); None: the checkpoint's training
            size (the same pixel count in each image's aspect; 512 x 512 for checkpoints that do not record it).
        batch_size: images per forward pass (images of one network size are batched together).
        num_workers: decoding processes.
        worker_start_method: how they start (``forkserver``, ``fork`` or ``spawn``; as training's loaders).
        frame_step: videos: keep every frame_step-th frame.
        max_frames: videos: stop after this many kept frames.
        keep_rgb: ship the original pixels with each batch (point-cloud colours, the contact sheet).
        pin_memory: DataLoader setting (GPUs).
        telemetry: the flight's pose per image: a CSV with columns name,height_m,pitch_deg,roll_deg,fov_deg (name:
            the image's file name, with or without extension, or a video frame's output name, DJI_0005_f000012;
            an empty cell or a missing column: unknown), or a DJI .SRT for the one video predicted (default: each
            video's own .SRT beside it).
        read_metadata: also read each JPEG's DJI XMP (relative altitude, gimbal pitch and roll) and EXIF focal
            length, for what the CSV does not give.
        sensor_width_mm: sensor width in mm (of the area the images cover): each image's EXIF FocalLength then gives
            its FoV, before its 35 mm equivalent (which gives it otherwise).
        strict_telemetry: stop when an image's metadata or a video's SRT cannot be read (by default that image or
            video falls back to the network's pose with one warning).
        telemetry_mode: condition (the known pose enters the network's IGD feature), scale (the depth is fitted
            to the known pose's ground afterwards; any checkpoint) or both.
        telemetry_sigma: σ of the telemetry (height m, pitch, roll, fov deg): 0 replaces the network's value,
            more fuses the two (docs/predict.md).
        igd_bound: margin of the IGD bound (docs/predict.md): images whose telemetry gives the height get no depth
            beyond ``1 + igd_bound`` times the flat ground of the pose used (default 0.1); None (``null``): no bound.
    """

    serves_prediction = True

    def __init__(self, source: str | list[str] = "images", image_width: int | None = None,
                 batch_size: int = DEFAULT_BATCH_SIZE, num_workers: int = 0, frame_step: int = 1,
                 max_frames: int | None = None,
                 keep_rgb: bool = True, pin_memory: bool = False, telemetry: str | None = None,
                 read_metadata: bool = True, sensor_width_mm: float | None = None,
                 telemetry_mode: PriorMode = "condition",
                 telemetry_sigma: tuple[float, float, float, float] = EXACT_SIGMA,
                 strict_telemetry: bool = False, igd_bound: float | None = IGD_BOUND_MARGIN,
                 worker_start_method: Literal["forkserver", "fork", "spawn"] = "forkserver") -> None:
        super().__init__(batch_size=batch_size, num_workers=num_workers, augment=False, pin_memory=pin_memory,
                         worker_start_method=worker_start_method)
        paths: Sources = source if isinstance(source, str) else tuple(source)
        self.source = PredictSource(paths, frame_step, max_frames, telemetry, read_metadata, sensor_width_mm,
                                    strict_telemetry)
        self.image_width, self.keep_rgb = image_width, keep_rgb
        self.prior_settings = PriorSettings(telemetry_mode, telemetry_sigma, igd_bound)

    def setup(self, stage: str | None = None) -> None:
        self.read_early(stage)

    def read_early(self, stage: str | None) -> None:
        """Refuse any stage but predict (before the trainer starts, when the command line calls it)."""
        if stage not in (None, "predict"):
            raise ValueError(f"{type(self).__name__} serves predict only (no labels), not {stage!r}; "
                             "use a labelled data module (e.g. UAPDDataModule) to validate or test")

    def network_target(self) -> NetworkSize:
        """The network size: ``image_width`` if set, else the model's training size."""
        if self.image_width is not None:
            return self.image_width
        module = self.trainer.lightning_module if self.trainer is not None else None
        return checkpoint_network_size(module)

    def predict_dataloader(self) -> DataLoader[Any] | list[DataLoader[Any]]:  # type: ignore[override]
        # Lightning's notes on custom batch samplers and on iterable data sets concern writers that need batch
        # indices; PredictionWriter names its files from the samples, and the size batches return every image
        warnings.filterwarnings("ignore", message="You are using a custom batch sampler `SizeBatchSampler`")
        warnings.filterwarnings("ignore", message="Couldn't infer the batch indices fetched from your dataloader")
        world_size, rank = self._processes()
        loaders = predict_loaders(self.source, self.network_target(), self.prior_settings,
                                  batch_size=self.batch_size, num_workers=self.num_workers, keep_rgb=self.keep_rgb,
                                  pin_memory=self.pin_memory, rank=rank, world_size=world_size,
                                  worker_start_method=self.worker_start_method)
        return loaders[0] if len(loaders) == 1 else loaders  # images, then each video: one after the other
