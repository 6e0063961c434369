"""Prediction on folders of ordinary images: data module, file writer, and a Python API.

Outputs per image (``OUT/NAME_*``): ``depth.npy`` float32 metres, ``depth16.png`` uint16 with
``DEPTH16_SCALE`` units per metre (1000 m = 64000; sky is written as 1000 m), ``depth_color.png``
for people, and one ``poses.csv`` / ``poses.json`` for the folder (height m, pitch, roll, fov deg).
"""

from __future__ import annotations

import csv
import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import lightning as L
import numpy as np
import torch
import torch.nn.functional as F
from lightning.pytorch.callbacks import BasePredictionWriter
from torch.utils.data import DataLoader, Dataset

from dapm_lightning.data.datamodules import DAPMDataModule
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_KEYS
from dapm_lightning.geometry.depth_codec import decode_log_depth, encode_log_depth
from dapm_lightning.training.visualize import colorize_depth

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
DEPTH16_SCALE = 64.0
"""``depth16.png`` stores ``round(depth_m * 64)``: 1/64 m steps, 1000 m = 64000."""


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


class ImageFolderDataset(Dataset[dict[str, Any]]):
    """Every image in ``folder`` (png, jpg, tif, bmp; grey, RGBA and 16-bit handled), resized for the network."""

    def __init__(self, folder: str | Path, image_width: int | None = 512) -> None:
        self.folder, self.image_width = Path(folder), image_width
        if not self.folder.is_dir():
            raise FileNotFoundError(f"{self.folder}: no such folder of images")
        self.paths = sorted(p for p in self.folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.paths:
            raise ValueError(f"{self.folder}: no images ({', '.join(IMAGE_SUFFIXES)})")

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> dict[str, Any]:
        path = self.paths[index]
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise ValueError(f"{path}: cannot be decoded as an image")
        rgb = to_rgb8(raw, str(path))
        return {"image": prepare_image(rgb, self.image_width), "name": path.stem,
                "orig_size": torch.tensor(rgb.shape[:2])}


class ImageFolderDataModule(DAPMDataModule):
    """``predict`` on a folder of images of any size; no depth or pose needed.

    Args:
        folder: the images. image_width: network input width (height scaled to keep the aspect);
            ``None`` keeps each image's size (rounded to 32). Images of different sizes need batch_size 1
            unless image_width is set.
    """

    def __init__(self, folder: str = "images", image_width: int | None = 512, batch_size: int = 1,
                 num_workers: int = 0, **kwargs: Any) -> None:
        super().__init__(batch_size=batch_size, num_workers=num_workers, augment=False, **kwargs)
        self.folder, self.image_width = folder, image_width

    def setup(self, stage: str | None = None) -> None:
        if stage not in (None, "predict"):
            raise ValueError(f"ImageFolderDataModule serves predict only (no labels), not {stage!r}")

    def predict_dataloader(self) -> DataLoader[dict[str, Any]]:
        return DataLoader(ImageFolderDataset(self.folder, self.image_width), batch_size=self.batch_size,
                          num_workers=self.num_workers, collate_fn=_collate)


def _collate(items: list[dict[str, Any]]) -> dict[str, Any]:
    return {"image": torch.stack([i["image"] for i in items]), "name": [i["name"] for i in items],
            "orig_size": torch.stack([i["orig_size"] for i in items])}


def resize_depth(depth_m: torch.Tensor, size: Sequence[int], max_depth: float = MAX_DEPTH_M) -> torch.Tensor:
    """``[1, h, w]`` metres to ``[1, H, W]``, interpolating in the log space (sky stays sky)."""
    if tuple(depth_m.shape[-2:]) == tuple(size):
        return depth_m
    norm = encode_log_depth(depth_m[None], max_depth)
    return decode_log_depth(F.interpolate(norm, size=tuple(int(s) for s in size), mode="bilinear",
                                          align_corners=False), max_depth)[0]


@dataclass
class Prediction:
    """Depth ``[H, W]`` metres at the input's size, sky mask, and pose ``{height, pitch, roll, fov}``."""

    depth_m: np.ndarray | None
    sky: np.ndarray | None
    pose: dict[str, float] | None


def write_prediction(out: Path, name: str, prediction: Prediction, max_depth: float = MAX_DEPTH_M) -> None:
    """Write ``NAME_depth.npy``, ``NAME_depth16.png`` and ``NAME_depth_color.png`` (depth only)."""
    if prediction.depth_m is None:
        return
    depth = prediction.depth_m.astype(np.float32)
    np.save(out / f"{name}_depth.npy", depth)
    cv2.imwrite(str(out / f"{name}_depth16.png"),
                np.clip(np.round(depth * DEPTH16_SCALE), 0, 65535).astype(np.uint16))
    color = colorize_depth(torch.from_numpy(depth), max_depth)
    cv2.imwrite(str(out / f"{name}_depth_color.png"), cv2.cvtColor(color, cv2.COLOR_RGB2BGR))


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


class PredictionWriter(BasePredictionWriter):
    """Writes each predicted image's depth files and, at the end, the folder's poses file.

    Under DDP every process writes its own images and ``poses_rank<k>.{csv,json}``.
    """

    def __init__(self, output_dir: str = "predictions") -> None:
        super().__init__(write_interval="batch")
        self.output_dir = Path(output_dir)
        self.rows: list[dict[str, Any]] = []

    def on_predict_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.rows = []
        self.output_dir.mkdir(parents=True, exist_ok=True)

    def write_on_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, prediction: Any,
                           batch_indices: Sequence[int] | None, batch: Any, batch_idx: int,
                           dataloader_idx: int = 0) -> None:
        max_depth = _max_depth(pl_module)
        sizes = batch.get("orig_size")
        for k, name in enumerate(prediction["name"]):
            size = sizes[k].tolist() if sizes is not None else None
            depth = sky = None
            if "depth_m" in prediction:
                depth_t = prediction["depth_m"][k].float().cpu()
                depth_t = resize_depth(depth_t, size, max_depth) if size else depth_t
                depth = depth_t[0].numpy()
                sky = depth >= max_depth
            pose = prediction["pose"][k].cpu() if "pose" in prediction else None
            write_prediction(self.output_dir, name, Prediction(depth, sky, None), max_depth)
            if pose is not None:
                self.rows.append(pose_row(name, pose))

    def on_predict_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if self.rows:
            suffix = f"_rank{trainer.global_rank}" if trainer.world_size > 1 else ""
            write_poses(self.output_dir, self.rows, suffix)


