"""Prediction at scale: folders, glob patterns and videos in; depth, sky, camera and metric 3D out.

Per image (``OUT/NAME_*``, each kind selectable with ``PredictionWriter(outputs=...)``): ``depth.npy`` and
``depth.tif`` float32 metres, ``depth16.png`` uint16 with ``DEPTH16_SCALE`` units per metre (1000 m = 64000;
sky is written as 1000 m), ``depth_color.png`` for people, ``sky.png`` (probability x 255), ``camera.json``
(intrinsics K from the predicted FoV, camera-to-world transform, pose) and ``points.ply`` (metric point
cloud in the gravity-aligned world frame of docs/conventions.md, ground at z = 0, coloured); one
``poses.csv`` / ``poses.json`` for the run (height m, pitch, roll, fov deg).
"""

from __future__ import annotations

import csv
import glob
import json
import math
import re
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import cv2
import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from lightning.pytorch.callbacks import BasePredictionWriter
from torch import Tensor
from torch.utils.data import DataLoader, Dataset, IterableDataset, get_worker_info

from dapm_lightning.data.datamodules import DAPMDataModule
from dapm_lightning.geometry.camera import intrinsics_matrix
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_KEYS
from dapm_lightning.geometry.depth_codec import decode_log_depth, encode_log_depth
from dapm_lightning.geometry.pointcloud import camera_to_world, depth_to_points, valid_points
from dapm_lightning.tools.ply import write_ply
from dapm_lightning.training.visualize import colorize_depth

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")
DEPTH16_SCALE = 64.0
"""``depth16.png`` stores ``round(depth_m * 64)``: 1/64 m steps, 1000 m = 64000."""
OUTPUT_KINDS = ("depth_npy", "depth_tiff", "depth16", "depth_color", "sky", "camera", "points")
"""What :class:`PredictionWriter` can write per image (all by default)."""
Output = Literal["depth_npy", "depth_tiff", "depth16", "depth_color", "sky", "camera", "points"]
Precision = Literal["32", "bf16", "16"]


# ----------------------------------------------------------------------------------------------------------- inputs
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


def network_size(height: int, width: int, image_width: int | None, multiple: int = 32) -> tuple[int, int]:
    """Input size for the network, ``(h, w)``.

    Width ``image_width`` (or the image's), height scaled by the same factor (square pixels keep the
    meaning of the FoV), both rounded to ``multiple``.
    """
    target_w = image_width or width
    target_h = height * target_w / width
    return (max(multiple, int(round(target_h / multiple)) * multiple),
            max(multiple, int(round(target_w / multiple)) * multiple))


def prepare_image(rgb: np.ndarray, image_width: int | None) -> torch.Tensor:
    """``[H, W, 3]`` uint8 RGB -> ``[3, h, w]`` uint8 tensor at the network size."""
    size = network_size(rgb.shape[0], rgb.shape[1], image_width)
    if size != rgb.shape[:2]:
        rgb = cv2.resize(rgb, (size[1], size[0]), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))


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


def _item(rgb: np.ndarray, name: str, image_width: int | None, keep_rgb: bool) -> dict[str, Any]:
    item = {"image": prepare_image(rgb, image_width), "name": name, "orig_size": torch.tensor(rgb.shape[:2])}
    if keep_rgb:
        item["rgb"] = torch.from_numpy(rgb)
    return item


class ImageFilesDataset(Dataset[dict[str, Any]]):
    """Image files (png, jpg, tif, bmp, webp; grey, RGBA and 16-bit handled), resized for the network.

    Args:
        paths: the files. image_width: network input width (aspect kept). keep_rgb: also return the
            original ``[H, W, 3]`` uint8 pixels (to colour point clouds).
    """

    def __init__(self, paths: Sequence[Path], image_width: int | None = 512, keep_rgb: bool = False) -> None:
        self.paths, self.image_width, self.keep_rgb = list(paths), image_width, keep_rgb
        stems: dict[str, Path] = {}
        for p in self.paths:
            if p.stem in stems:
                raise ValueError(f"{p} and {stems[p.stem]} would write the same output files (same name "
                                 f"{p.stem!r}): predict them in separate runs or rename one")
            stems[p.stem] = p

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> dict[str, Any]:
        path = self.paths[index]
        return _item(read_image(path), path.stem, self.image_width, self.keep_rgb)


