"""ISPRS Potsdam (design.md §4): RGB + height tiles cut into square crops, seeded 8:2 split, depth only."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch

from dapm_lightning.data.errors import DatasetError
from dapm_lightning.data.sample import Sample, SampleKey, Transform, make_sample, seed_augmentation, split_key
from dapm_lightning.geometry.constants import MAX_DEPTH_M, MIN_DEPTH_M


class PotsdamCrops:
    """Cut Potsdam tiles into ``crop_size`` crops once, under ``root/crops_<size>/`` (rgb PNG + height .npy).

    Tiles are paired by tile id: ``top_potsdam_<a>_<b>_RGB.tif`` with the height tile whose name holds
    ``potsdam_<a>_<b>`` (leading zeros ignored; e.g. ``dsm_potsdam_02_10.tif``), found in ``height_dir``.
    """

    rgb_pattern = re.compile(r"top_potsdam_0*(\d+)_0*(\d+)_RGB\.tif$", re.IGNORECASE)
    height_pattern = re.compile(r"potsdam_0*(\d+)_0*(\d+).*\.tiff?$", re.IGNORECASE)

    def __init__(self, root: str | Path, *, rgb_dir: str = "rgb", height_dir: str = "height",
                 crop_size: int = 512) -> None:
        self.root, self.crop_size = Path(root), crop_size
        self.rgb_dir, self.height_dir = self.root / rgb_dir, self.root / height_dir
        self.out = self.root / f"crops_{crop_size}"

    def pairs(self) -> list[tuple[Path, Path]]:
        """``(rgb tile, height tile)`` pairs; a :class:`DatasetError` lists every unpaired tile."""
        for folder in (self.rgb_dir, self.height_dir):
            if not folder.is_dir():
                raise DatasetError(self.root, [f"{folder}: missing folder"])
        rgb = {m.groups(): p for p in sorted(self.rgb_dir.iterdir()) if (m := self.rgb_pattern.search(p.name))}
        height = {m.groups(): p for p in sorted(self.height_dir.iterdir())
                  if (m := self.height_pattern.search(p.name)) and "RGB" not in p.name}
        problems = [f"{rgb[k]}: no height tile for id {k}" for k in sorted(rgb.keys() - height.keys())]
        problems += [f"{height[k]}: no RGB tile for id {k}" for k in sorted(height.keys() - rgb.keys())]
        if problems or not rgb:
            raise DatasetError(self.root, problems or [f"{self.rgb_dir}: no top_potsdam_*_RGB.tif tiles"])
        return [(rgb[k], height[k]) for k in sorted(rgb)]

    def prepare(self) -> Path:
        """Write the crops (once; skipped when ``crops.json`` is there) and return their folder."""
        index = self.out / "crops.json"
        if index.is_file():
            return self.out
        (self.out / "rgb").mkdir(parents=True, exist_ok=True)
        (self.out / "height").mkdir(parents=True, exist_ok=True)
        names = []
        for rgb_path, height_path in self.pairs():
            rgb = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
            height = cv2.imread(str(height_path), cv2.IMREAD_UNCHANGED)
            if rgb is None or height is None:
                raise DatasetError(self.root, [f"{rgb_path if rgb is None else height_path}: cannot be decoded"])
            if height.ndim != 2:
                raise DatasetError(self.root, [f"{height_path}: height must be single-channel, got {height.shape}"])
            if height.shape != rgb.shape[:2]:
                raise DatasetError(self.root, [f"{height_path}: size {height.shape[::-1]} differs from "
                                               f"{rgb_path.name} {rgb.shape[1::-1]}"])
            s = self.crop_size
            for top in range(0, rgb.shape[0] - s + 1, s):
                for left in range(0, rgb.shape[1] - s + 1, s):
                    name = f"{rgb_path.stem}_{top}_{left}"
                    cv2.imwrite(str(self.out / "rgb" / f"{name}.png"), rgb[top:top + s, left:left + s])
                    np.save(self.out / "height" / f"{name}.npy",
                            height[top:top + s, left:left + s].astype(np.float32))
                    names.append(name)
        index.write_text(json.dumps({"crop_size": self.crop_size, "names": names}) + "\n")
        return self.out


class PotsdamDataset(torch.utils.data.Dataset[Sample]):
    """Potsdam crops as :class:`Sample` s: depth = height above ground in metres, no pose (NaN).

    Args:
        root: folder with ``rgb/`` and ``height/`` tiles (crops are cut on first use).
        split: ``"train"`` or ``"val"``: a seeded 8:2 split of the crops.
        seed: split seed.
    """

    def __init__(self, root: str | Path, split: Literal["train", "val"], transform: Transform | None = None, *,
                 crop_size: int = 512, val_fraction: float = 0.2, seed: int = 0,
                 image_dtype: Literal["float32", "uint8"] = "float32", augment_seed: int | None = None) -> None:
        crops = PotsdamCrops(root, crop_size=crop_size).prepare()
        names: list[str] = json.loads((crops / "crops.json").read_text())["names"]
        order = torch.randperm(len(names), generator=torch.Generator().manual_seed(seed)).tolist()
        n_val = max(1, round(len(names) * val_fraction)) if len(names) > 1 else 0
        chosen = order[:n_val] if split == "val" else order[n_val:]
        self.crops, self.names = crops, [names[i] for i in sorted(chosen)]
        self.transform, self.image_dtype = transform, image_dtype
        self.augment_seed = augment_seed
        if not self.names:
            raise DatasetError(root, [f"{crops}: no crops for split {split!r}"])

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, key: SampleKey) -> Sample:
        epoch, index = split_key(key)
        name = self.names[index]
        bgr = cv2.imread(str(self.crops / "rgb" / f"{name}.png"), cv2.IMREAD_COLOR)
        if bgr is None:
            raise ValueError(f"{self.crops / 'rgb' / name}.png: cannot be decoded")
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        height = np.load(self.crops / "height" / f"{name}.npy")
        pose = np.full(4, np.nan, np.float32)
        if self.transform is not None:
            seed_augmentation(self.transform, self.augment_seed, epoch, index)
            result = self.transform(image=rgb, mask=height, pose=pose)
            rgb, height, pose = result["image"], result["mask"], result["pose"]
        if not np.isfinite(height).all():
            raise ValueError(f"{self.crops / 'height' / name}.npy: {int((~np.isfinite(height)).sum())} "
                             "non-finite height value(s) (NaN or Inf) in this crop")
        depth_m = np.minimum(height, MAX_DEPTH_M - MIN_DEPTH_M)
        return make_sample(rgb, depth_m, None, name, {}, image_dtype=self.image_dtype)
