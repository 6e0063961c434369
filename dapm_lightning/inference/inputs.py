"""Prediction inputs: image files, folders, glob patterns and videos, and the one loader that batches them.

Each data set yields :class:`~dapm_lightning.data.unlabelled.PredictInput` (the image at the network size, its
name, original size, source file, telemetry prior and, when asked for, its pixels); :func:`predict_loader`
batches them by network size into :class:`~dapm_lightning.data.unlabelled.PredictBatch`, for the one-line
command, the Lightning ``predict`` subcommand and the Python API alike.
"""

from __future__ import annotations

import glob
import math
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from lightning.pytorch.utilities import rank_zero_info
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, IterableDataset, Sampler, get_worker_info

from dapm_lightning.data.uapd import IMAGE_SUFFIXES
from dapm_lightning.data.unlabelled import PredictCollate, PredictInput
from dapm_lightning.inference import telemetry as flight
from dapm_lightning.models.prior import PriorSettings

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")
SIZE_MULTIPLE = 32
"""The encoder's total stride: the shortest network input side, and what exported ONNX sizes are multiples of."""
DEFAULT_NETWORK_SIZE = (512, 512)
"""The network size for checkpoints that do not record their training size (the paper's 512 x 512)."""
MAX_UPSCALE = 4.0
"""An input enlarged more than this for the network is warned about (little detail to see)."""

DEFAULT_BATCH_SIZE = 4
"""Images per forward pass in prediction, unless told otherwise (every entry point)."""
NetworkSize = tuple[int, int] | int | None
"""How big the network input is: ``(H, W)`` (the pixel count kept, each image's aspect), a width (height
from the aspect), or None (the image's own size, rounded)."""


def to_rgb8(image: np.ndarray, source: str = "image", *, bgr: bool = True) -> np.ndarray:
    """Any grey, grey+alpha, colour or colour+alpha image of 8 or 16 bits to ``[H, W, 3]`` uint8 RGB.

    ``bgr``: colour channels in OpenCV's order (as ``cv2.imread`` gives); False for RGB arrays.
    Anything else (float pixels, other channel counts) is refused with a message naming ``source``.
    """
    if image.dtype == np.uint16:
        image = (image // 257).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ValueError(f"{source}: unsupported pixel type {image.dtype} (use 8- or 16-bit images)")
    if image.ndim == 2:
        return np.repeat(image[..., None], 3, axis=2)
    if image.ndim != 3:
        raise ValueError(f"{source}: expected an [H, W] or [H, W, C] image, got shape {image.shape}")
    channels = image.shape[2]
    if channels == 1:
        return np.repeat(image, 3, axis=2)
    if channels == 2:
        return np.repeat(image[..., :1], 3, axis=2)  # grey + alpha
    if channels in (3, 4):
        return cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2RGB) if bgr else np.ascontiguousarray(image[..., :3])
    raise ValueError(f"{source}: unsupported number of channels {channels}")


def network_size(height: int, width: int, target: NetworkSize, multiple: int = 1) -> tuple[int, int]:
    """The network input ``(h, w)`` for an ``height x width`` image, in the image's own aspect.

    ``target`` ``(H, W)``: about ``H * W`` pixels (a model trained on 64 x 64 images sees a 4000 x 3000 photo at
    74 x 55: the scale of what it learnt on). An int: that width. None: the image's own size. The short side is
    at least 32 pixels (the encoder's stride). The aspect is kept to the pixel, as the network's IGD and the
    FoV assume square pixels; ``multiple`` rounds both sides to a multiple (32 for an exported ONNX model),
    which bends the aspect slightly.
    """
    if target is None:
        scale = 1.0
    elif isinstance(target, int):
        scale = target / width
    else:
        scale = math.sqrt(target[0] * target[1] / (height * width))
    scale *= max(1.0, SIZE_MULTIPLE / (min(height, width) * scale))
    return (max(multiple, int(round(height * scale / multiple)) * multiple),
            max(multiple, int(round(width * scale / multiple)) * multiple))


def upscale_note(name: str, size: Sequence[int], net: Sequence[int]) -> str | None:
    """A warning when the network size enlarges an image more than :data:`MAX_UPSCALE` times."""
    factor = max(net[0] / size[0], net[1] / size[1])
    if factor <= MAX_UPSCALE:
        return None
    return (f"{name}: {size[1]}x{size[0]} pixels enlarged {factor:.0f}x to the network's {net[1]}x{net[0]}; "
            "predictions from so little detail are unreliable (give larger images)")