class ImageFolderDataset(ImageFilesDataset):
    """Every image in ``folder`` (or matching a glob pattern), resized for the network."""

    def __init__(self, folder: str | Path, image_width: int | None = 512, keep_rgb: bool = False) -> None:
        kind, paths = resolve_source(folder)
        if kind != "images":
            raise ValueError(f"{folder}: a video; use VideoFramesDataset")
        super().__init__(paths, image_width, keep_rgb)
        self.folder = Path(folder)


class VideoFramesDataset(IterableDataset[dict[str, Any]]):
    """Frames of a video file (anything OpenCV's FFmpeg back-end reads), named ``STEM_f<frame number>``.

    Args:
        path: the video. image_width: network input width. frame_step: keep every ``frame_step``-th frame.
        max_frames: stop after this many kept frames. chunk: frames a loader worker takes in a row (the
            batch size keeps the frames in order with several workers; each worker decodes the whole video
            but converts only its own frames). keep_rgb: also return the frame's pixels.

    Under DDP each process takes its own share of the chunks.
    """

    def __init__(self, path: str | Path, image_width: int | None = 512, frame_step: int = 1,
                 max_frames: int | None = None, chunk: int = 1, keep_rgb: bool = False) -> None:
        self.path, self.image_width, self.keep_rgb = Path(path), image_width, keep_rgb
        if frame_step < 1 or chunk < 1:
            raise ValueError(f"frame_step and chunk must be >= 1, got {frame_step} and {chunk}")
        self.frame_step, self.max_frames, self.chunk = frame_step, max_frames, chunk
        self.rank, self.world_size = 0, 1
        capture = self._open()
        self.frame_count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        capture.release()

    def _open(self) -> Any:
        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            raise ValueError(f"{self.path}: OpenCV cannot open it as a video (damaged, or a codec its FFmpeg "
                             "lacks: convert it, e.g. ffmpeg -i IN -c:v libx264 OUT.mp4, or extract frames)")
        return capture

    def __iter__(self) -> Iterator[dict[str, Any]]:
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
                yield _item(to_rgb8(bgr, f"{self.path} frame {frame}"), f"{self.path.stem}_f{frame:06d}",
                            self.image_width, self.keep_rgb)
        finally:
            capture.release()


def _collate(items: list[dict[str, Any]]) -> dict[str, Any]:
    sizes = {tuple(i["image"].shape) for i in items}
    if len(sizes) > 1:
        names = ", ".join(f"{i['name']} {tuple(i['image'].shape[1:])}" for i in items[:4])
        raise ValueError(f"images of different aspect ratios in one batch ({names}): set "
                         "data.init_args.batch_size: 1, or predict each size in its own run")
    batch = {"image": torch.stack([i["image"] for i in items]), "name": [i["name"] for i in items],
             "orig_size": torch.stack([i["orig_size"] for i in items])}
    if "rgb" in items[0]:
        batch["rgb"] = [i["rgb"] for i in items]
    return batch


