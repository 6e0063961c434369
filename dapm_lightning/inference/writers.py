"""Prediction files: per image depth, sky, camera and metric 3D; per run the poses table and a contact sheet.

Per image (``OUT/NAME_*``, each kind selectable, :data:`Output`): ``depth.npy`` and ``depth.tif`` float32 metres,
``depth16.png`` uint16 with :data:`DEPTH16_SCALE` units per metre (1000 m = 64000; sky is written as the depth
limit), ``depth_color.png`` for people, ``sky.png`` (probability x 255), ``camera.json`` (K, camera-to-world,
the pose per component with its source and the network's own estimate), ``points.ply`` (metric point cloud in
the gravity-aligned world frame of docs/conventions.md, ground at z = 0, coloured, sky left out) and, on request,
``npz`` (all of it in one ``NAME.npz``). Per run: ``poses.csv`` / ``poses.json`` (merged with those of earlier
runs into the same folder) and ``contact_sheet.png``.
"""

from __future__ import annotations

import csv
import json
import re
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import BasePredictionWriter
from lightning.pytorch.utilities import rank_zero_info

from dapm_lightning.geometry.camera import horizon_segment
from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.inference.inputs import PriorMode
from dapm_lightning.inference.postprocess import Prediction, pose_field, predictions_from_outputs
from dapm_lightning.inference.prior import apply_pose_prior
from dapm_lightning.training.module import batch_prior
from dapm_lightning.training.visualize import colorize_depth

Output = Literal["depth_npy", "depth_tiff", "depth16", "depth_color", "sky", "camera", "points", "npz"]
"""A per-image file kind."""
OUTPUT_KINDS: tuple[str, ...] = get_args(Output)
DEFAULT_OUTPUTS: tuple[str, ...] = tuple(k for k in OUTPUT_KINDS if k != "npz")
"""What is written when nothing is chosen: every kind but the compact ``npz``."""
DEPTH16_SCALE = 64.0
"""``depth16.png`` stores ``round(depth_m * 64)``: 1/64 m steps, 1000 m = 64000."""
POSE_COLUMNS = ["name", *(pose_field(k) for k in POSE_KEYS)]
CONTACT_TILE = 160
"""Height in pixels of one contact-sheet row."""


def check_outputs(outputs: Iterable[str] | None) -> list[str]:
    """The chosen output kinds (default :data:`DEFAULT_OUTPUTS`); unknown ones are refused with the valid list."""
    chosen = list(DEFAULT_OUTPUTS if outputs is None else outputs)
    unknown = sorted(set(chosen) - set(OUTPUT_KINDS))
    if unknown:
        raise ValueError(f"unknown output(s) {unknown}; choose from {list(OUTPUT_KINDS)}")
    return chosen


