"""Prediction files: per image depth, sky, camera and metric 3D; per run the poses table and a contact sheet.

Per image (``OUT/NAME_*``, each kind selectable, :data:`Output`): ``depth.npy`` and ``depth.tif`` float32 metres,
``depth16.png`` uint16 with :data:`DEPTH16_SCALE` units per metre (1000 m = 64000; sky is written as the depth
limit), ``depth_color.png`` for people, ``sky.png`` (probability x 255), ``camera.json`` (K, camera-to-world,
the pose per component with its source and the network's own estimate), ``points.ply`` (metric point cloud in
the gravity-aligned world frame of docs/conventions.md, ground at z = 0, coloured, sky left out) and, on request,
``npz`` (all of it in one ``NAME.npz``); an image's files all come from one run (the others of its name are
removed). Per run: ``poses.csv`` / ``poses.json`` (merged with those of earlier runs into the same folder, under a
lock: runs into one folder at once keep every row) and ``contact_sheet.png`` (tiles bounded for any aspect).

Every file is written whole or not at all and checked (:mod:`dapm_lightning.data.files`): a failed write raises
:class:`~dapm_lightning.data.files.WriteError` naming the file and the fix. The output folder is checked before
any work and made with the first file; one inside the source is refused (:func:`check_output_outside_source`).
A folder written to is marked as a run's (:data:`~dapm_lightning.inference.run_folder.OUTPUT_MARKER`), so that a
later source scan leaves its pictures out (:mod:`dapm_lightning.inference.sources`).
"""

from __future__ import annotations

import fnmatch
import json
import re
import warnings
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import lightning as L
import numpy as np
import torch.distributed as dist
from lightning.pytorch.callbacks import BasePredictionWriter
from lightning.pytorch.utilities import rank_zero_info
from lightning.pytorch.utilities.exceptions import SIGTERMException

from dapm_lightning.data.files import (
    WriteError,
    check_folder_writable,
    make_folder,
    open_atomic,
    remove_empty_folders,
    stops_deferred,
    write_image,
    write_text,
)
from dapm_lightning.data.pictures import depth_picture
from dapm_lightning.geometry.constants import POSE_FIELDS, POSE_KEYS
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.inference.contact_sheet import CONTACT_MAX_IMAGES, contact_sheet, contact_tiles
from dapm_lightning.inference.inputs import PredictSource
from dapm_lightning.inference.poses_table import pose_row, read_poses, write_poses
from dapm_lightning.inference.postprocess import Prediction, batch_predictions
from dapm_lightning.inference.run_folder import (
    MARKER_TEXT,
    OUTPUT_MARKER,
    PER_IMAGE_FILES,
    remove_stale_files,
    run_folder,
)
from dapm_lightning.inference.runtime import apply_inference_options
from dapm_lightning.inference.sources import Sources, as_list, is_list_file, list_entries
from dapm_lightning.inference.video_preview import VideoPreviews
from dapm_lightning.models.dapm import DAPMOutput
from dapm_lightning.options import DEFAULT_OUTPUTS as DEFAULT_OUTPUTS
from dapm_lightning.options import OUTPUT_KINDS as OUTPUT_KINDS
from dapm_lightning.options import Output as Output
from dapm_lightning.options import check_outputs as check_outputs
from dapm_lightning.training.checkpointing import EXIT_SIGTERM, started_by_lightning

DEPTH16_SCALE = 64.0
"""``depth16.png`` stores ``round(depth_m * 64)``: 1/64 m steps, 1000 m = 64000."""