class PredictDataModule(DAPMDataModule):
    """predict on images or a video of any size; no depth or pose needed.

    Args:
        source: a folder of images, a glob pattern ('flight/**/*.jpg', quoted), one image, or a video
            file (.mp4, .avi, .mov, ...).
        image_width: network input width (height scaled to keep the aspect); None keeps each image's
            size (rounded to 32). A batch needs images of one aspect ratio.
        batch_size: images per forward pass.
        num_workers: decoding processes.
        frame_step: videos: keep every frame_step-th frame.
        max_frames: videos: stop after this many kept frames.
        keep_rgb: ship the original pixels with each batch (the writer colours point clouds with them).
        pin_memory: DataLoader setting (GPUs).
        folder: the former name of source (kept so that older commands work); source wins when both are set.
    """

    def __init__(self, source: str = "images", image_width: int | None = 512, batch_size: int = 1,
                 num_workers: int = 0, frame_step: int = 1, max_frames: int | None = None,
                 keep_rgb: bool = True, pin_memory: bool = False, folder: str | None = None) -> None:
        super().__init__(batch_size=batch_size, num_workers=num_workers, augment=False, pin_memory=pin_memory)
        self.source = folder if folder is not None and source == "images" else source
        self.image_width = image_width
        self.frame_step, self.max_frames, self.keep_rgb = frame_step, max_frames, keep_rgb

    def setup(self, stage: str | None = None) -> None:
        if stage not in (None, "predict"):
            raise ValueError(f"{type(self).__name__} serves predict only (no labels), not {stage!r}; "
                             "use a labelled data module (e.g. UAPDDataModule) to validate or test")

    def dataset(self) -> Dataset[dict[str, Any]]:
        """The images' or the video's data set."""
        kind, paths = resolve_source(self.source)
        if kind == "video":
            video = VideoFramesDataset(paths[0], self.image_width, self.frame_step, self.max_frames,
                                       chunk=self.batch_size, keep_rgb=self.keep_rgb)
            if self.trainer is not None:
                video.rank, video.world_size = self.trainer.global_rank, self.trainer.world_size
            return video
        return ImageFilesDataset(paths, self.image_width, self.keep_rgb)

    def predict_dataloader(self) -> DataLoader[dict[str, Any]]:
        return DataLoader(self.dataset(), batch_size=self.batch_size, num_workers=self.num_workers,
                          collate_fn=_collate, pin_memory=self.pin_memory)


class ImageFolderDataModule(PredictDataModule):
    """The former name of PredictDataModule (folder is its source)."""

    def __init__(self, folder: str = "images", image_width: int | None = 512, batch_size: int = 1,
                 num_workers: int = 0, keep_rgb: bool = True) -> None:
        super().__init__(source=folder, image_width=image_width, batch_size=batch_size, num_workers=num_workers,
                         keep_rgb=keep_rgb)


# ---------------------------------------------------------------------------------------------------------- outputs
def resize_depth(depth_m: torch.Tensor, size: Sequence[int], max_depth: float = MAX_DEPTH_M) -> torch.Tensor:
    """``[1, h, w]`` metres to ``[1, H, W]``, interpolating in the log space (sky stays sky)."""
    if tuple(depth_m.shape[-2:]) == tuple(size):
        return depth_m
    norm = encode_log_depth(depth_m[None], max_depth)
    return decode_log_depth(F.interpolate(norm, size=tuple(int(s) for s in size), mode="bilinear",
                                          align_corners=False), max_depth)[0]


@dataclass
class PointCloud:
    """Points ``xyz`` ``[N, 3]`` float32 metres in the world frame, optional colours ``rgb`` ``[N, 3]`` uint8."""

    xyz: np.ndarray
    rgb: np.ndarray | None = None

    def write_ply(self, path: str | Path) -> Path:
        """Binary PLY (opens in MeshLab, CloudCompare, Open3D, trimesh)."""
        return write_ply(path, self.xyz, self.rgb)