def write_prediction(out: Path, prediction: Prediction, outputs: Iterable[str] = DEFAULT_OUTPUTS,
                     rgb: np.ndarray | None = None, points_stride: int = 2,
                     points_max_depth: float | None = None) -> list[Path]:
    """Write the selected per-image files of one prediction (``OUT/NAME_*``); returns the paths written."""
    outputs, written, name = set(outputs), [], prediction.name
    if prediction.depth_m is not None:
        depth = prediction.depth_m.astype(np.float32)
        if "depth_npy" in outputs:
            written.append(out / f"{name}_depth.npy")
            np.save(written[-1], depth)
        if "depth_tiff" in outputs:  # 32-bit float TIFF: GDAL, QGIS, PIL ("F" mode), tifffile, OpenCV read it
            written.append(out / f"{name}_depth.tif")
            cv2.imwrite(str(written[-1]), depth)
        if "depth16" in outputs:
            written.append(out / f"{name}_depth16.png")
            cv2.imwrite(str(written[-1]), np.clip(np.round(depth * DEPTH16_SCALE), 0, 65535).astype(np.uint16))
        if "depth_color" in outputs:
            written.append(out / f"{name}_depth_color.png")
            color = colorize_depth(torch.from_numpy(depth), prediction.max_depth)
            cv2.imwrite(str(written[-1]), cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
    if "sky" in outputs and prediction.sky_prob is not None:
        written.append(out / f"{name}_sky.png")
        cv2.imwrite(str(written[-1]), np.round(np.clip(prediction.sky_prob, 0, 1) * 255).astype(np.uint8))
    if "camera" in outputs and prediction.pose is not None:
        written.append(out / f"{name}_camera.json")
        written[-1].write_text(_json_rows(prediction.camera_dict()))
    if "points" in outputs and prediction.depth_m is not None and prediction.pose is not None:
        written.append(out / f"{name}_points.ply")
        prediction.points(points_stride, points_max_depth, rgb).write_ply(written[-1])
    if "npz" in outputs:
        written.append(out / f"{name}.npz")
        arrays: dict[str, Any] = npz_arrays(prediction)
        np.savez_compressed(written[-1], **arrays)
    return written


def npz_arrays(prediction: Prediction) -> dict[str, np.ndarray]:
    """What ``NAME.npz`` holds, of what the model predicts.

    ``depth`` (m), ``sky_prob``, ``K``, ``pose`` (height m, pitch, roll, fov deg), ``pose_network``,
    ``camera_to_world``.
    """
    arrays: dict[str, np.ndarray | None] = {
        "depth": prediction.depth_m, "sky_prob": prediction.sky_prob, "K": prediction.K,
        "camera_to_world": prediction.camera_to_world,
        "pose": None if prediction.pose is None else np.array([prediction.pose[k] for k in POSE_KEYS]),
        "pose_network": None if prediction.pose_network is None
        else np.array([prediction.pose_network[k] for k in POSE_KEYS])}
    return {k: v for k, v in arrays.items() if v is not None}


def _json_rows(value: Any) -> str:
    """JSON with each innermost list (a matrix row) on one line."""
    text = json.dumps(value, indent=2)
    return re.sub(r"\[\s+([^\[\]{}]+?)\s+\]", lambda m: "[" + " ".join(m.group(1).split()) + "]", text) + "\n"


def pose_row(prediction: Prediction) -> dict[str, Any]:
    """One poses-table row: the pose used; with a prior also each component's source and the network's value."""
    assert prediction.pose is not None
    row: dict[str, Any] = {"name": prediction.name,
                           **{pose_field(k): round(v, 4) for k, v in prediction.pose.items()}}
    if prediction.pose_source:
        network = prediction.pose_network or prediction.pose
        for key in POSE_KEYS:
            row[f"{pose_field(key)}_source"] = prediction.pose_source.get(key, "network")
            row[f"{pose_field(key)}_network"] = round(network[key], 4)
    return row


def write_poses(out: Path, rows: list[dict[str, Any]], suffix: str = "") -> Path:
    """``poses{suffix}.csv`` and ``.json``, merged with the folder's earlier ones.

    A row of the same name is replaced, the others are kept (a second run into one folder adds to its table).
    """
    path = out / f"poses{suffix}.csv"
    merged: dict[str, dict[str, Any]] = {}
    if path.is_file():
        with path.open(newline="") as handle:
            merged = {row["name"]: row for row in csv.DictReader(handle) if row.get("name")}
    merged.update({row["name"]: row for row in rows})
    columns = POSE_COLUMNS + sorted({k for row in merged.values() for k in row} - set(POSE_COLUMNS))
    for row in merged.values():  # rows of images without telemetry: their pose is the network's
        for column in columns[len(POSE_COLUMNS):]:
            if row.get(column) in (None, "") and column.endswith(("_source", "_network")):
                row[column] = "network" if column.endswith("_source") else row.get(column[:-len("_network")], "")
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(merged.values())
    values = [{k: _number(v) for k, v in row.items()} for row in merged.values()]
    (out / f"poses{suffix}.json").write_text(json.dumps(values, indent=2) + "\n")
    return path


def _number(value: Any) -> Any:
    """A CSV cell back to a number where it is one (rows merged from an earlier run's file are text)."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def contact_row(prediction: Prediction, rgb: np.ndarray | None, tile: int = CONTACT_TILE) -> np.ndarray:
    """``image | depth | sky | pose`` for one prediction, ``tile`` pixels high.

    The horizon of the pose used is drawn on the image, the pose written on the last tile.
    """
    height, width = prediction.size
    w = max(1, round(width * tile / height))

    def fit(picture: np.ndarray) -> np.ndarray:
        return cv2.resize(picture, (w, tile), interpolation=cv2.INTER_AREA)

    grey = np.full((tile, w, 3), 40, np.uint8)
    image = fit(rgb) if rgb is not None else grey.copy()
    if prediction.pose is not None:
        segment = horizon_segment(prediction.pose["pitch"], prediction.pose["roll"], prediction.pose["fov"],
                                  (height, width))
        if segment is not None:
            (x0, y0), (x1, y1) = segment
            scale = tile / height
            cv2.line(image, (round(x0 * scale), round(y0 * scale)), (round(x1 * scale), round(y1 * scale)),
                     (255, 220, 0), 2, cv2.LINE_AA)
    depth = (fit(colorize_depth(torch.from_numpy(prediction.depth_m), prediction.max_depth))
             if prediction.depth_m is not None else grey)
    sky = (fit(np.repeat((np.clip(prediction.sky_prob, 0, 1) * 255).astype(np.uint8)[..., None], 3, axis=2))
           if prediction.sky_prob is not None else grey)
    text = np.full((tile, 2 * tile, 3), 255, np.uint8)
    lines = [prediction.name[:28]]
    if prediction.pose is not None:
        sources = prediction.pose_source or {}
        lines += [f"{k} {v:.1f} {'m' if k == 'height' else 'deg'}"
                  + (f" ({sources[k]})" if sources.get(k, "network") != "network" else "")
                  for k, v in prediction.pose.items()]
    for row, line in enumerate(lines):
        cv2.putText(text, line, (6, 22 + 24 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([image, depth, sky, text], axis=1)


def contact_sheet(rows: Sequence[np.ndarray]) -> np.ndarray:
    """Rows of :func:`contact_row` stacked (padded to the widest), RGB."""
    width = max(r.shape[1] for r in rows)
    return np.concatenate([np.pad(r, ((0, 4), (0, width - r.shape[1]), (0, 0)), constant_values=255)
                           for r in rows], axis=0)


class PredictionFiles:
    """One run's files: each prediction's as it comes, then the poses table, contact sheet and summary line.

    :meth:`add` writes a prediction's files, :meth:`finish` the run's. Used by :class:`PredictionWriter` and
    the one-line ``predict`` command.

    Args:
        output_dir: where the files go (created).
        outputs: which per-image files to write, any of depth_npy, depth_tiff, depth16, depth_color, sky, camera,
            points, npz (default: all but npz).
        points_stride: point clouds keep every points_stride-th row and column.
        points_max_depth: point clouds drop points farther than this (metres; sky is always dropped).
        contact_sheet: ``contact_sheet.png`` with the first this many images (image and horizon | depth | sky |
            pose); 0: none.
    """

    def __init__(self, output_dir: str | Path = "predictions", outputs: Iterable[str] | None = None,
                 points_stride: int = 2, points_max_depth: float | None = None, contact_sheet: int = 8) -> None:
        self.output_dir = Path(output_dir)
        self.outputs = check_outputs(outputs)
        if points_stride < 1:
            raise ValueError(f"points_stride must be >= 1, got {points_stride}")
        self.points_stride, self.points_max_depth = points_stride, points_max_depth
        self.contact_images = max(0, contact_sheet)
        self.start()

    def start(self) -> None:
        """A new run: nothing counted yet; the folder is created."""
        self.rows: list[dict[str, Any]] = []
        self.contact_rows: list[np.ndarray] = []
        self.images = 0
        self.output_dir.mkdir(parents=True, exist_ok=True)

    def add(self, prediction: Prediction, rgb: np.ndarray | None = None) -> None:
        """Write one prediction's files (``rgb``: the input's pixels, for point colours and the contact sheet)."""
        write_prediction(self.output_dir, prediction, self.outputs, rgb, self.points_stride, self.points_max_depth)
        if prediction.pose is not None:
            self.rows.append(pose_row(prediction))
        if len(self.contact_rows) < self.contact_images:
            self.contact_rows.append(contact_row(prediction, rgb))
        self.images += 1

    def finish(self, suffix: str = "") -> str:
        """Write the poses table (merged with the folder's) and the contact sheet; returns the summary line."""
        extra = []
        if self.rows:
            extra.append(write_poses(self.output_dir, self.rows, suffix).name)
        if self.contact_rows:
            path = self.output_dir / f"contact_sheet{suffix}.png"
            cv2.imwrite(str(path), cv2.cvtColor(contact_sheet(self.contact_rows), cv2.COLOR_RGB2BGR))
            extra.append(path.name)
        return summary_line(self.images, self.outputs, self.output_dir, extra)


class PredictionWriter(BasePredictionWriter):
    """Lightning's side of :class:`PredictionFiles`: each batch's files, then the run's, then one summary line.

    Predictions are not kept in memory (the trainer's return_predictions is switched off), so memory
    stays flat over any number of images or frames.

    Args:
        output_dir, outputs, points_stride, points_max_depth, contact_sheet: as in :class:`PredictionFiles`.
        channels_last: run the network with channels-last memory (NHWC convolutions).
        compile: torch.compile the network before the first batch (each new input size compiles
            again: worth it for long runs of one size, e.g. a video).

    Under DDP every process writes its own images and poses_rank<k>.{csv,json}.
    """

    def __init__(self, output_dir: str = "predictions", outputs: list[Output] | None = None, points_stride: int = 2,
                 points_max_depth: float | None = None, contact_sheet: int = 8, channels_last: bool = False,
                 compile: bool = False) -> None:
        super().__init__(write_interval="batch")
        self.channels_last, self.compile = channels_last, compile
        self.files = PredictionFiles(output_dir, outputs, points_stride, points_max_depth, contact_sheet)
        self.spec = IGDSpec()

    @property
    def output_dir(self) -> Path:
        """Where the files go (:attr:`PredictionFiles.output_dir`)."""
        return self.files.output_dir

    def on_predict_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        from dapm_lightning.inference.predictor import apply_inference_options

        trainer.predict_loop.return_predictions = False  # the files are the result: keep nothing in memory
        apply_inference_options(pl_module, self.channels_last, self.compile)
        config = getattr(pl_module, "net_config", None)
        self.spec = config.igd if config is not None else IGDSpec()

    def on_predict_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.files.start()

    def write_on_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, prediction: Any,
                           batch_indices: Sequence[int] | None, batch: Any, batch_idx: int,
                           dataloader_idx: int = 0) -> None:
        for meta, result in zip(batch["meta"], predictions_from_batch(prediction, batch, self.spec)):
            self.files.add(result, meta.get("rgb"))

    def on_predict_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        suffix = f"_rank{trainer.global_rank}" if trainer.world_size > 1 else ""
        message = self.files.finish(suffix)
        if trainer.world_size > 1:
            print(f"{message} (process {trainer.global_rank} of {trainer.world_size})", flush=True)
        else:
            rank_zero_info(message)