def write_prediction(out: Path, prediction: Prediction, outputs: Iterable[str] = DEFAULT_OUTPUTS,
                     points_stride: int | None = None, points_max_depth: float | None = None,
                     depth_range: tuple[float, float] | None = None) -> list[Path]:
    """Write the selected per-image files of one prediction (``OUT/NAME_*``); returns the paths written.

    Each file is written whole or not at all and checked (:mod:`dapm_lightning.data.files`). The point cloud is
    coloured with the prediction's ``rgb`` when it carries the input's pixels; ``points_stride`` None keeps
    about as many points as the network saw pixels (:meth:`Prediction.auto_stride`). The colour depth map is in
    its own robust range with a colour bar in metres, or in ``depth_range`` (metres) for maps to compare
    (:func:`~dapm_lightning.data.pictures.depth_picture`).

    Raises:
        WriteError: a file could not be written (a full disk, a read-only folder, an image too large to encode).
    """
    return list(prediction_files(out, prediction, outputs, points_stride, points_max_depth, depth_range).values())


def prediction_files(out: Path, prediction: Prediction, outputs: Iterable[str] = DEFAULT_OUTPUTS,
                     points_stride: int | None = None, points_max_depth: float | None = None,
                     depth_range: tuple[float, float] | None = None) -> dict[str, Path]:
    """:func:`write_prediction`, returning each kind written with its path (what the model could give of it).

    A write that fails (a full disk) removes the image's files written before it: an image has all its files or none.
    """
    written: dict[str, Path] = {}
    try:
        return _write_prediction_files(out, prediction, set(outputs), written, points_stride, points_max_depth,
                                       depth_range)
    except BaseException:
        for path in written.values():
            path.unlink(missing_ok=True)
        raise