@dataclass
class Prediction:
    """One image's prediction at the input's size.

    Attributes:
        depth_m: ``[H, W]`` float32 metres (sky = max depth), None for DAPM(P).
        sky: ``[H, W]`` bool, depth at or beyond the limit.
        pose: ``{height, pitch, roll, fov}`` (m, deg), None for DAPM(D).
        sky_prob: ``[H, W]`` float32 probability of "beyond max depth", None without a sky stage.
        K: ``[3, 3]`` intrinsics for the input's size from the predicted FoV (pixel ``(i, j)`` centre at
            ``(j + 0.5, i + 0.5)``), None without a pose.
        camera_to_world: ``[4, 4]`` camera (x right, y down, z forward) to world (origin on the ground
            under the camera, Z up), None without a pose.
        depth_kind: ``"range"`` or ``"planar"``: what ``depth_m`` measures (the model's setting).
        max_depth: the model's depth limit (sky).
    """

    depth_m: np.ndarray | None
    sky: np.ndarray | None
    pose: dict[str, float] | None
    sky_prob: np.ndarray | None = None
    K: np.ndarray | None = None
    camera_to_world: np.ndarray | None = None
    depth_kind: str = "range"
    max_depth: float = MAX_DEPTH_M
    name: str = ""
    extras: dict[str, Any] = field(default_factory=dict)

    def points(self, stride: int = 1, max_depth: float | None = None, rgb: np.ndarray | None = None) -> PointCloud:
        """Metric point cloud of the non-sky pixels, every ``stride``-th row and column, in the world frame.

        Args:
            stride: subsampling step in pixels. max_depth: drop points farther than this (metres).
            rgb: ``[H, W, 3]`` uint8 image of the input's size to colour the points.
        """
        if self.depth_m is None or self.pose is None:
            raise ValueError("a point cloud needs depth and pose: DAPM(D) and DAPM(P) models predict only one")
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        depth = torch.from_numpy(np.ascontiguousarray(self.depth_m, np.float32))[None, None]
        pose = torch.tensor([[self.pose[k] for k in POSE_KEYS]], dtype=torch.float64)
        xyz = depth_to_points(depth.double(), pose, depth_kind=self.depth_kind)[0, ::stride, ::stride]
        keep = valid_points(depth, min(self.max_depth, max_depth or math.inf))[0, ::stride, ::stride]
        colours = None
        if rgb is not None:
            if rgb.shape[:2] != self.depth_m.shape:
                raise ValueError(f"rgb is {rgb.shape[:2]}, depth {self.depth_m.shape}: give the input image")
            colours = np.asarray(rgb)[::stride, ::stride][keep.numpy()].astype(np.uint8)
        return PointCloud(xyz[keep].float().numpy(), colours)

    def camera_dict(self) -> dict[str, Any]:
        """What ``NAME_camera.json`` holds: image size, K, camera-to-world, pose, conventions."""
        height, width = (self.depth_m.shape if self.depth_m is not None else self.extras["size"])
        return {"name": self.name, "width": int(width), "height": int(height),
                "K": None if self.K is None else self.K.tolist(),
                "camera_to_world": None if self.camera_to_world is None else self.camera_to_world.tolist(),
                "pose": None if self.pose is None else {f"{k}_{'m' if k == 'height' else 'deg'}": v
                                                         for k, v in self.pose.items()},
                "depth_kind": self.depth_kind, "max_depth_m": self.max_depth,
                "conventions": "pixel (i, j) centre at (j + 0.5, i + 0.5); camera x right, y down, z forward; world "
                               "origin on the ground under the camera, X horizontal along the optical axis, Y left, "
                               "Z up (docs/conventions.md)"}


def make_prediction(name: str, size: Sequence[int], depth_m: Tensor | None, sky_prob: Tensor | None,
                    pose: Tensor | None, *, max_depth: float = MAX_DEPTH_M, depth_kind: str = "range") -> Prediction:
    """One image's :class:`Prediction` at the input size ``(H, W)`` from the network's outputs for it.

    Args:
        depth_m: ``[1, h, w]`` metres at the network size. sky_prob: ``[1, h, w]``. pose: ``[4]`` physical.
    """
    size = (int(size[0]), int(size[1]))
    depth = sky = prob = None
    if depth_m is not None:
        depth = resize_depth(depth_m.float().cpu(), size, max_depth)[0].numpy()
        sky = depth >= max_depth
    if sky_prob is not None:
        prob_t = sky_prob.float().cpu()[None]
        if tuple(prob_t.shape[-2:]) != size:
            prob_t = F.interpolate(prob_t, size=size, mode="bilinear", align_corners=False)
        prob = prob_t[0, 0].numpy()
    pose_dict = k = c2w = None
    if pose is not None:
        pose64 = pose.detach().double().cpu()[None]
        pose_dict = {key: float(v) for key, v in zip(POSE_KEYS, pose64[0])}
        k = intrinsics_matrix(pose64[:, 3], size)[0].numpy()
        c2w = camera_to_world(pose64)[0].numpy()
    return Prediction(depth, sky, pose_dict, prob, k, c2w, depth_kind, max_depth, name, {"size": size})


