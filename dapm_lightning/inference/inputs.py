"""Prediction inputs: the data sets of image files and videos, and the loaders that batch them.

The files come from :mod:`~dapm_lightning.inference.sources` (folders, patterns, lists), the pixels' handling
from :mod:`~dapm_lightning.inference.pixels`. Each data set yields
:class:`~dapm_lightning.data.unlabelled.PredictInput` (the image at the network size, its name, original size,
source file, telemetry prior and, when asked for, its pixels); :func:`predict_loaders` batch them by network size
into :class:`~dapm_lightning.data.unlabelled.PredictBatch` (one loader for the images, one per video), for the
one-line command, the Lightning ``predict`` subcommand and the Python API alike.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_info
from torch.utils.data import DataLoader, Dataset, IterableDataset, Sampler, get_worker_info

from dapm_lightning.data.unlabelled import PredictBatch, PredictCollate, PredictInput
from dapm_lightning.data.workers import loader_workers
from dapm_lightning.inference import telemetry as flight
from dapm_lightning.inference.pixels import DEFAULT_NETWORK_SIZE as DEFAULT_NETWORK_SIZE
from dapm_lightning.inference.pixels import MAX_UPSCALE as MAX_UPSCALE
from dapm_lightning.inference.pixels import SIZE_MULTIPLE as SIZE_MULTIPLE
from dapm_lightning.inference.pixels import NetworkSize as NetworkSize
from dapm_lightning.inference.pixels import image_size as image_size
from dapm_lightning.inference.pixels import network_size as network_size
from dapm_lightning.inference.pixels import prepare_image as prepare_image
from dapm_lightning.inference.pixels import read_image as read_image
from dapm_lightning.inference.pixels import resize_images as resize_images
from dapm_lightning.inference.pixels import to_rgb8 as to_rgb8
from dapm_lightning.inference.pixels import upscale_note as upscale_note
from dapm_lightning.inference.sources import VIDEO_SUFFIXES as VIDEO_SUFFIXES
from dapm_lightning.inference.sources import SourceFile, Sources, permission_denied, resolve_sources
from dapm_lightning.inference.sources import resolve_source as resolve_source
from dapm_lightning.inference.telemetry.gather import first_few
from dapm_lightning.models.prior import PriorSettings
from dapm_lightning.options import DEFAULT_BATCH_SIZE as DEFAULT_BATCH_SIZE

FRAME_COUNT_SLACK = (2, 0.02)
"""A video may end this many frames, or this share of its frames (the larger), before the count its container
announces without a warning: OpenCV's frame count is an estimate from the duration for some containers."""


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
        names: per path its output name (default: the file's stem); two alike are refused.
    """

    def __init__(self, paths: Sequence[Path], target: NetworkSize = DEFAULT_NETWORK_SIZE, keep_rgb: bool = False,
                 priors: np.ndarray | None = None, provenance: Sequence[Sequence[str]] | None = None,
                 names: Sequence[str] | None = None) -> None:
        self.paths, self.target, self.keep_rgb = list(paths), target, keep_rgb
        if priors is not None and len(priors) != len(self.paths):
            raise ValueError(f"{len(priors)} pose priors for {len(self.paths)} images")
        self.priors, self.provenance = priors, provenance
        self.names = list(names) if names is not None else [p.stem for p in self.paths]
        self.telemetry_report: flight.TelemetryReport | None = None
        seen: dict[str, Path] = {}
        for p, name in zip(self.paths, self.names):
            if name in seen:
                raise ValueError(f"{p} and {seen[name]} would write the same output files (same name "
                                 f"{name!r}): predict them in separate runs or rename one")
            seen[name] = p
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
        return predict_input(read_image(path), self.names[index], str(path), self.target, self.keep_rgb, prior,
                             provenance)


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
        name: the frames' name before ``_f<frame>`` (default: the video's stem).

    Under DDP each process takes its own share of the chunks. A video that ends well before the frame count its
    container announces (beyond :data:`FRAME_COUNT_SLACK`: a file cut short) is predicted as far as it goes, with
    one warning naming it and the frames read of those announced.
    """

    def __init__(self, path: str | Path, target: NetworkSize = DEFAULT_NETWORK_SIZE, frame_step: int = 1,
                 max_frames: int | None = None, chunk: int = 1, keep_rgb: bool = False,
                 priors: dict[int, np.ndarray] | None = None,
                 provenance: dict[int, tuple[str, ...]] | None = None, name: str | None = None) -> None:
        self.path, self.target, self.keep_rgb = Path(path), target, keep_rgb
        self.name = name if name is not None else self.path.stem
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

    def expected_frames(self) -> int | None:
        """The frames this process will predict (its share under DDP); None when the video's length is unknown."""
        if self.frame_count <= 0:
            return None
        kept = len(range(0, self.frame_count, self.frame_step)[:self.max_frames])
        chunks = [min(self.chunk, kept - k) for k in range(0, kept, self.chunk)]
        return sum(chunks[self.rank::self.world_size])

    def _open(self) -> Any:
        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            if self.path.exists() and not os.access(self.path, os.R_OK):
                raise permission_denied(self.path)
            raise ValueError(f"{self.path}: OpenCV cannot open it as a video (damaged, or a codec its FFmpeg "
                             "lacks: convert it, e.g. ffmpeg -i IN -c:v libx264 OUT.mp4, or extract frames)")
        return capture

    def __iter__(self) -> Iterator[PredictInput]:
        info = get_worker_info()
        workers, worker = (info.num_workers, info.id) if info is not None else (1, 0)
        shards, shard = workers * self.world_size, self.rank * workers + worker
        capture = self._open()
        try:
            frame, kept, ended = -1, 0, False
            while self.max_frames is None or kept < self.max_frames:
                if not capture.grab():  # grab only: frames of other workers are never converted
                    ended = True
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
                    ended, frame = True, frame - 1
                    break
                item = predict_input(to_rgb8(bgr, f"{self.path} frame {frame}"), f"{self.name}_f{frame:06d}",
                                     f"{self.path}#{frame}", self.target, self.keep_rgb, self.priors.get(frame),
                                     self.provenance.get(frame))
                item.time_s = self._time_s(capture, frame)
                yield item
        finally:
            capture.release()
        if ended and shard == 0:  # each worker reads the whole video: the first one says so
            self._check_length(frame + 1)

    def _time_s(self, capture: Any, frame: int) -> float | None:
        """The grabbed frame's time in the video (s).

        Its own timestamp (right for a variable frame rate too), else ``frame / fps`` (a container without
        timestamps), else None.
        """
        msec = capture.get(cv2.CAP_PROP_POS_MSEC)
        if msec > 0 or (frame == 0 and msec == 0):
            return msec / 1000.0
        return frame / self.fps if self.fps > 0 else None

    def _check_length(self, read: int) -> None:
        """Warn when the video ended well before the frame count its container announces (a file cut short)."""
        slack = max(FRAME_COUNT_SLACK[0], round(FRAME_COUNT_SLACK[1] * self.frame_count))
        if self.frame_count <= 0 or read >= self.frame_count - slack:
            return
        warnings.warn(f"{self.path}: the video ends after {read} of the {self.frame_count} frames its header "
                      "announces (cut short while copying?): the frames after it are not predicted. Fix: copy the "
                      "file again.", stacklevel=2)


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
        path: a folder of images (sub-folders included), a glob pattern ('flight/**/*.jpg', extensions in any
            case), an image, a video file, a ``.txt`` list of paths, or a list of any of those
            (:func:`~dapm_lightning.inference.sources.resolve_sources`).
        frame_step: videos: keep every ``frame_step``-th frame. max_frames: videos: stop after this many.
        telemetry: a CSV (``name,height_m,pitch_deg,roll_deg,fov_deg``; see
            :func:`~dapm_lightning.inference.telemetry.read_telemetry_csv`) naming images, and video frames as
            their outputs are named (``DJI_0005_f000012``), read once for all of them; or a DJI ``.SRT``, the
            telemetry of the one video predicted (images beside it keep their own metadata).
        read_metadata: images: each component the CSV lacks from the image's own DJI XMP / EXIF; videos: the
            video's own ``.SRT`` beside it, for what no ``telemetry`` CSV gives.
        sensor_width_mm: sensor width in mm (of the area the images cover): each image's EXIF FocalLength then gives
            its FoV, before its 35 mm equivalent (which gives it otherwise).
        strict_telemetry: a drone-written file whose telemetry cannot be read (a damaged XMP, an SRT that is not
            one) stops the run; by default that image or video falls back to the network with one warning.
    """

    path: Sources
    frame_step: int = 1
    max_frames: int | None = None
    telemetry: str | Path | None = None
    read_metadata: bool = True
    sensor_width_mm: float | None = None
    strict_telemetry: bool = False

    def __post_init__(self) -> None:
        if self.telemetry is not None and not Path(self.telemetry).is_file():
            what = "a folder, not a file" if Path(self.telemetry).is_dir() else "no such file"
            raise FileNotFoundError(f"--telemetry {self.telemetry}: {what} (the flight's telemetry: a CSV, or a "
                                    "video's SRT).\nFix: give the file's path (relative paths start from the "
                                    f"current directory, {Path.cwd()}), or leave --telemetry out.")


def _video_telemetry(video: VideoFramesDataset, source: PredictSource, srt: Path | None,
                     table: flight.TelemetryCsv | None) -> flight.TelemetryReport | None:
    """The video's priors (and their provenance) from its SRT and / or a CSV naming its frames; the report.

    ``srt``: the one given as ``--telemetry``; None: the video's own beside it, unless metadata is not read.
    """
    if srt is None and source.read_metadata:
        srt = next((p for p in (video.path.with_suffix(".SRT"), video.path.with_suffix(".srt")) if p.is_file()), None)
    if srt is None and table is None:
        return None
    frames = range(0, video.frame_count, video.frame_step)[:video.max_frames] if video.frame_count > 0 else None
    height, width = video.frame_size
    found, report = flight.video_telemetry(video.path, frames, srt, table, fps=video.fps,
                                           size=(width, height) if width > 0 and height > 0 else None,
                                           strict=source.strict_telemetry, name=video.name)
    video.priors = {frame: t.values() for frame, t in found.items()}
    video.provenance = {frame: t.provenance for frame, t in found.items()}
    return report


def _images_dataset(files: list[SourceFile], source: PredictSource, target: NetworkSize, keep_rgb: bool,
                    table: flight.TelemetryCsv | None) -> ImageFilesDataset:
    paths, names = [f.path for f in files], [f.name for f in files]
    report = None
    if table is not None or source.read_metadata:
        found, report = flight.images_telemetry(paths, table, read_metadata=source.read_metadata,
                                                sensor_width_mm=source.sensor_width_mm,
                                                strict=source.strict_telemetry)
        rows = np.stack([t.values() for t in found])
        known = bool(np.isfinite(rows).any())
        dataset = ImageFilesDataset(paths, target, keep_rgb, rows if known else None,
                                    [t.provenance for t in found] if known else None, names)
    else:
        dataset = ImageFilesDataset(paths, target, keep_rgb, names=names)
    dataset.telemetry_report = report
    return dataset


def source_datasets(source: PredictSource, target: NetworkSize, keep_rgb: bool = False,
                    chunk: int = 1) -> list[ImageFilesDataset | VideoFramesDataset]:
    """The data sets of a source at the network size ``target``, each image with its telemetry prior.

    All images in one data set (batched by size), then one per video, in the order given. ``chunk``: video
    frames a loader worker takes in a row (the batch size keeps frames in order). When telemetry is read, its
    summary (how many images or frames use it, from which sources) is logged once per data set; what the sources
    hold but are not predicted (videos in a folder) is logged too. A ``telemetry`` CSV is read once for all the
    data sets, with one warning for its names that match none of them; a ``.SRT`` serves the one video.

    Raises:
        ValueError: a ``.SRT`` as ``telemetry`` for several videos.
        TelemetryError: the CSV's errors (a ``.SRT`` with no video predicted among them).
    """
    files, notes = resolve_sources(source.path)
    for note in notes:
        rank_zero_info(note)
    images = [f for f in files if f.kind == "image"]
    videos = [f for f in files if f.kind == "video"]
    given = Path(source.telemetry) if source.telemetry is not None else None
    srt = given if given is not None and given.suffix.lower() == ".srt" and videos else None
    if srt is not None and len(videos) > 1:
        raise ValueError(f"--telemetry {srt}: one SRT for {len(videos)} videos "
                         f"({first_few([v.path.name for v in videos])}); predict its video alone with it, "
                         "leave each video's .SRT beside it (read by default), or give a CSV naming the frames as "
                         "their outputs are named (DJI_0005_f000012)")
    table = flight.TelemetryCsv.read(given) if given is not None and srt is None else None
    datasets: list[ImageFilesDataset | VideoFramesDataset] = []
    if images:
        datasets.append(_images_dataset(images, source, target, keep_rgb, table))
    for file in videos:
        video = VideoFramesDataset(file.path, target, source.frame_step, source.max_frames, chunk, keep_rgb,
                                   name=file.name)
        video.telemetry_report = _video_telemetry(video, source, srt, table)
        datasets.append(video)
    if table is not None:
        table.warn_unmatched()
    for dataset in datasets:
        if dataset.telemetry_report is not None:
            rank_zero_info(dataset.telemetry_report.summary())
    return datasets


def source_dataset(source: PredictSource, target: NetworkSize, keep_rgb: bool = False,
                   chunk: int = 1) -> ImageFilesDataset | VideoFramesDataset:
    """The one data set of a source of images, or of one video (:func:`source_datasets`)."""
    datasets = source_datasets(source, target, keep_rgb, chunk)
    if len(datasets) != 1:
        raise ValueError(f"{source.path}: images and {len(datasets) - 1} video(s): use source_datasets")
    return datasets[0]


class PredictLoader:
    """The batches of every loader of a source in turn (images, then each video); ``loaders`` for Lightning."""

    def __init__(self, loaders: list[DataLoader[PredictInput]]) -> None:
        self.loaders = loaders

    def __iter__(self) -> Iterator[PredictBatch]:
        for loader in self.loaders:
            yield from loader

    def expected_images(self) -> int | None:
        """How many images (frames) this process will predict; None where a video's length is not known."""
        counts = [expected_images(loader) for loader in self.loaders]
        return None if None in counts else sum(c for c in counts if c is not None)


def expected_images(loader: DataLoader[PredictInput]) -> int | None:
    """The images (frames) one loader of :func:`predict_loaders` gives; None for a video of unknown length."""
    dataset = loader.dataset
    if isinstance(dataset, VideoFramesDataset):
        return dataset.expected_frames()
    sampler = loader.batch_sampler
    return sum(len(b) for b in sampler.batches) if isinstance(sampler, SizeBatchSampler) else len(dataset)  # type: ignore[arg-type]


def predict_loaders(source: PredictSource, target: NetworkSize, settings: PriorSettings = PriorSettings(),  # noqa: B008
                    *, batch_size: int = DEFAULT_BATCH_SIZE, num_workers: int = 0, keep_rgb: bool = False,
                    pin_memory: bool = False, rank: int = 0, world_size: int = 1,
                    worker_start_method: str = "forkserver") -> list[DataLoader[PredictInput]]:
    """The loaders of prediction: :class:`PredictBatch` es of a source, images batched by network size.

    One for the images, then one per video. Every entry point uses them: the one-line command and the Python API
    (through :class:`~dapm_lightning.inference.predictor.DAPMPredictor`, chained by :func:`predict_loader`) and
    the Lightning ``predict`` subcommand (:class:`~dapm_lightning.inference.datamodule.PredictDataModule`). Under
    several processes (``rank`` of ``world_size``) each process takes every ``world_size``-th batch of images,
    or its share of a video's frames.
    """
    collate = PredictCollate(settings)
    loaders: list[DataLoader[PredictInput]] = []
    for dataset in source_datasets(source, target, keep_rgb, chunk=batch_size):
        # workers ignore a SIGTERM to the whole job: this process stops the run (the tables written) and then them
        workers: dict[str, Any] = {"collate_fn": collate, "pin_memory": pin_memory,
                                   **loader_workers(num_workers, rank, worker_start_method)}
        if isinstance(dataset, VideoFramesDataset):
            dataset.rank, dataset.world_size = rank, world_size
            loaders.append(DataLoader(dataset, batch_size=batch_size, **workers))
        else:
            sampler = SizeBatchSampler(dataset.network_sizes(), batch_size, rank, world_size)
            loaders.append(DataLoader(dataset, batch_sampler=sampler, **workers))
    return loaders


def predict_loader(source: PredictSource, target: NetworkSize, settings: PriorSettings = PriorSettings(),  # noqa: B008
                   *, batch_size: int = DEFAULT_BATCH_SIZE, num_workers: int = 0, keep_rgb: bool = False,
                   pin_memory: bool = False, rank: int = 0, world_size: int = 1) -> PredictLoader:
    """Every :class:`PredictBatch` of a source, in order: the loaders of :func:`predict_loaders` chained."""
    return PredictLoader(predict_loaders(source, target, settings, batch_size=batch_size, num_workers=num_workers,
                                         keep_rgb=keep_rgb, pin_memory=pin_memory, rank=rank, world_size=world_size))