def _write_prediction_files(out: Path, prediction: Prediction, outputs: set[str], written: dict[str, Path],
                            points_stride: int | None, points_max_depth: float | None,
                            depth_range: tuple[float, float] | None) -> dict[str, Path]:
    """:func:`prediction_files`' writes, each path entered in ``written`` as it is written."""
    name = prediction.name

    def path(kind: str) -> Path:
        return out / PER_IMAGE_FILES[kind].format(name)

    if prediction.depth_m is not None:
        depth = prediction.depth_m.astype(np.float32)
        if "depth_npy" in outputs:
            with open_atomic(path("depth_npy")) as handle:
                np.save(handle, depth)
            written["depth_npy"] = path("depth_npy")
        if "depth_tiff" in outputs:  # 32-bit float TIFF: GDAL, QGIS, PIL ("F" mode), tifffile, OpenCV read it
            written["depth_tiff"] = write_image(path("depth_tiff"), depth)
        if "depth16" in outputs:
            written["depth16"] = write_image(path("depth16"),
                                             np.clip(np.round(depth * DEPTH16_SCALE), 0, 65535).astype(np.uint16))
        if "depth_color" in outputs:
            color = depth_picture(depth, prediction.sky, depth_range)
            written["depth_color"] = write_image(path("depth_color"),
                                                 cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
    if "sky" in outputs and prediction.sky_prob is not None:
        written["sky"] = write_image(path("sky"),
                                     np.round(np.clip(prediction.sky_prob, 0, 1) * 255).astype(np.uint8))
    if "camera" in outputs and prediction.pose is not None:
        written["camera"] = write_text(path("camera"), _json_rows(prediction.camera_dict()))
    if "points" in outputs and prediction.depth_m is not None and prediction.pose is not None:
        stride = points_stride or prediction.auto_stride()  # None: about the network's resolution
        written["points"] = prediction.points(stride, points_max_depth, prediction.rgb).write_ply(
            path("points"))
    if "npz" in outputs:
        arrays: dict[str, Any] = npz_arrays(prediction)
        with open_atomic(path("npz")) as handle:
            np.savez_compressed(handle, **arrays)
        written["npz"] = path("npz")
    remove_stale_files(out, name, written.values())  # an image's files all come from one run
    return written


def npz_arrays(prediction: Prediction) -> dict[str, np.ndarray]:
    """What ``NAME.npz`` holds, of what the model predicts.

    ``depth`` (m), ``sky_prob``, ``K``, ``pose`` (height m, pitch, roll, fov deg), ``pose_network``,
    ``pose_fields`` (the names of ``pose``'s entries, as the files name them: ``height_m``, ``pitch_deg``, ...),
    ``camera_to_world``.
    """
    arrays: dict[str, np.ndarray | None] = {
        "depth": prediction.depth_m, "sky_prob": prediction.sky_prob, "K": prediction.K,
        "camera_to_world": prediction.camera_to_world,
        "pose": None if prediction.pose is None else np.array([prediction.pose[k] for k in POSE_KEYS]),
        "pose_network": None if prediction.pose_network is None
        else np.array([prediction.pose_network[k] for k in POSE_KEYS]),
        "pose_fields": None if prediction.pose is None else np.array(POSE_FIELDS)}
    return {k: v for k, v in arrays.items() if v is not None}


def _json_rows(value: Any) -> str:
    """JSON with each innermost list (a matrix row) on one line."""
    text = json.dumps(value, indent=2)
    return re.sub(r"\[\s+([^\[\]{}]+?)\s+\]", lambda m: "[" + " ".join(m.group(1).split()) + "]", text) + "\n"


def _glob_magic(text: str) -> bool:
    return any(c in text for c in "*?[")


def source_holding(out: str | Path, source: str | Path) -> Path | None:
    """The source folder, or glob pattern root, that the output folder ``out`` is or lies in; None if apart.

    A folder source holds ``out`` when ``out`` is the folder or inside it. A glob pattern's root (its path up to
    the first component with ``*``, ``?`` or ``[``) holds ``out`` when ``out`` is the root, or lies where the
    pattern reaches: anywhere below it with ``**``, else in a folder the pattern's components match (so
    ``'*.jpg'`` with ``--out predictions`` is apart, ``'flight/*/*.jpg'`` with ``--out flight/out`` is not).
    An image or a video file holds nothing. Paths are compared resolved (links followed).
    """
    text = str(source)
    path = Path(text).expanduser()
    target = Path(out).expanduser().resolve()
    if path.is_dir():
        root = path.resolve()
        return path if target == root or root in target.parents else None
    if path.exists() or not _glob_magic(text):
        return None
    parts = path.parts
    first = next(k for k, part in enumerate(parts) if _glob_magic(part))
    root_path = Path(*parts[:first]) if first else Path(".")
    rest = parts[first:]
    try:
        inside = target.relative_to(root_path.resolve()).parts
    except ValueError:
        return None
    if not inside or "**" in rest:
        return root_path
    if len(inside) < len(rest) and all(fnmatch.fnmatchcase(p, pattern) for p, pattern in zip(inside, rest)):
        return root_path
    return None


def check_output_outside_source(out: str | Path, source: Sources, option: str = "--out") -> None:
    """Refuse an output folder whose files a source would read back as images (one line).

    The folders and patterns a ``.txt`` list names count as sources too (the next run would read them).

    Raises:
        ValueError: ``out`` is a source folder or lies inside one (:func:`source_holding`).
    """
    named: list[tuple[str | Path, str]] = []  # each source with where it was named
    for one in as_list(source):
        if is_list_file(one):
            named += [(text, f" (line {number} of {one})") for number, _, text in list_entries(Path(one).expanduser())]
        else:
            named.append((one, ""))
    for one, origin in named:
        root = source_holding(out, one)
        if root is None:
            continue
        where = "is" if Path(out).expanduser().resolve() == root.resolve() else "lies inside"
        raise ValueError(f"{option} {out} {where} the source {root}{origin}, so its files would be read back as "
                         "images: give an output folder outside the source")


class PredictionFiles:
    """One run's files: each prediction's as it comes, then the poses table, contact sheet and summary line.

    :meth:`add` writes a prediction's files, :meth:`finish` the run's. Used by :class:`PredictionWriter` and
    the one-line ``predict`` command. The output folder is checked when this is made (before a model is loaded),
    an earlier ``poses.csv`` in it read whole (:func:`~dapm_lightning.inference.poses_table.read_poses`: a damaged
    or foreign one is refused before anything is written), and created with the first file, so a run that writes
    nothing leaves no folder; as a context manager (or through :meth:`close`) a folder it created goes again when
    the run fails before writing into it. A run that stops after writing (a damaged image, Ctrl-C, a failed write)
    still writes its tables and sheet for the images written so far when it is closed (:meth:`keep_written`), so
    that they describe the folder's files. Every file is written whole and checked: a failed write raises
    :class:`~dapm_lightning.data.files.WriteError` naming the file and the fix.

    Args:
        output_dir: where the files go (created with the first file); None: a new ``runs/predict<N>``
            (:func:`~dapm_lightning.inference.run_folder.run_folder`).
        outputs: which per-image files to write, any of depth_npy, depth_tiff, depth16, depth_color, sky, camera,
            points, npz, or all; a list or comma-separated (default: depth_color, sky, camera).
        points_stride: point clouds keep every points_stride-th row and column; None: about the network's
            resolution.
        points_max_depth: point clouds drop points farther than this (metres; sky is always dropped).
        contact_sheet: ``contact_sheet.png`` with the first this many images (image and horizon | depth | sky |
            pose), at most :data:`CONTACT_MAX_IMAGES`; 0: none.
        option: the setting that named ``output_dir`` (e.g. ``--out``), named in error messages.
        depth_range: the colour depth maps' range in metres (maps to compare); None: each map its own.
        video_preview: a video's frames beside their depth as ``STEM_depth.mp4``.
        exist_ok: add to an ``output_dir`` that already holds files (each image's files rewritten together); False
            refuses it in one line. exist_ok_option: the setting that says so, named in that line.
    """

    def __init__(self, output_dir: str | Path | None = None, outputs: Iterable[str] | str | None = None,
                 points_stride: int | None = None, points_max_depth: float | None = None, contact_sheet: int = 8,
                 option: str | None = None, exist_ok: bool = True, exist_ok_option: str = "--exist_ok",
                 depth_range: tuple[float, float] | None = None, video_preview: bool = True) -> None:
        if points_stride is not None and points_stride < 1:
            raise ValueError(f"points_stride must be >= 1, got {points_stride}")
        if points_max_depth is not None and not points_max_depth > 0:  # a point cloud with no point, written whole
            raise ValueError(f"points_max_depth must be a distance above 0 m (or None: no limit), got "
                             f"{points_max_depth}")
        self.output_dir = run_folder(output_dir, exist_ok, option or "output_dir", exist_ok_option)
        self.outputs = check_outputs(outputs)
        self.points_stride, self.points_max_depth = points_stride, points_max_depth
        if contact_sheet > CONTACT_MAX_IMAGES:
            warnings.warn(f"a contact sheet shows at most {CONTACT_MAX_IMAGES} images, not {contact_sheet}",
                          stacklevel=2)
        self.contact_images = min(max(0, contact_sheet), CONTACT_MAX_IMAGES)
        self.option, self.video_preview = option, video_preview
        if depth_range is not None and not 0 < depth_range[0] < depth_range[1]:
            raise ValueError(f"depth_range must be two depths in metres, 0 < MIN < MAX, got {list(depth_range)}")
        self.depth_range = None if depth_range is None else (float(depth_range[0]), float(depth_range[1]))
        check_folder_writable(self.output_dir, option)
        read_poses(self.output_dir / "poses.csv", option or "output_dir")  # an earlier table it can add to, or none
        self.created: list[Path] = []
        """The folders this object created (outermost first)."""
        self.marked = False
        """Whether the folder was marked as a prediction run's (:meth:`_mark`)."""
        self.start()

    def start(self) -> None:
        """A new run: nothing counted yet (the folder is created with the first file)."""
        self.rows: list[dict[str, Any]] = []
        self.contact_rows: list[list[np.ndarray]] = []
        self.previews = VideoPreviews()
        self.images = 0
        self.kinds: set[str] = set()
        """The per-image kinds written for at least one image."""
        self.finished = False
        """Whether the run's files were attempted, once only (:meth:`finish`; :meth:`keep_written` after a failure)."""
        self.kept: str | None = None
        """After a run that stopped early: the summary of what it kept (:meth:`keep_written`)."""

    def _folder(self) -> Path:
        if not self.output_dir.is_dir():
            self.created += make_folder(self.output_dir)
        return self.output_dir

    def _mark(self) -> None:
        """Mark the folder as a prediction run's, once, after its first file.

        With :data:`~dapm_lightning.inference.run_folder.OUTPUT_MARKER` there, a later run given a folder or pattern
        that reaches it leaves its pictures out.

        Best effort: a marker that cannot be written (a full disk) does not stop the run, whose error would name
        it instead of the files; the folder is still known by its poses tables.
        """
        if not self.marked:
            self.marked = True
            if not (self.output_dir / OUTPUT_MARKER).is_file():
                try:
                    write_text(self.output_dir / OUTPUT_MARKER, MARKER_TEXT)
                except (WriteError, OSError):
                    pass

    def _failed(self, error: BaseException) -> BaseException:
        """After a failed write: the folder goes if this run created it and it is empty; the error names the option."""
        self.close()
        if isinstance(error, WriteError) and self.option and self.option not in error.fix:
            return WriteError(error.path, error.reason, f"{error.fix} ({self.option})")
        return error

    def add(self, prediction: Prediction) -> None:
        """Write one prediction's files (its ``rgb``, when kept, colours the points and the contact sheet).

        SIGTERM and Ctrl-C wait until the files and the image's row are both kept (:func:`stops_deferred`).
        """
        with stops_deferred():
            self._add(prediction)

    def _add(self, prediction: Prediction) -> None:
        try:
            written = prediction_files(self._folder(), prediction, self.outputs, self.points_stride,
                                       self.points_max_depth, self.depth_range)
            if written:
                self._mark()
            if self.video_preview and prediction.time_s is not None and prediction.depth_m is not None:
                self.previews.add(self.output_dir, prediction,
                                  depth_picture(prediction.depth_m, prediction.sky, self.depth_range))
        except BaseException as error:
            raised = self._failed(error)
            if raised is error:
                raise
            raise raised from error
        self.kinds.update(written)
        if prediction.pose is not None:
            self.rows.append(pose_row(prediction))
        if len(self.contact_rows) < self.contact_images:
            self.contact_rows.append(contact_tiles(prediction))
        self.images += 1

    def finish(self) -> str:
        """Write the poses table (merged with the folder's) and the contact sheet; returns the summary line.

        The summary names only the files written: the per-image kinds the model gave, the tables and sheet. Tried
        once: when it fails, :meth:`close` does not write them again (every image was written, nothing stopped early).
        """
        extra: list[str] = []
        self.finished = True
        try:
            with stops_deferred():  # a stop meanwhile would leave the table half updated (poses.csv, no poses.json)
                for _, step in self._run_files():
                    extra += step()
        except BaseException as error:
            raised = self._failed(error)
            if raised is error:
                raise
            raise raised from error
        return summary_line(self.images, [k for k in self.outputs if k in self.kinds], self.output_dir, extra)

    def _run_files(self) -> list[tuple[str, Callable[[], list[str]]]]:
        """The steps that write the run's files (previews, poses table, sheet): each named, each giving its names."""

        def previews() -> list[str]:
            return [p.name for p in self.previews.finish()]

        def poses() -> list[str]:
            return [write_poses(self._folder(), self.rows).name] if self.rows else []

        def sheet() -> list[str]:
            if not self.contact_rows:
                return []
            return [write_image(self._folder() / "contact_sheet.png",
                                cv2.cvtColor(contact_sheet(self.contact_rows), cv2.COLOR_RGB2BGR)).name]

        return [("the video preview", previews), ("the poses tables (poses.csv, poses.json)", poses),
                ("contact_sheet.png", sheet)]

    def keep_written(self) -> str | None:
        """After a run that stopped early: the run's files for the images written so far; their summary line.

        A damaged image, Ctrl-C or a failed write stops a run after some images' files were written (with
        ``exist_ok`` over an earlier run's): the poses table takes their rows and the contact sheet shows them, so
        the tables describe the folder's files as after a whole run. Best effort, each file on its own: one that
        cannot be written either (a full disk) stays as it was, whole. None when nothing was written (or the run
        finished); :meth:`close` calls this.
        """
        if self.finished or not self.images or not self.output_dir.is_dir():
            return None
        self.finished = True
        extra: list[str] = []
        failed: list[str] = []
        with stops_deferred():  # a second Ctrl-C while the tables of a stopped run are written
            for what, step in self._run_files():
                try:
                    extra += step()
                except Exception as error:  # noqa: BLE001 - the error that stopped the run is the one reported
                    self.previews.abandon()
                    failed.append(f"{what} ({getattr(error, 'reason', None) or error})")
        self.kept = summary_line(self.images, [k for k in self.outputs if k in self.kinds], self.output_dir, extra)
        if failed:
            self.kept += f"; could not be updated: {', '.join(failed)}"
        return self.kept

    def gather_to_first_process(self, is_first: bool) -> None:
        """Under ``torch.distributed``, gather every process's rows, sheet rows, image count and kinds into the first.

        The first process's :meth:`finish` then writes the one poses table and contact sheet; the others keep none.
        """
        if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
            return
        parts: list[Any] = [None] * dist.get_world_size()
        dist.all_gather_object(parts, (self.rows, self.contact_rows, self.images, sorted(self.kinds)))
        if is_first:
            self.rows = sorted((row for part in parts for row in part[0]), key=lambda row: str(row["name"]))
            self.contact_rows = [row for part in parts for row in part[1]][:self.contact_images]
            self.images = sum(part[2] for part in parts)
            self.kinds = {kind for part in parts for kind in part[3]}
        else:
            self.rows, self.contact_rows = [], []

    def close(self) -> None:
        """The end of a run, done or failed: the folders this run created go again if nothing was written there.

        A run closed before :meth:`finish` (it failed) first writes its tables for what it wrote
        (:meth:`keep_written`). A stop arriving meanwhile (a second Ctrl-C) waits until it is done.
        """
        with stops_deferred():
            self.keep_written()
            self.previews.abandon()
            remove_empty_folders(self.created)
            self.created = [folder for folder in self.created if folder.is_dir()]

    def __enter__(self) -> PredictionFiles:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()


class PredictionWriter(BasePredictionWriter):
    """Lightning's side of :class:`PredictionFiles`: each batch's files, then the run's, then one summary line.

    Predictions are not kept in memory (the trainer's return_predictions is switched off), so memory
    stays flat over any number of images or frames. The output folder is checked when the writer is made, and
    refused before the first batch when the data module's source would read its files back as images; a run
    that writes nothing leaves no folder.

    Args:
        output_dir, outputs, points_stride, points_max_depth, contact_sheet: as in :class:`PredictionFiles`.
        channels_last: run the network with channels-last memory (NHWC convolutions).
        compile: torch.compile the network before the first batch (each new input size compiles
            again: worth it for long runs of one size, e.g. a video).

    Under DDP every process writes the files of its own images into rank 0's folder; the first process gathers
    every process's rows and writes the one poses table and contact sheet of all (every image exactly once) and
    the summary line.
    ``output_dir`` None: a new ``runs/predict<N>`` per run; one that holds files is refused unless ``exist_ok``.
    """

    OPTION = "--trainer.callbacks.output_dir"
    """The setting that names the output folder, in messages."""

    def __init__(self, output_dir: str | None = None, outputs: list[str] | str | None = None,
                 points_stride: int | None = None,
                 points_max_depth: float | None = None, contact_sheet: int = 8, channels_last: bool = False,
                 compile: bool = False, exist_ok: bool = False,
                 depth_range: tuple[float, float] | None = None) -> None:
        super().__init__(write_interval="batch")
        self.channels_last, self.compile = channels_last, compile
        self.files = PredictionFiles(output_dir, outputs, points_stride, points_max_depth, contact_sheet,
                                     option=self.OPTION, depth_range=depth_range)
        self.named, self.exist_ok = output_dir is not None, exist_ok
        self.spec = IGDSpec()

    @property
    def output_dir(self) -> Path:
        """Where the files go."""
        return self.files.output_dir

    def on_predict_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        source = getattr(getattr(trainer, "datamodule", None), "source", None)
        if isinstance(source, PredictSource):  # before the first batch; a missing checkpoint is named first
            check_output_outside_source(self.output_dir, source.path, self.OPTION)
        if self.named:  # a folder that holds files: refused unless exist_ok
            run_folder(self.output_dir, self.exist_ok, self.OPTION, "--trainer.callbacks.exist_ok")
        if trainer.world_size > 1:  # one folder for every process: rank 0's (a new runs/predict<N> is per process)
            self.files.output_dir = Path(trainer.strategy.broadcast(str(self.files.output_dir)))
        self.files.video_preview = trainer.world_size == 1  # a video's frames are shared between processes
        trainer.predict_loop.return_predictions = False  # the files are the result: keep nothing in memory
        apply_inference_options(pl_module, self.channels_last, self.compile)
        config = getattr(pl_module, "net_config", None)
        self.spec = config.igd if config is not None else IGDSpec()

    def on_predict_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.files.start()

    def write_on_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, prediction: Any,
                           batch_indices: Sequence[int] | None, batch: Any, batch_idx: int,
                           dataloader_idx: int = 0) -> None:
        output: DAPMOutput = prediction  # DAPMModule.predict_step's
        for result in batch_predictions(output.inference_outputs(spread=True), batch, self.spec):
            self.files.add(result)
        if trainer.received_sigterm:  # Lightning's predict loop runs on after SIGTERM: stop here, as for Ctrl-C
            raise SIGTERMException(0 if started_by_lightning(trainer) else EXIT_SIGTERM)

    def on_predict_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """The run's tables and sheet: under DDP every process's rows gathered, written once by the first process."""
        self.files.gather_to_first_process(trainer.is_global_zero)
        message = self.files.finish()
        self.files.close()
        if trainer.world_size > 1:
            message += f" ({trainer.world_size} processes)"
        rank_zero_info(message)

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        """A failed run: the tables take the rows of the images written; one that wrote nothing leaves no folder.

        Each process merges its own rows into the one table (under its lock); the first process's images make the
        contact sheet.
        """
        if not trainer.is_global_zero:
            self.files.contact_rows = []
        self.files.close()
        if isinstance(exception, SIGTERMException):
            rank_zero_info(f"stopped by SIGTERM{f': {self.files.kept}' if self.files.kept else ''}")
        elif self.files.kept:
            rank_zero_info(f"stopped early by the error below: {self.files.kept}")


def summary_line(images: int, outputs: Sequence[str], out: Path, extra: Sequence[str] = ()) -> str:
    """``predicted N images: depth_npy, ... per image; poses.csv, contact_sheet.png in OUT/``.

    ``outputs``: the per-image kinds written, ``extra``: the run's files written; with neither, ``nothing written``.
    """
    count = f"predicted {images} image{'s' if images != 1 else ''}"
    if not outputs and not extra:
        return f"{count}: nothing written"
    per_image = f"{', '.join(outputs)} per image" if outputs else ""
    files = ", ".join(extra)
    return f"{count}: {per_image}{'; ' if per_image and files else ''}{files} in {out}/"