def write_prediction(out: Path, name: str, prediction: Prediction, max_depth: float = MAX_DEPTH_M,
                     outputs: Iterable[str] = OUTPUT_KINDS, rgb: np.ndarray | None = None,
                     points_stride: int = 2, points_max_depth: float | None = None) -> list[Path]:
    """Write the selected per-image files of one prediction; returns the paths written."""
    outputs, written = set(outputs), []
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
            color = colorize_depth(torch.from_numpy(depth), max_depth)
            cv2.imwrite(str(written[-1]), cv2.cvtColor(color, cv2.COLOR_RGB2BGR))
    if "sky" in outputs and prediction.sky_prob is not None:
        written.append(out / f"{name}_sky.png")
        cv2.imwrite(str(written[-1]), np.round(np.clip(prediction.sky_prob, 0, 1) * 255).astype(np.uint8))
    if "camera" in outputs and prediction.K is not None:
        written.append(out / f"{name}_camera.json")
        written[-1].write_text(_json_rows(prediction.camera_dict()))
    if "points" in outputs and prediction.depth_m is not None and prediction.pose is not None:
        written.append(out / f"{name}_points.ply")
        prediction.points(points_stride, points_max_depth, rgb).write_ply(written[-1])
    return written


def _json_rows(value: Any) -> str:
    """JSON with each innermost list (a matrix row) on one line."""
    text = json.dumps(value, indent=2)
    return re.sub(r"\[\s+([^\[\]{}]+?)\s+\]", lambda m: "[" + " ".join(m.group(1).split()) + "]", text) + "\n"