def prepare_image(rgb: np.ndarray, target: NetworkSize, multiple: int = 1) -> torch.Tensor:
    """``[H, W, 3]`` uint8 RGB -> ``[3, h, w]`` uint8 tensor at the network size."""
    size = network_size(rgb.shape[0], rgb.shape[1], target, multiple)
    if size != rgb.shape[:2]:
        shrink = size[0] < rgb.shape[0]
        rgb = cv2.resize(rgb, (size[1], size[0]), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    return torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))


def resize_images(images: Tensor, size: tuple[int, int]) -> Tensor:
    """``[B, 3, H, W]`` float images to ``size`` (antialiased bilinear).

    For float tensors given to the API and the exported model's sizes; 8-bit pixels go through
    :func:`prepare_image` (OpenCV) instead.
    """
    if tuple(images.shape[-2:]) == size:
        return images
    return F.interpolate(images, size=size, mode="bilinear", align_corners=False, antialias=True)


def _has_magic(text: str) -> bool:
    return any(c in text for c in "*?[")


def resolve_source(source: str | Path) -> tuple[Literal["images", "video"], list[Path]]:
    """What ``source`` names: ``("images", paths)`` or ``("video", [path])``.

    A folder (its images, sorted), a glob pattern (``**`` recursive) or an image file give images; a video file
    gives video. Raises ``FileNotFoundError`` / ``ValueError`` saying what to give instead.
    """
    text = str(source)
    path = Path(text).expanduser()
    if path.is_dir():
        paths = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not paths:
            videos = sorted(p.name for p in path.iterdir() if p.suffix.lower() in VIDEO_SUFFIXES)
            hint = f" (it holds video(s) {', '.join(videos[:3])}: give the video file itself)" if videos else ""
            raise ValueError(f"{path}: no images ({', '.join(IMAGE_SUFFIXES)}){hint}")
        return "images", paths
    if path.is_file():
        if path.suffix.lower() in VIDEO_SUFFIXES:
            return "video", [path]
        if path.suffix.lower() in IMAGE_SUFFIXES:
            return "images", [path]
        raise ValueError(f"{path}: neither an image ({', '.join(IMAGE_SUFFIXES)}) nor a video "
                         f"({', '.join(VIDEO_SUFFIXES)})")
    if _has_magic(text):
        matches = sorted(Path(p) for p in glob.glob(str(path), recursive=True))
        paths = [p for p in matches if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
        if not paths:
            raise FileNotFoundError(f"{text}: the pattern matches no image ({len(matches)} other path(s)); "
                                    "quote it so that the shell leaves it to dapm-lightning, e.g. 'frames/*.jpg'")
        return "images", paths
    raise FileNotFoundError(f"{text}: no such file or folder (give a folder of images, a glob pattern such as "
                            "'flight/**/*.jpg', an image or a video file)")


def read_image(path: Path) -> np.ndarray:
    """``[H, W, 3]`` uint8 RGB from any 8/16-bit grey, colour or RGBA image file (named in errors)."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"{path}: cannot be decoded as an image (damaged, or not an image)")
    return to_rgb8(raw, str(path))


def image_size(path: Path) -> tuple[int, int]:
    """``(H, W)`` of an image file from its header (Pillow reads no pixels), else by decoding it."""
    try:
        from PIL import Image

        with Image.open(path) as image:
            return int(image.height), int(image.width)
    except Exception:  # a format Pillow lacks (OpenCV may still read it), or a damaged file named later
        height, width = read_image(path).shape[:2]
        return int(height), int(width)


def predict_input(rgb: np.ndarray, name: str, source: str, target: NetworkSize, keep_rgb: bool,
                  prior: np.ndarray | None = None, provenance: Sequence[str] | None = None) -> PredictInput:
    """One image to predict at the network size; ``prior``: ``[4]`` telemetry, NaN where unknown.

    ``provenance``: per component, where the prior's value came from (``""`` where unknown).
    """
    item = PredictInput(prepare_image(rgb, target), name, (int(rgb.shape[0]), int(rgb.shape[1])), source,
                        rgb=rgb if keep_rgb else None)
    if prior is not None:
        item.prior = torch.as_tensor(prior, dtype=torch.float32)
    if provenance is not None:
        item.provenance = tuple(provenance)
    return item


class ImageFilesDataset(Dataset[PredictInput]):
    """Image files (png, jpg, tif, bmp, webp; grey, RGBA and 16-bit handled) as unlabelled samples.

    Args:
        paths: the files. target: the network size (:data:`NetworkSize`). keep_rgb: also return the original
            pixels (to colour point clouds). priors: ``[N, 4]`` pose priors (NaN where unknown), one per path.
        provenance: per path, per component where its prior came from.
    """

    def __init__(self, paths: Sequence[Path], target: NetworkSize = DEFAULT_NETWORK_SIZE, keep_rgb: bool = False,
                 priors: np.ndarray | None = None, provenance: Sequence[Sequence[str]] | None = None) -> None:
        self.paths, self.target, self.keep_rgb = list(paths), target, keep_rgb
        if priors is not None and len(priors) != len(self.paths):
            raise ValueError(f"{len(priors)} pose priors for {len(self.paths)} images")
        self.priors, self.provenance = priors, provenance
        self.telemetry_report: flight.TelemetryReport | None = None
        stems: dict[str, Path] = {}
        for p in self.paths:
            if p.stem in stems:
                raise ValueError(f"{p} and {stems[p.stem]} would write the same output files (same name "
                                 f"{p.stem!r}): predict them in separate runs or rename one")
            stems[p.stem] = p
        self._sizes: list[tuple[int, int]] | None = None

    def __len__(self) -> int:
        return len(self.paths)

    def sizes(self) -> list[tuple[int, int]]:
        """Each image's ``(H, W)``, read from the file headers once."""
        if self._sizes is None:
            self._sizes = [image_size(p) for p in self.paths]
        return self._sizes

    def network_sizes(self) -> list[tuple[int, int]]:
        """Each image's network input ``(h, w)``; warns once about images enlarged too much."""
        sizes = self.sizes()
        nets = [network_size(*size, self.target) for size in sizes]
        notes = [n for n in (upscale_note(p.name, s, t) for p, s, t in zip(self.paths, sizes, nets)) if n]
        if notes:
            more = f" (and {len(notes) - 1} more)" if len(notes) > 1 else ""
            warnings.warn(notes[0] + more, stacklevel=2)
        return nets

    def __getitem__(self, index: int) -> PredictInput:
        path = self.paths[index]
        prior = None if self.priors is None else self.priors[index]
        provenance = None if self.provenance is None else self.provenance[index]
        return predict_input(read_image(path), path.stem, str(path), self.target, self.keep_rgb, prior, provenance)


class SizeBatchSampler(Sampler[list[int]]):
    """Batches of images of one network size (folders of mixed sizes and aspects), in file order within a size.

    Under several processes each takes every ``world_size``-th batch, starting at its ``rank``.
    """

    def __init__(self, sizes: Sequence[tuple[int, int]], batch_size: int, rank: int = 0, world_size: int = 1) -> None:
        groups: dict[tuple[int, int], list[int]] = {}
        for index, size in enumerate(sizes):
            groups.setdefault(tuple(size), []).append(index)  # type: ignore[arg-type]
        batches = [indices[k:k + batch_size] for indices in groups.values()
                   for k in range(0, len(indices), batch_size)]
        self.batches = batches[rank::world_size]

    def __iter__(self) -> Iterator[list[int]]:
        return iter(self.batches)

    def __len__(self) -> int:
        return len(self.batches)


class VideoFramesDataset(IterableDataset[PredictInput]):
    """Frames of a video file (anything OpenCV's FFmpeg back-end reads), named ``STEM_f<frame number>``.

    Args:
        path: the video. target: the network size. frame_step: keep every ``frame_step``-th frame.
        max_frames: stop after this many kept frames. chunk: frames a loader worker takes in a row (the
            batch size keeps the frames in order with several workers; each worker decodes the whole video
            but converts only its own frames). keep_rgb: also return the frame's pixels.
        priors: frame number -> ``[4]`` pose prior (NaN where unknown), e.g. from the video's SRT telemetry.
        provenance: frame number -> per component where its prior came from.

    Under DDP each process takes its own share of the chunks.
    """

    def __init__(self, path: str | Path, target: NetworkSize = DEFAULT_NETWORK_SIZE, frame_step: int = 1,
                 max_frames: int | None = None, chunk: int = 1, keep_rgb: bool = False,
                 priors: dict[int, np.ndarray] | None = None,
                 provenance: dict[int, tuple[str, ...]] | None = None) -> None:
        self.path, self.target, self.keep_rgb = Path(path), target, keep_rgb
        if frame_step < 1 or chunk < 1:
            raise ValueError(f"frame_step and chunk must be >= 1, got {frame_step} and {chunk}")
        self.frame_step, self.max_frames, self.chunk = frame_step, max_frames, chunk
        self.priors, self.provenance = priors or {}, provenance or {}
        self.telemetry_report: flight.TelemetryReport | None = None
        self.rank, self.world_size = 0, 1
        capture = self._open()
        self.frame_count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        self.fps = float(capture.get(cv2.CAP_PROP_FPS))
        self.frame_size = (int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)), int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)))
        capture.release()
        note = upscale_note(self.path.name, self.frame_size, network_size(*self.frame_size, target))
        if note and min(self.frame_size) > 0:
            warnings.warn(note, stacklevel=2)

    def _open(self) -> Any:
        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            raise ValueError(f"{self.path}: OpenCV cannot open it as a video (damaged, or a codec its FFmpeg "
                             "lacks: convert it, e.g. ffmpeg -i IN -c:v libx264 OUT.mp4, or extract frames)")
        return capture

    def __iter__(self) -> Iterator[PredictInput]:
        info = get_worker_info()
        workers, worker = (info.num_workers, info.id) if info is not None else (1, 0)
        shards, shard = workers * self.world_size, self.rank * workers + worker
        capture = self._open()
        try:
            frame, kept = -1, 0
            while self.max_frames is None or kept < self.max_frames:
                if not capture.grab():  # grab only: frames of other workers are never converted
                    break
                frame += 1
                if frame % self.frame_step:
                    continue
                mine = (kept // self.chunk) % shards == shard
                kept += 1
                if not mine:
                    continue
                ok, bgr = capture.retrieve()
                if not ok:
                    break
                item = predict_input(to_rgb8(bgr, f"{self.path} frame {frame}"), f"{self.path.stem}_f{frame:06d}",
                                     f"{self.path}#{frame}", self.target, self.keep_rgb, self.priors.get(frame),
                                     self.provenance.get(frame))
                item.time_s = frame / self.fps if self.fps > 0 else None
                yield item
        finally:
            capture.release()


def checkpoint_network_size(module: torch.nn.Module | None) -> tuple[int, int]:
    """The network size a module's checkpoint was trained at, else :data:`DEFAULT_NETWORK_SIZE` with a note."""
    size = getattr(module, "train_image_size", None)
    if size is not None:
        return int(size[0]), int(size[1])
    warnings.warn(f"the checkpoint does not record its training image size: predicting at "
                  f"{DEFAULT_NETWORK_SIZE[1]}x{DEFAULT_NETWORK_SIZE[0]} pixels (set the image width to the one it "
                  "was trained at)", stacklevel=2)
    return DEFAULT_NETWORK_SIZE


@dataclass(frozen=True)
class PredictSource:
    """What to predict and where its telemetry comes from.

    Args:
        path: a folder of images, a glob pattern ('flight/**/*.jpg'), one image, or a video file.
        frame_step: videos: keep every ``frame_step``-th frame. max_frames: videos: stop after this many.
        telemetry: images: a CSV (``name,height_m,pitch_deg,roll_deg,fov_deg``; see
            :func:`~dapm_lightning.inference.telemetry.read_telemetry_csv`); videos: a DJI SRT file, or a CSV
            naming frames as their outputs are named (``DJI_0005_f000012``).
        read_metadata: images: each component the CSV lacks from the image's own DJI XMP / EXIF; videos: the
            video's own ``.SRT`` beside it, for what no ``telemetry`` CSV gives.
        sensor_width_mm: sensor width, for an EXIF FocalLength without a 35 mm equivalent.
        strict_telemetry: a drone-written file whose telemetry cannot be read (a damaged XMP, an SRT that is not
            one) stops the run; by default that image or video falls back to the network with one warning.
    """

    path: str | Path
    frame_step: int = 1
    max_frames: int | None = None
    telemetry: str | Path | None = None
    read_metadata: bool = True
    sensor_width_mm: float | None = None
    strict_telemetry: bool = False


def _video_telemetry(video: VideoFramesDataset, source: PredictSource) -> flight.TelemetryReport | None:
    """The video's priors (and their provenance) from its SRT and / or a CSV naming its frames; the report."""
    given = Path(source.telemetry) if source.telemetry is not None else None
    csv_path = given if given is not None and given.suffix.lower() == ".csv" else None
    srt = given if given is not None and csv_path is None else None
    if srt is None and source.read_metadata:
        srt = next((p for p in (video.path.with_suffix(".SRT"), video.path.with_suffix(".srt")) if p.is_file()), None)
    if srt is None and csv_path is None:
        return None
    frames = range(0, video.frame_count, video.frame_step)[:video.max_frames] if video.frame_count > 0 else None
    height, width = video.frame_size
    found, report = flight.video_telemetry(video.path, frames, srt, csv_path, fps=video.fps,
                                           size=(width, height) if width > 0 and height > 0 else None,
                                           strict=source.strict_telemetry)
    video.priors = {frame: t.values() for frame, t in found.items()}
    video.provenance = {frame: t.provenance for frame, t in found.items()}
    return report


def source_dataset(source: PredictSource, target: NetworkSize, keep_rgb: bool = False,
                   chunk: int = 1) -> ImageFilesDataset | VideoFramesDataset:
    """The data set of a source at the network size ``target``, each image with its telemetry prior.

    ``chunk``: video frames a loader worker takes in a row (the batch size keeps frames in order). When telemetry
    is read, its summary (how many images or frames use it, from which sources) is logged once.
    """
    kind, paths = resolve_source(source.path)
    dataset: ImageFilesDataset | VideoFramesDataset
    if kind == "video":
        dataset = VideoFramesDataset(paths[0], target, source.frame_step, source.max_frames, chunk, keep_rgb)
        report = _video_telemetry(dataset, source)
    elif source.telemetry is not None or source.read_metadata:
        found, report = flight.images_telemetry(paths, source.telemetry, read_metadata=source.read_metadata,
                                                sensor_width_mm=source.sensor_width_mm,
                                                strict=source.strict_telemetry)
        rows = np.stack([t.values() for t in found])
        known = bool(np.isfinite(rows).any())
        dataset = ImageFilesDataset(paths, target, keep_rgb, rows if known else None,
                                    [t.provenance for t in found] if known else None)
    else:
        dataset, report = ImageFilesDataset(paths, target, keep_rgb), None
    dataset.telemetry_report = report
    if report is not None:
        rank_zero_info(report.summary())
    return dataset


def predict_loader(source: PredictSource, target: NetworkSize, settings: PriorSettings = PriorSettings(),  # noqa: B008
                   *, batch_size: int = DEFAULT_BATCH_SIZE, num_workers: int = 0, keep_rgb: bool = False,
                   pin_memory: bool = False, rank: int = 0, world_size: int = 1) -> DataLoader[PredictInput]:
    """The one loader of prediction: :class:`PredictBatch` of a source, images batched by network size.

    Every entry point uses it: the one-line command and the Python API (through
    :class:`~dapm_lightning.inference.predictor.DAPMPredictor`) and the Lightning ``predict`` subcommand
    (:class:`~dapm_lightning.inference.datamodule.PredictDataModule`). Under several processes (``rank`` of
    ``world_size``) each process takes every ``world_size``-th batch of images, or its share of a video's frames.
    """
    dataset = source_dataset(source, target, keep_rgb, chunk=batch_size)
    collate = PredictCollate(settings)
    if isinstance(dataset, VideoFramesDataset):
        dataset.rank, dataset.world_size = rank, world_size
        return DataLoader(dataset, batch_size=batch_size, num_workers=num_workers, collate_fn=collate,
                          pin_memory=pin_memory)
    sampler = SizeBatchSampler(dataset.network_sizes(), batch_size, rank, world_size)
    return DataLoader(dataset, batch_sampler=sampler, num_workers=num_workers, collate_fn=collate,
                      pin_memory=pin_memory)
