"""``DAPMPredictor``: the Python API. Load a checkpoint once, then predict images, batches, folders or videos."""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import DataLoader

from dapm_lightning.data.datamodules import collate_samples
from dapm_lightning.inference.inputs import (
    SIZE_MULTIPLE,
    NetworkSize,
    PriorMode,
    PriorSettings,
    SizeBatchSampler,
    VideoFramesDataset,
    checkpoint_network_size,
    network_size,
    prepare_image,
    source_dataset,
    to_rgb8,
    upscale_note,
)
from dapm_lightning.inference.postprocess import Prediction
from dapm_lightning.inference.prior import as_prior
from dapm_lightning.inference.writers import predictions_with_prior
from dapm_lightning.models.prior import PosePrior
from dapm_lightning.training.module import network_prior

Precision = Literal["32", "bf16", "16"]


def apply_inference_options(module: torch.nn.Module, channels_last: bool, compile: bool) -> torch.nn.Module:
    """Channels-last and/or ``torch.compile`` on ``module``'s network in place; returns ``module``."""
    net = getattr(module, "net", module)
    if channels_last:
        net.to(memory_format=torch.channels_last)
    if compile and not getattr(net, "_dapm_compiled", False):
        net.compile(dynamic=False)
        net._dapm_compiled = True
    return module