def predictions_from_batch(output: Any, batch: dict[str, Any], spec: IGDSpec) -> list[Prediction]:
    """The predictions of one predict batch from the module's output (a ``DAPMOutput``), its prior applied."""
    outputs = output.inference_outputs(spread=True) if hasattr(output, "inference_outputs") else dict(output)
    return predictions_with_prior(outputs, batch, spec)


def predictions_with_prior(outputs: dict[str, Any], batch: dict[str, Any], spec: IGDSpec) -> list[Prediction]:
    """Per-image predictions of a batch's network outputs, with the batch's pose prior applied (telemetry)."""
    metas = batch["meta"]
    prior = batch_prior(batch)
    mode: PriorMode = metas[0].get("prior_mode", "condition") if metas else "condition"
    outputs, sources, methods = apply_pose_prior(outputs, prior, mode, spec)
    predictions = predictions_from_outputs(outputs, batch["name"], [meta["size"] for meta in metas], spec,
                                           pose_network=outputs.get("pose_network"),
                                           pose_sources=sources if prior is not None else None)
    for prediction, method in zip(predictions, methods):
        prediction.extras["scale_from"] = method
    return predictions


def summary_line(images: int, outputs: Sequence[str], out: Path, extra: Sequence[str] = ()) -> str:
    """``predicted N images: depth_npy, ... per image; poses.csv, contact_sheet.png in OUT``."""
    files = f"; {', '.join(extra)}" if extra else ""
    return f"predicted {images} image{'s' if images != 1 else ''}: {', '.join(outputs)} per image{files} in {out}/"
