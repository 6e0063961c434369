"""``DAPMPredictor``: the Python API. Load a checkpoint once, then predict images, batches, folders or videos."""

from __future__ import annotations

import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from dapm_lightning.data.unlabelled import PredictBatch, PredictInput
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.inference.inputs import (
    DEFAULT_BATCH_SIZE,
    NetworkSize,
    PredictLoader,
    PredictSource,
    checkpoint_network_size,
    network_size,
    predict_input,
    predict_loader,
    read_image,
    resize_images,
    to_rgb8,
    upscale_note,
)
from dapm_lightning.inference.onnx import ensure_exported
from dapm_lightning.inference.postprocess import Prediction, batch_predictions
from dapm_lightning.inference.prior import prior_rows
from dapm_lightning.inference.runtime import OnnxRuntime, Precision, Runtime, TorchRuntime
from dapm_lightning.inference.sources import Sources
from dapm_lightning.inference.telemetry.gather import images_telemetry
from dapm_lightning.inference.telemetry.pose import PoseTelemetry
from dapm_lightning.models.prior import EXACT_SIGMA, IGD_BOUND_MARGIN, PriorMode, PriorSettings
from dapm_lightning.training.checkpointing import load_dapm_module

PIL_MODES_TO_RGB = ("1", "P", "PA", "CMYK", "YCbCr", "LAB", "HSV")
"""PIL images whose arrays are not RGB or grey pixels (palette indices, CMYK inks, ...): converted to RGB first."""