class DAPMPredictor:
    """Python API: load a checkpoint once, then call it on images, batches, tensors, folders or videos.

    Args:
        module: a :class:`~dapm_lightning.training.module.DAPMModule` (or anything returning a ``DAPMOutput``).
        image_width: network input width (height from each image's aspect); None: the checkpoint's training
            size (the same pixel count in each image's aspect).
        device: ``"cpu"``, ``"cuda"``, ``"cuda:1"``, or ``"auto"`` (a GPU when there is one).
        precision: ``"32"``, ``"bf16"`` or ``"16"`` (autocast; half precision is for GPUs).
        batch_size: images per forward pass when given several.
        channels_last: channels-last memory (NHWC convolutions). compile: ``torch.compile`` the network.
        onnx_path: run the network in onnxruntime from this ONNX file instead of PyTorch; exported from
            ``module`` first when the file does not exist. float32 only (pose priors: ``scale`` mode only).
        telemetry_mode: how pose priors (telemetry) are used: ``condition`` (into the network's IGD feature),
            ``scale`` (the depth fitted to the known pose's ground afterwards; any checkpoint) or ``both``.
        telemetry_sigma: σ of the telemetry (height m, pitch, roll, fov deg) where a prior gives none; 0: the
            telemetry replaces the network's value, > 0: fused with it.

    Example:
        >>> predictor = DAPMPredictor.from_checkpoint("last.ckpt")                  # doctest: +SKIP
        >>> result = predictor(np.asarray(PIL.Image.open("frame.jpg")))              # doctest: +SKIP
        >>> result.depth_m.shape, result.pose["pitch"], result.K                    # doctest: +SKIP
        >>> results = predictor([frame0, frame1])          # list in, list out      # doctest: +SKIP
        >>> for r in predictor.predict_source("flight.mp4"): r.points(4).write_ply(f"{r.name}.ply")  # doctest: +SKIP
        >>> predictor(image, prior={"height_m": 45.2, "pitch_deg": -40.0})  # height, gimbal pitch # doctest: +SKIP
        >>> predictor.predict_source("flight/", telemetry="flight.csv")  # CSV, else XMP/EXIF  # doctest: +SKIP
    """

    def __init__(self, module: torch.nn.Module, image_width: int | None = None, device: str = "cpu",
                 precision: Precision = "32", batch_size: int = 8, channels_last: bool = False,
                 compile: bool = False, onnx_path: str | Path | None = None, telemetry_mode: PriorMode = "condition",
                 telemetry_sigma: Sequence[float] = (0.0, 0.0, 0.0, 0.0)) -> None:
        if str(precision) not in ("32", "bf16", "16"):
            raise ValueError(f"precision must be '32', 'bf16' or '16', got {precision!r}")
        device = resolve_device(device)
        self.session: Any = None
        if onnx_path is not None:
            if str(precision) != "32":
                raise ValueError("onnx_path runs the float32 ONNX model: use precision '32' (or --fp16 at export)")
            from dapm_lightning.inference.onnx import onnx_session

            self.session = onnx_session(module, Path(onnx_path))
        self.module = apply_inference_options(module.eval().to(device), channels_last, compile)
        self.target: NetworkSize = image_width if image_width is not None else checkpoint_network_size(module)
        self.device, self.batch_size = torch.device(device), max(1, batch_size)
        self.precision, self.channels_last = str(precision), channels_last
        self.prior_settings = PriorSettings(telemetry_mode, tuple(telemetry_sigma))  # type: ignore[arg-type]
        if self.session is not None:  # the ONNX model takes no prior: the known pose is applied afterwards
            self.prior_settings = PriorSettings("scale", self.prior_settings.sigma)
        config = getattr(module, "net_config", None) or getattr(module, "config", None)
        from dapm_lightning.geometry.igd import IGDSpec

        self.spec = config.igd if config is not None else IGDSpec()

    @classmethod
    def from_checkpoint(cls, path: str | Path, image_width: int | None = None, device: str = "cpu",
                        **options: Any) -> DAPMPredictor:
        """Load a DAPMModule checkpoint (tensors only: ``weights_only=True``); ``options`` as in the class.

        A file that is not a dapm-lightning checkpoint is refused with a message naming it.
        """
        from dapm_lightning.training.checkpointing import load_dapm_module

        return cls(load_dapm_module(path, map_location="cpu"), image_width, device, **options)

    def _autocast(self) -> Any:
        if self.precision == "32":
            return torch.autocast(self.device.type, enabled=False)
        return torch.autocast(self.device.type, dtype=torch.bfloat16 if self.precision == "bf16" else torch.float16)

    @torch.no_grad()
    def network_outputs(self, images: Tensor, prior: PosePrior | None = None) -> dict[str, Tensor]:
        """``images [B, 3, h, w]`` (uint8, or float in [0, 1]) at the network size -> the network's outputs.

        ``{depth_m, sky_prob, pose}``, and ``pose_network`` when ``prior`` conditions the network.
        """
        images = images.to(self.device, non_blocking=True)
        if self.channels_last:
            images = images.contiguous(memory_format=torch.channels_last)
        if self.session is not None:
            feed = images.float().div(255.0) if images.dtype == torch.uint8 else images.float()
            size = network_size(feed.shape[-2], feed.shape[-1], None, SIZE_MULTIPLE)  # the exported model's sizes
            if size != tuple(feed.shape[-2:]):
                feed = F.interpolate(feed, size=size, mode="bilinear", align_corners=False, antialias=True)
            names = [o.name for o in self.session.get_outputs()]
            values = self.session.run(None, {"image": feed.cpu().numpy()})
            return {n: torch.from_numpy(v) for n, v in zip(names, values)}
        with self._autocast():
            out = self.module(images, prior.to(self.device)) if prior is not None else self.module(images)
        return out.inference_outputs(spread=True)

    def forward_batch(self, images: Tensor, names: Sequence[str], sizes: Sequence[Sequence[int]],
                      priors: Tensor | None = None) -> list[Prediction]:
        """``images [B, 3, h, w]`` at the network size -> predictions at ``sizes``.

        ``priors``: ``[B, 4]`` known pose components (NaN where unknown), used as ``telemetry_mode`` says.
        """
        batch: dict[str, Any] = {"image": images, "name": list(names),
                                 "meta": [{"size": tuple(size), "prior_mode": self.prior_settings.mode}
                                          for size in sizes]}
        if priors is not None:
            batch["pose"] = priors.float()
            batch["pose_sigma"] = torch.tensor(self.prior_settings.sigma).expand(len(names), 4)
        return self.predict_batch(batch)

    def predict_batch(self, batch: dict[str, Any]) -> list[Prediction]:
        """Predictions of a batch of unlabelled samples (:mod:`~dapm_lightning.inference.inputs`).

        Its pose prior is given to the network or applied afterwards, as the batch's ``prior_mode`` says.
        """
        outputs = self.network_outputs(batch["image"], network_prior(batch))
        return predictions_with_prior(outputs, batch, self.spec)

    def _network_input(self, image: Any, index: int) -> tuple[Tensor, tuple[int, int]]:
        """One image (numpy RGB, PIL, or tensor ``[3, H, W]``) -> ``[3, h, w]`` network input and ``(H, W)``."""
        if isinstance(image, Tensor):
            if image.ndim != 3 or image.shape[0] not in (1, 3):
                raise ValueError(f"image {index}: a tensor must be [3, H, W] or [B, 3, H, W] RGB, got "
                                 f"{tuple(image.shape)}")
            size = (int(image.shape[1]), int(image.shape[2]))
            net = network_size(*size, self.target)
            image = image.expand(3, -1, -1)
            if net != size:
                resized = F.interpolate(image[None].float(), size=net, mode="bilinear", antialias=True,
                                        align_corners=False)[0]
                image = resized.round().clamp(0, 255).to(torch.uint8) if image.dtype == torch.uint8 else resized
        else:
            rgb = to_rgb8(np.asarray(image), f"image {index}", bgr=False)
            size = (rgb.shape[0], rgb.shape[1])
            net = network_size(*size, self.target)
            image = prepare_image(rgb, self.target)
        note = upscale_note(f"image {index}", size, net)
        if note:
            warnings.warn(note, stacklevel=3)
        return image, size

    def __call__(self, images: Any, prior: Any = None) -> Prediction | list[Prediction]:
        """Predict one image or several.

        Args:
            images: one image: ``[H, W]`` / ``[H, W, 3|4]`` numpy array in RGB order (uint8 or uint16), a PIL
                image, or a ``[3, H, W]`` tensor (uint8, or float RGB in [0, 1]); or several: a list of those,
                a ``[B, H, W, 3]`` numpy array or a ``[B, 3, H, W]`` tensor.
            prior: what is known of the pose (telemetry): for one image a dict (``height_m``, ``pitch_deg``,
                ``roll_deg``, ``fov_deg``, any subset), a ``[4]`` array with NaN where unknown, or a
                ``PoseTelemetry``; for several, a list of those (None for an image without).

        Returns:
            a :class:`Prediction` for one image, a list of them for several (in order), at each input's size.
        """
        single = ((isinstance(images, Tensor) and images.ndim == 3)
                  or (isinstance(images, np.ndarray) and images.ndim in (2, 3))
                  or not isinstance(images, (list, tuple, np.ndarray, Tensor)))
        items = [images] if single else list(images)
        priors = [prior] if single else list(prior) if prior is not None else [None] * len(items)
        if len(priors) != len(items):
            raise ValueError(f"{len(priors)} priors for {len(items)} images: give one per image (None: unknown)")
        known = as_prior(priors)
        values = known.value if known is not None else torch.full((len(items), 4), float("nan"))
        results: list[Prediction] = []
        pending: list[tuple[Tensor, tuple[int, int], int]] = []

        def flush() -> None:
            if pending:
                names = [str(len(results) + k) for k in range(len(pending))]
                results.extend(self.forward_batch(torch.stack([p[0] for p in pending]), names,
                                                  [p[1] for p in pending], values[[p[2] for p in pending]]))
                pending.clear()

        for index, image in enumerate(items):
            tensor, size = self._network_input(image, index)
            if pending and (len(pending) >= self.batch_size or tensor.shape != pending[0][0].shape
                            or tensor.dtype != pending[0][0].dtype):
                flush()
            pending.append((tensor, size, index))
        flush()
        return results[0] if single else results

    def loader(self, source: str | Path, frame_step: int = 1, max_frames: int | None = None,
               keep_rgb: bool = False, num_workers: int = 0, telemetry: str | Path | None = None,
               read_metadata: bool = True, sensor_width_mm: float | None = None) -> DataLoader[Any]:
        """Batches of a folder, glob pattern, image or video at the network size, with their telemetry.

        Mixed sizes are batched by size; telemetry as :func:`source_dataset` finds it.
        """
        dataset = source_dataset(source, self.target, frame_step, max_frames, self.batch_size, keep_rgb,
                                 telemetry, read_metadata, sensor_width_mm, self.prior_settings)
        if isinstance(dataset, VideoFramesDataset):
            return DataLoader(dataset, batch_size=self.batch_size, num_workers=num_workers,
                              collate_fn=collate_samples)
        sampler = SizeBatchSampler(dataset.network_sizes(), self.batch_size)
        return DataLoader(dataset, batch_sampler=sampler, num_workers=num_workers, collate_fn=collate_samples)

    def predict_source(self, source: str | Path, frame_step: int = 1, max_frames: int | None = None,
                       keep_rgb: bool = False, num_workers: int = 0, telemetry: str | Path | None = None,
                       read_metadata: bool = True, sensor_width_mm: float | None = None) -> Iterator[Prediction]:
        """Predictions for a folder, glob pattern, image or video file, one at a time (constant memory).

        With ``keep_rgb`` each prediction's ``extras["rgb"]`` holds the input pixels (for coloured points).
        ``telemetry``, ``read_metadata``, ``sensor_width_mm``: where pose priors come from (:func:`source_dataset`).
        """
        for batch in self.loader(source, frame_step, max_frames, keep_rgb, num_workers, telemetry, read_metadata,
                                 sensor_width_mm):
            for meta, prediction in zip(batch["meta"], self.predict_batch(batch)):
                if keep_rgb:
                    prediction.extras["rgb"] = meta["rgb"]
                yield prediction


def resolve_device(device: str) -> str:
    """``"auto"``: ``"cuda"`` when a GPU is there, else ``"cpu"``; ``"cuda"`` without one is refused."""
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: no CUDA GPU is available here (use --device cpu or auto)")
    return device