def write_poses(out: Path, rows: list[dict[str, Any]], suffix: str = "") -> None:
    """``poses{suffix}.csv`` and ``poses{suffix}.json``: name, height_m, pitch_deg, roll_deg, fov_deg."""
    keys = ["name", "height_m", "pitch_deg", "roll_deg", "fov_deg"]
    with (out / f"poses{suffix}.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    (out / f"poses{suffix}.json").write_text(json.dumps(rows, indent=2) + "\n")


def pose_row(name: str, pose: torch.Tensor) -> dict[str, Any]:
    """One poses-file row from a ``[4]`` physical pose."""
    values = [float(v) for v in pose]
    return {"name": name, **{f"{k}_{'m' if k == 'height' else 'deg'}": round(v, 4)
                             for k, v in zip(POSE_KEYS, values)}}


def _model_settings(module: torch.nn.Module) -> tuple[float, str]:
    config = getattr(module, "net_config", None) or getattr(module, "config", None)
    if config is None:
        return MAX_DEPTH_M, "range"
    return float(config.igd.max_depth), str(config.igd.depth_kind)


class PredictionWriter(BasePredictionWriter):
    """Writes each image's files as its batch is predicted and, at the end, the run's poses file.

    Predictions are not kept in memory (the trainer's return_predictions is switched off), so memory
    stays flat over any number of images or frames.

    Args:
        output_dir: where the files go (created).
        outputs: which per-image files to write, any of depth_npy, depth_tiff, depth16,
            depth_color, sky, camera, points (default: all).
        points_stride: point clouds keep every points_stride-th row and column.
        points_max_depth: point clouds drop points farther than this (metres; sky is always dropped).
        channels_last: run the network with channels-last memory (NHWC convolutions).
        compile: torch.compile the network before the first batch (each new input size compiles
            again: worth it for long runs of one size, e.g. a video).

    Under DDP every process writes its own images and poses_rank<k>.{csv,json}.
    """

    def __init__(self, output_dir: str = "predictions", outputs: list[Output] | None = None, points_stride: int = 2,
                 points_max_depth: float | None = None, channels_last: bool = False, compile: bool = False) -> None:
        super().__init__(write_interval="batch")
        self.channels_last, self.compile = channels_last, compile
        self.output_dir = Path(output_dir)
        self.outputs = list(OUTPUT_KINDS if outputs is None else outputs)
        unknown = sorted(set(self.outputs) - set(OUTPUT_KINDS))
        if unknown:
            raise ValueError(f"unknown output(s) {unknown}; choose from {list(OUTPUT_KINDS)}")
        if points_stride < 1:
            raise ValueError(f"points_stride must be >= 1, got {points_stride}")
        self.points_stride, self.points_max_depth = points_stride, points_max_depth
        self.rows: list[dict[str, Any]] = []
        self.images = 0

    def on_predict_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        trainer.predict_loop.return_predictions = False  # the files are the result: keep nothing in memory
        apply_inference_options(pl_module, self.channels_last, self.compile)

    def on_predict_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.rows, self.images = [], 0
        self.output_dir.mkdir(parents=True, exist_ok=True)

    def write_on_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, prediction: Any,
                           batch_indices: Sequence[int] | None, batch: Any, batch_idx: int,
                           dataloader_idx: int = 0) -> None:
        max_depth, depth_kind = _model_settings(pl_module)
        sizes = batch.get("orig_size")
        rgbs = batch.get("rgb")
        for k, name in enumerate(prediction["name"]):
            size = sizes[k].tolist() if sizes is not None else list(batch["image"].shape[-2:])
            depth = prediction["depth_m"][k] if "depth_m" in prediction else None
            sky_prob = prediction["sky_prob"][k] if "sky_prob" in prediction else None
            pose = prediction["pose"][k] if "pose" in prediction else None
            result = make_prediction(name, size, depth, sky_prob, pose, max_depth=max_depth, depth_kind=depth_kind)
            rgb = rgbs[k].numpy() if rgbs is not None else None
            write_prediction(self.output_dir, name, result, max_depth, self.outputs, rgb, self.points_stride,
                             self.points_max_depth)
            if pose is not None:
                self.rows.append(pose_row(name, pose.float().cpu()))
            self.images += 1

    def on_predict_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.rows:
            suffix = f"_rank{trainer.global_rank}" if trainer.world_size > 1 else ""
            write_poses(self.output_dir, self.rows, suffix)


def apply_inference_options(module: torch.nn.Module, channels_last: bool, compile: bool) -> torch.nn.Module:
    """Channels-last and/or ``torch.compile`` on ``module``'s network in place; returns ``module``."""
    net = getattr(module, "net", module)
    if channels_last:
        net.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    if compile and not getattr(net, "_dapm_compiled", False):
        net.compile(dynamic=False)
        net._dapm_compiled = True
    return module


def _onnx_session(module: torch.nn.Module, path: Path) -> Any:
    """An onnxruntime session of ``path``, exported from ``module`` (dynamic sizes, checked) when missing."""
    import onnxruntime

    if not path.is_file():
        from dapm_lightning.tools.export import export_onnx

        export_onnx(getattr(module, "net", module).eval(), path, (64, 64), checks=1, dynamic=True)
    return onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])