class DAPMPredictor:
    """Python API: load a checkpoint once, then call it on images, batches, tensors, folders or videos.

    Args:
        module: a :class:`~dapm_lightning.training.module.DAPMModule` (or anything returning a ``DAPMOutput``); None
            with ``onnx_path``: the exported model alone.
        image_width: network input width (height from each image's aspect); None: the checkpoint's training
            size (the same pixel count in each image's aspect).
        device: ``"cpu"``, ``"cuda"``, ``"cuda:1"``, or ``"auto"`` (a GPU when there is one).
        precision: ``"32"``, ``"bf16"`` or ``"16"`` (autocast; half precision is for GPUs).
        batch_size: images per forward pass when given several.
        channels_last: channels-last memory (NHWC convolutions). compile: ``torch.compile`` the network.
        onnx_path: run the network in onnxruntime from this exported model (``dapm-lightning export``: float32,
            fp16 or int8) instead of PyTorch; exported from ``module`` first when given and the file does not
            exist. Its metadata gives the network's settings and training size; telemetry works as in PyTorch.
        telemetry_mode: how pose priors (telemetry) are used: ``condition`` (into the network's IGD feature),
            ``scale`` (the depth fitted to the known pose's ground afterwards; any checkpoint) or ``both``.
        telemetry_sigma: σ of the telemetry (height m, pitch, roll, fov deg) where a prior gives none; 0: the
            telemetry replaces the network's value, > 0: fused with it.
        igd_bound: margin of the IGD bound: an image whose telemetry gives the height gets no depth beyond
            ``1 + igd_bound`` times the flat ground of the pose used (docs/predict.md; default 0.1); None: no bound.

    Example:
        >>> predictor = DAPMPredictor.from_checkpoint("last.ckpt")                  # doctest: +SKIP
        >>> result = predictor(np.asarray(PIL.Image.open("frame.jpg")))              # doctest: +SKIP
        >>> result.depth_m.shape, result.pose["pitch"], result.K                    # doctest: +SKIP
        >>> results = predictor([frame0, frame1])          # list in, list out      # doctest: +SKIP
        >>> for r in predictor.predict_source("flight.mp4"): r.points(4).write_ply(f"{r.name}.ply")  # doctest: +SKIP
        >>> predictor(image, prior={"height_m": 45.2, "pitch_deg": -40.0})  # height, gimbal pitch # doctest: +SKIP
        >>> predictor.predict_source("flight/", telemetry="flight.csv")  # CSV, else XMP/EXIF  # doctest: +SKIP
    """

    def __init__(self, module: torch.nn.Module | None, image_width: int | None = None, device: str = "cpu",
                 precision: Precision = "32", batch_size: int = DEFAULT_BATCH_SIZE, channels_last: bool = False,
                 compile: bool = False, onnx_path: str | Path | None = None, telemetry_mode: PriorMode = "condition",
                 telemetry_sigma: Sequence[float] = EXACT_SIGMA, igd_bound: float | None = IGD_BOUND_MARGIN) -> None:
        runtime: Runtime
        config: Any
        trained: tuple[int, int] | None = None
        if onnx_path is not None:
            if str(precision) != "32":
                raise ValueError("an ONNX model runs in the precision it was exported in: use precision '32'")
            onnx_path = Path(onnx_path).expanduser()
            if module is not None:
                ensure_exported(module.eval(), onnx_path)
            onnx_runtime = OnnxRuntime(onnx_path)
            runtime, trained = onnx_runtime, onnx_runtime.train_image_size
            config = onnx_runtime.config
        elif module is None:
            raise ValueError("give a module (a DAPMModule), or onnx_path: an exported model")
        else:
            runtime = TorchRuntime(module, device, precision, channels_last, compile)
            config = getattr(module, "net_config", None) or getattr(module, "config", None)
        self.runtime, self.module = runtime, module
        if image_width is not None:
            self.target: NetworkSize = image_width
        else:
            self.target = trained if trained is not None else checkpoint_network_size(module)
        self.batch_size = max(1, batch_size)
        settings = PriorSettings(telemetry_mode, tuple(telemetry_sigma), igd_bound)  # type: ignore[arg-type]
        # a runtime that takes no prior (ONNX) applies the known pose afterwards
        self.prior_settings = settings if runtime.takes_prior else PriorSettings("scale", settings.sigma, igd_bound)
        self.spec: IGDSpec = config.igd if config is not None else IGDSpec()

    @classmethod
    def from_checkpoint(cls, path: str | Path, image_width: int | None = None, device: str = "cpu",
                        **options: Any) -> DAPMPredictor:
        """Load a DAPMModule checkpoint (tensors only: ``weights_only=True``) or an exported ``.onnx`` model.

        ``options`` as in the class. A file that is neither is refused with a message naming it.
        """
        if Path(path).suffix.lower() == ".onnx":
            return cls(None, image_width, device, onnx_path=path, **options)
        return cls(load_dapm_module(path, map_location="cpu"), image_width, device, **options)

    def predict_batch(self, batch: PredictBatch) -> list[Prediction]:
        """Predictions of a :class:`~dapm_lightning.data.unlabelled.PredictBatch`, at each image's own size.

        Its pose prior is given to the network or applied afterwards, as the batch's mode says.
        """
        return batch_predictions(self.runtime(batch.images, batch.network_prior), batch, self.spec)

    def _predict_input(self, image: Any, index: int, prior: Tensor, provenance: tuple[str, ...]) -> PredictInput:
        """One image (a path, numpy RGB, PIL, or tensor ``[3, H, W]``) at the network size, with its prior."""
        if isinstance(image, (str, Path)):  # an image file: named by its stem
            path = Path(image).expanduser()
            if not path.is_file():
                raise FileNotFoundError(f"image {index}: {path}: no such file")
            item = predict_input(read_image(path), path.stem, str(path), self.target, False, prior.numpy(),
                                 provenance)
        elif isinstance(image, Tensor) and image.dtype != torch.uint8:  # float RGB: resized as floats
            if image.ndim != 3 or image.shape[0] not in (1, 3):
                raise ValueError(f"image {index}: a tensor must be [3, H, W] or [B, 3, H, W] RGB, got "
                                 f"{tuple(image.shape)}")
            if not image.is_floating_point():
                raise ValueError(f"image {index}: a tensor must be uint8 (0-255) or float RGB in [0, 1], got "
                                 f"{image.dtype}")
            low, high = (float(v) for v in torch.aminmax(image.detach()))
            if not (-1e-3 <= low and high <= 1.0 + 1e-3):  # NaN fails too
                raise ValueError(f"image {index}: a float tensor must hold RGB in [0, 1], got values from {low:g} to "
                                 f"{high:g}; divide 0-255 values by 255 (or pass a uint8 tensor)")
            size = (int(image.shape[1]), int(image.shape[2]))
            net = network_size(*size, self.target)
            item = PredictInput(resize_images(image.expand(3, -1, -1)[None], net)[0], str(index), size, prior=prior,
                                provenance=provenance)
        else:
            if isinstance(image, Tensor):
                if image.ndim != 3 or image.shape[0] not in (1, 3):
                    raise ValueError(f"image {index}: a tensor must be [3, H, W] or [B, 3, H, W] RGB, got "
                                     f"{tuple(image.shape)}")
                image = image.expand(3, -1, -1).permute(1, 2, 0).numpy()
            if getattr(image, "mode", None) in PIL_MODES_TO_RGB:  # a PIL image of codes, not of RGB or grey values
                image = image.convert("RGB")
            rgb = to_rgb8(np.asarray(image), f"image {index}", bgr=False)
            item = predict_input(rgb, str(index), "", self.target, False, prior.numpy(), provenance)
        note = upscale_note(f"image {index}", item.size, tuple(item.image.shape[-2:]))
        if note:
            warnings.warn(note, stacklevel=3)
        return item

    def __call__(self, images: Any, prior: Any = None, read_metadata: bool = True,
                 sensor_width_mm: float | None = None,
                 strict_telemetry: bool = False) -> Prediction | list[Prediction]:
        """Predict one image or several.

        Args:
            images: one image: a path to an image file (named by its stem), an ``[H, W]`` / ``[H, W, 3|4]``
                numpy array in RGB order (uint8 or uint16), a PIL image, or a ``[3, H, W]`` tensor (uint8, or float
                RGB in [0, 1]); or several: a list of those, a ``[B, H, W, 3]`` numpy array or a ``[B, 3, H, W]``
                tensor. (Folders, patterns and videos: :meth:`predict_source`.)
            prior: what is known of the pose (telemetry): for one image a dict (``height_m``, ``pitch_deg``,
                ``roll_deg``, ``fov_deg``, any subset), a ``[4]`` array with NaN where unknown, or a
                ``PoseTelemetry``; for several, a list of those (None for an image without). Checked as a
                telemetry CSV is: an impossible value (height <= 0, |pitch| > 180, FoV outside (0, 180), inf) is a
                ``TelemetryError``.
            read_metadata: an image given by its path also takes, for what ``prior`` leaves unknown, its own DJI
                XMP and EXIF telemetry, as ``predict_source`` and the command line do (metadata that cannot be
                read: the network's pose, with one warning).
            sensor_width_mm: the sensor width for the EXIF focal length (as the command line's option).
            strict_telemetry: metadata that cannot be read is a ``TelemetryError`` instead of the warning.

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
        rows, provenance = prior_rows(priors)
        files = {k: Path(image).expanduser() for k, image in enumerate(items) if isinstance(image, (str, Path))}
        files = {k: path for k, path in files.items() if path.is_file() and np.isnan(rows[k]).any()}
        if read_metadata and files:  # one call: one warning for all images whose metadata cannot be read
            given = [PoseTelemetry.from_values(rows[k], "", provenance[k]) for k in files]  # the prior wins
            found = images_telemetry(files.values(), sensor_width_mm=sensor_width_mm, strict=strict_telemetry,
                                     priors=given)[0]
            for index, telemetry in zip(files, found):
                rows[index], provenance[index] = telemetry.values(), telemetry.provenance
        values = torch.from_numpy(rows).float()
        results: list[Prediction] = []
        pending: list[PredictInput] = []

        def flush() -> None:
            if pending:
                results.extend(self.predict_batch(PredictBatch.collate(pending, self.prior_settings)))
                pending.clear()

        for index, image in enumerate(items):
            item = self._predict_input(image, index, values[index], provenance[index])
            if pending and (len(pending) >= self.batch_size or item.image.shape != pending[0].image.shape
                            or item.image.dtype != pending[0].image.dtype):
                flush()
            pending.append(item)
        flush()
        return results[0] if single else results

    def loader(self, source: Sources | PredictSource, keep_rgb: bool = False, num_workers: int = 0) -> PredictLoader:
        """Batches of folders, glob patterns, images, videos or lists at the network size, with their telemetry.

        ``source``: a path, or a :class:`~dapm_lightning.inference.inputs.PredictSource` saying also which frames
        and where the telemetry comes from. Mixed sizes are batched by size (:func:`predict_loader`).
        """
        source = source if isinstance(source, PredictSource) else PredictSource(source)
        return predict_loader(source, self.target, self.prior_settings, batch_size=self.batch_size,
                              num_workers=num_workers, keep_rgb=keep_rgb)

    def predict_source(self, source: Sources | PredictSource, frame_step: int = 1, max_frames: int | None = None,
                       keep_rgb: bool = False, num_workers: int = 0, telemetry: str | Path | None = None,
                       read_metadata: bool = True, sensor_width_mm: float | None = None,
                       strict_telemetry: bool = False) -> Iterator[Prediction]:
        """Predictions for folders, glob patterns, images, videos or ``.txt`` lists, one at a time (constant memory).

        With ``keep_rgb`` each prediction's ``rgb`` holds the input pixels (for coloured points).
        ``frame_step``, ``max_frames``, ``telemetry``, ``read_metadata``, ``sensor_width_mm``,
        ``strict_telemetry``: as in :class:`~dapm_lightning.inference.inputs.PredictSource` (or give one as ``source``).
        """
        if not isinstance(source, PredictSource):
            source = PredictSource(source, frame_step, max_frames, telemetry, read_metadata, sensor_width_mm,
                                   strict_telemetry)
        for batch in self.loader(source, keep_rgb, num_workers):
            yield from self.predict_batch(batch)