def _max_depth(module: L.LightningModule) -> float:
    config = getattr(module, "net_config", None)
    return float(config.igd.max_depth) if config is not None else MAX_DEPTH_M


class DAPMPredictor:
    """Python API: load a checkpoint once, then call it on numpy / PIL images.

    Example:
        >>> predictor = DAPMPredictor.from_checkpoint("last.ckpt")         # doctest: +SKIP
        >>> result = predictor(np.asarray(PIL.Image.open("frame.jpg")))     # doctest: +SKIP
        >>> result.depth_m.shape, result.pose["pitch"]                     # doctest: +SKIP
    """

    def __init__(self, module: L.LightningModule, image_width: int | None = 512, device: str = "cpu") -> None:
        self.module = module.eval().to(device)
        self.image_width, self.device = image_width, device
        self.max_depth = _max_depth(module)

    @classmethod
    def from_checkpoint(cls, path: str | Path, image_width: int | None = 512, device: str = "cpu") -> DAPMPredictor:
        """Load a DAPMModule checkpoint (tensors only: ``weights_only=True``)."""
        from dapm_lightning.training.module import DAPMModule

        return cls(DAPMModule.load_from_checkpoint(str(path), map_location=device, weights_only=True),
                   image_width, device)

    @torch.no_grad()
    def __call__(self, image: Any) -> Prediction:
        """``image``: ``[H, W]`` / ``[H, W, 3|4]`` numpy array in RGB order (uint8 or uint16) or a PIL image."""
        rgb = to_rgb8(np.asarray(image), "image", bgr=False)
        tensor = prepare_image(rgb, self.image_width)[None].to(self.device)
        out = self.module(tensor)
        depth = sky = None
        if out.depth_m is not None:
            depth_t = resize_depth(out.depth_m[0].float().cpu(), rgb.shape[:2], self.max_depth)
            depth = depth_t[0].numpy()
            sky = depth >= self.max_depth
        pose = (None if out.pose_physical is None
                else {k: float(v) for k, v in zip(POSE_KEYS, out.pose_physical[0].cpu())})
        return Prediction(depth, sky, pose)