# ------------------------------------------------------------------------------------------------------- Python API
class DAPMPredictor:
    """Python API: load a checkpoint once, then call it on images, batches, tensors, folders or videos.

    Args:
        module: a :class:`~dapm_lightning.training.module.DAPMModule` (or anything returning a ``DAPMOutput``).
        image_width: network input width (aspect kept); None: each image's own size (rounded to 32).
        device: ``"cpu"``, ``"cuda"``, ``"cuda:1"``...
        precision: ``"32"``, ``"bf16"`` or ``"16"`` (autocast; half precision is for GPUs).
        batch_size: images per forward pass when given several.
        channels_last, compile: see :class:`PredictionWriter`.
        onnx_path: run the network in onnxruntime from this ONNX file instead of PyTorch (about 3x eager on
            a CPU at 512x512, same outputs to 4e-5 m; see docs/predict.md); exported from ``module`` first
            when the file does not exist. float32 only.

    Example:
        >>> predictor = DAPMPredictor.from_checkpoint("last.ckpt")                  # doctest: +SKIP
        >>> result = predictor(np.asarray(PIL.Image.open("frame.jpg")))              # doctest: +SKIP
        >>> result.depth_m.shape, result.pose["pitch"], result.K                    # doctest: +SKIP
        >>> results = predictor([frame0, frame1])          # list in, list out      # doctest: +SKIP
        >>> for r in predictor.predict_source("flight.mp4"): r.points(4).write_ply(f"{r.name}.ply")  # doctest: +SKIP
    """

    def __init__(self, module: torch.nn.Module, image_width: int | None = 512, device: str = "cpu",
                 precision: Precision = "32", batch_size: int = 8, channels_last: bool = False,
                 compile: bool = False, onnx_path: str | Path | None = None) -> None:
        if str(precision) not in ("32", "bf16", "16"):
            raise ValueError(f"precision must be '32', 'bf16' or '16', got {precision!r}")
        self.session: Any = None
        if onnx_path is not None:
            if str(precision) != "32":
                raise ValueError("onnx_path runs the float32 ONNX model: use precision '32' (or --fp16 at export)")
            self.session = _onnx_session(module, Path(onnx_path))
        self.module = apply_inference_options(module.eval().to(device), channels_last, compile)
        self.image_width, self.device, self.batch_size = image_width, torch.device(device), max(1, batch_size)
        self.precision, self.channels_last = str(precision), channels_last
        self.max_depth, self.depth_kind = _model_settings(module)

    @classmethod
    def from_checkpoint(cls, path: str | Path, image_width: int | None = 512, device: str = "cpu",
                        **options: Any) -> DAPMPredictor:
        """Load a DAPMModule checkpoint (tensors only: ``weights_only=True``); ``options`` as in the class."""
        from dapm_lightning.training.module import DAPMModule

        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such checkpoint file")
        return cls(DAPMModule.load_from_checkpoint(str(path), map_location=device, weights_only=True),
                   image_width, device, **options)

    def _autocast(self) -> Any:
        if self.precision == "32":
            return torch.autocast(self.device.type, enabled=False)
        return torch.autocast(self.device.type, dtype=torch.bfloat16 if self.precision == "bf16" else torch.float16)

    @torch.no_grad()
    def forward_batch(self, images: Tensor, names: Sequence[str], sizes: Sequence[Sequence[int]]) -> list[Prediction]:
        """``images [B, 3, h, w]`` (uint8, or float in [0, 1]) at the network size -> predictions at ``sizes``."""
        images = images.to(self.device, non_blocking=True)
        if self.channels_last:
            images = images.contiguous(memory_format=torch.channels_last)
        if self.session is not None:
            feed = images.float().div(255.0) if images.dtype == torch.uint8 else images.float()
            outputs = [o.name for o in self.session.get_outputs()]
            values = self.session.run(None, {"image": feed.cpu().numpy()})
            got = {n: torch.from_numpy(v) for n, v in zip(outputs, values)}
            depth, sky_prob, pose = got.get("depth_m"), got.get("sky_prob"), got.get("pose")
        else:
            with self._autocast():
                out = self.module(images)
            depth, sky_prob, pose = out.depth_m, out.sky_prob, out.pose_physical
        return [make_prediction(names[k], sizes[k], None if depth is None else depth[k],
                                None if sky_prob is None else sky_prob[k], None if pose is None else pose[k],
                                max_depth=self.max_depth, depth_kind=self.depth_kind) for k in range(len(names))]

    def _network_input(self, image: Any, index: int) -> tuple[Tensor, tuple[int, int]]:
        """One image (numpy RGB, PIL, or tensor ``[3, H, W]``) -> ``[3, h, w]`` network input and ``(H, W)``."""
        if isinstance(image, Tensor):
            if image.ndim != 3 or image.shape[0] not in (1, 3):
                raise ValueError(f"image {index}: a tensor must be [3, H, W] or [B, 3, H, W] RGB, got "
                                 f"{tuple(image.shape)}")
            size = (int(image.shape[1]), int(image.shape[2]))
            net = network_size(*size, self.image_width)
            image = image.expand(3, -1, -1)
            if image.dtype != torch.uint8:
                image = image.float()
            if net != size:
                resized = F.interpolate(image[None].float(), size=net, mode="bilinear", antialias=True,
                                        align_corners=False)[0]
                image = resized.round().clamp(0, 255).to(torch.uint8) if image.dtype == torch.uint8 else resized
            return image, size
        rgb = to_rgb8(np.asarray(image), f"image {index}", bgr=False)
        return prepare_image(rgb, self.image_width), (rgb.shape[0], rgb.shape[1])

    def __call__(self, images: Any) -> Prediction | list[Prediction]:
        """Predict one image or several.

        Args:
            images: one image: ``[H, W]`` / ``[H, W, 3|4]`` numpy array in RGB order (uint8 or uint16), a PIL
                image, or a ``[3, H, W]`` tensor (uint8, or float RGB in [0, 1]); or several: a list of those,
                a ``[B, H, W, 3]`` numpy array or a ``[B, 3, H, W]`` tensor.

        Returns:
            a :class:`Prediction` for one image, a list of them for several (in order), at each input's size.
        """
        single = ((isinstance(images, Tensor) and images.ndim == 3)
                  or (isinstance(images, np.ndarray) and images.ndim in (2, 3))
                  or not isinstance(images, (list, tuple, np.ndarray, Tensor)))
        items = [images] if single else list(images)
        results: list[Prediction] = []
        pending: list[tuple[Tensor, tuple[int, int]]] = []

        def flush() -> None:
            if pending:
                names = [str(len(results) + k) for k in range(len(pending))]
                results.extend(self.forward_batch(torch.stack([p[0] for p in pending]), names,
                                                  [p[1] for p in pending]))
                pending.clear()

        for index, image in enumerate(items):
            prepared = self._network_input(image, index)
            if pending and (len(pending) >= self.batch_size or prepared[0].shape != pending[0][0].shape
                            or prepared[0].dtype != pending[0][0].dtype):
                flush()
            pending.append(prepared)
        flush()
        return results[0] if single else results

    def predict_source(self, source: str | Path, frame_step: int = 1, max_frames: int | None = None,
                       keep_rgb: bool = False, num_workers: int = 0) -> Iterator[Prediction]:
        """Predictions for a folder, glob pattern, image or video file, one at a time (constant memory).

        With ``keep_rgb`` each prediction's ``extras["rgb"]`` holds the input pixels (for coloured points).
        """
        kind, paths = resolve_source(source)
        dataset: Dataset[dict[str, Any]]
        if kind == "video":
            dataset = VideoFramesDataset(paths[0], self.image_width, frame_step, max_frames, self.batch_size,
                                         keep_rgb)
        else:
            dataset = ImageFilesDataset(paths, self.image_width, keep_rgb)
        loader = DataLoader(dataset, batch_size=self.batch_size, num_workers=num_workers, collate_fn=_collate)
        for batch in loader:
            predictions = self.forward_batch(batch["image"], batch["name"], batch["orig_size"].tolist())
            for k, prediction in enumerate(predictions):
                if keep_rgb:
                    prediction.extras["rgb"] = batch["rgb"][k].numpy()
                yield prediction
