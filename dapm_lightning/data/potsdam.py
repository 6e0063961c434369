"""ISPRS Potsdam (docs/data.md, "Potsdam"): RGB + height tiles cut into square crops, seeded 8:2 split, depth only."""

from __future__ import annotations

import json
import re
import warnings
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch

from dapm_lightning.data.errors import EVERY_FILE_SKIPPED_FIX, BadFileError, DatasetError, SkipsBadFiles, unreadable
from dapm_lightning.data.pngcheck import read_npy_header, read_png_info, scan_files
from dapm_lightning.data.sample import Sample, SampleKey, Transform, make_sample, seed_augmentation, split_key
from dapm_lightning.geometry.constants import MAX_DEPTH_M, MIN_DEPTH_M
from dapm_lightning.geometry.depth_codec import decode_log_depth


def _tile_id(match: re.Match[str]) -> tuple[int, int]:
    """Tile id as numbers, so zero-padded (``02_10``) and plain (``2_10``) names pair."""
    return int(match.group(1)), int(match.group(2))


Product = Literal["ndsm", "dsm"]
"""Height product of the ISPRS download: ``"ndsm"`` (``1_DSM_normalisation``, 8-bit JPEG, height above
ground; what height-estimation work on Potsdam and Table 5's baselines use) or ``"dsm"`` (``1_DSM``,
float TIFF, metres above datum)."""

ISPRS_RGB_DIR = "2_Ortho_RGB"
ISPRS_PRODUCT_DIRS: dict[str, str] = {"ndsm": "1_DSM_normalisation", "dsm": "1_DSM"}
ROOT_FIX = ("Fix: give data.init_args.root the unpacked ISPRS Potsdam download (2_Ortho_RGB/ beside "
            "1_DSM_normalisation/ or 1_DSM/), or a folder of rgb/ and height/ tiles (relative paths start from the "
            "current directory; docs/data.md).")
TILE_FIX = ("Fix: correct the tiles listed, or move each one and its twin (RGB and height) out of their folders, or "
            "leave them out with --data.init_args.on_bad_file skip (`dapm-lightning doctor ROOT` checks every tile).")
"""The fix for bad tiles (an unpaired, undecodable or mismatched one): removing one file of a pair leaves its twin
unpaired."""


def is_potsdam_root(root: Path) -> bool:
    """Whether ``root`` holds Potsdam tiles: the ISPRS download (``2_Ortho_RGB/``) or flat ``rgb/`` + ``height/``."""
    return (root / ISPRS_RGB_DIR).is_dir() or ((root / "rgb").is_dir() and (root / "height").is_dir())


class PotsdamCrops:
    """Cut Potsdam tiles into ``crop_size`` crops once, under ``root/crops_<size>[_<product>]/`` (PNG + .npy).

    Two layouts, detected from ``root``:

    - the unpacked ISPRS download, no renaming: ``2_Ortho_RGB/top_potsdam_<a>_<b>_RGB.tif`` paired by tile
      id with the chosen ``product``: ``1_DSM_normalisation/dsm_potsdam_<aa>_<bb>_normalized_lastools.jpg``
      (``"ndsm"``, the default) or ``1_DSM/dsm_potsdam_<aa>_<bb>.tif`` (``"dsm"``); ids are compared as
      numbers (``02_10`` pairs with ``2_10``);
    - the older flat layout ``rgb/`` + ``height/`` (float height TIFFs whose names hold ``potsdam_<a>_<b>``).

    How a height tile becomes the depth the model learns (metres, the network's log encoding of
    ``[0, 1000 m]``): a float TIFF holds metres and is used as is. The 8-bit nDSM is read per
    ``ndsm_scale``: None (default) reads grey ``g`` the way the authors' loader reads a depth PNG, as the
    normalised log depth ``g / 255``, i.e. ``depth = decode_log_depth(g / 255)`` (so the loss in the
    authors' space and :class:`~dapm_lightning.metrics.AuthorsDepthMetrics` see ``g`` itself); a number
    reads it as ``g * ndsm_scale`` metres. Height 0 (ground in an nDSM) stays 0: a valid target.
    """

    rgb_pattern = re.compile(r"top_potsdam_0*(\d+)_0*(\d+)_RGB\.tif$", re.IGNORECASE)
    height_patterns: dict[str, re.Pattern[str]] = {
        "legacy": re.compile(r"potsdam_0*(\d+)_0*(\d+).*\.tiff?$", re.IGNORECASE),
        "dsm": re.compile(r"^dsm_potsdam_0*(\d+)_0*(\d+)\.tiff?$", re.IGNORECASE),
        "ndsm": re.compile(r"^dsm_potsdam_0*(\d+)_0*(\d+)_normalized_lastools\.jpe?g$", re.IGNORECASE),
    }

    def __init__(self, root: str | Path, *, rgb_dir: str | None = None, height_dir: str | None = None,
                 crop_size: int = 512, product: Product = "ndsm", ndsm_scale: float | None = None,
                 on_bad_file: Literal["raise", "skip"] = "raise") -> None:
        if product not in ISPRS_PRODUCT_DIRS:
            raise ValueError(f"product must be one of {sorted(ISPRS_PRODUCT_DIRS)}, got {product!r}")
        if on_bad_file not in ("raise", "skip"):
            raise ValueError(f"on_bad_file must be 'raise' or 'skip', got {on_bad_file!r}")
        self.root, self.crop_size, self.product, self.ndsm_scale = Path(root), crop_size, product, ndsm_scale
        self.on_bad_file = on_bad_file
        self.isprs = rgb_dir is None and (self.root / ISPRS_RGB_DIR).is_dir()
        if self.isprs:
            self.rgb_dir, self.height_dir = self.root / ISPRS_RGB_DIR, self.root / ISPRS_PRODUCT_DIRS[product]
            self.kind = product
            scale = "log" if ndsm_scale is None else f"{ndsm_scale:g}m"
            self.out = self.root / (f"crops_{crop_size}_{product}" + ("" if product == "dsm" else f"_{scale}"))
        else:
            self.rgb_dir, self.height_dir = self.root / (rgb_dir or "rgb"), self.root / (height_dir or "height")
            self.kind = "legacy"
            self.out = self.root / f"crops_{crop_size}"

    def pairs(self) -> tuple[list[tuple[Path, Path]], list[str]]:
        """``(rgb tile, height tile)`` pairs, and every unpaired tile as a problem.

        Raises:
            DatasetError: no root, no tile folder, or no RGB tile at all (nothing to leave out: the fix is the root).
        """
        if not self.root.is_dir():
            what = "a file, not a folder" if self.root.exists() else "no such folder"
            raise DatasetError(self.root, [f"{self.root}: {what}"], fix=ROOT_FIX)
        for folder in (self.rgb_dir, self.height_dir):
            if not folder.is_dir():
                hint = (f" (the ISPRS download's folder for product {self.product!r}; set product to the one "
                        "you unpacked)" if self.isprs and folder == self.height_dir else "")
                raise DatasetError(self.root, [f"{folder}: missing folder{hint}"], fix=ROOT_FIX)
        pattern = self.height_patterns[self.kind]
        rgb = {_tile_id(m): p for p in sorted(self.rgb_dir.iterdir()) if (m := self.rgb_pattern.search(p.name))}
        height = {_tile_id(m): p for p in sorted(self.height_dir.iterdir())
                  if (m := pattern.search(p.name)) and "RGB" not in p.name}
        if not rgb:
            raise DatasetError(self.root, [f"{self.rgb_dir}: no top_potsdam_*_RGB.tif tiles"], fix=ROOT_FIX)
        problems = [f"{rgb[k]}: no height tile for id {k}" for k in sorted(rgb.keys() - height.keys())]
        problems += [f"{height[k]}: no RGB tile for id {k}" for k in sorted(height.keys() - rgb.keys())]
        return [(rgb[k], height[k]) for k in sorted(rgb.keys() & height.keys())], problems

    def read_pair(self, rgb_path: Path, height_path: Path) -> tuple[np.ndarray, np.ndarray] | list[str]:
        """A tile pair decoded, ``(rgb [H, W, 3] BGR uint8, height [H, W] float32 metres)``, or its problems."""
        rgb = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
        height = self.read_height(height_path)
        if rgb is None or height is None:  # both are decoded: each one that fails is listed
            return [str(unreadable(path, "cannot be decoded")) for path, image in
                    ((rgb_path, rgb), (height_path, height)) if image is None]
        if height.ndim != 2:
            return [f"{height_path}: height must be single-channel, got {height.shape}"]
        if height.shape != rgb.shape[:2]:
            return [f"{height_path}: size {height.shape[::-1]} differs from {rgb_path.name} {rgb.shape[1::-1]}"]
        return rgb, height

    def check_tiles(self) -> tuple[int, list[str]]:
        """``(tile pairs, problems)``: every tile paired, decoded and of its twin's size (nothing is written)."""
        pairs, problems = self.pairs()
        for rgb_path, height_path in pairs:
            result = self.read_pair(rgb_path, height_path)
            if isinstance(result, list):
                problems += result
        return len(pairs), problems

    def read_height(self, path: Path) -> np.ndarray | None:
        """A height tile as float32 metres (see the class notes), or None when it cannot be decoded."""
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            return None
        if raw.ndim == 3:  # an 8-bit JPEG nDSM may be stored with three equal channels
            raw = raw[..., 0] if np.array_equal(raw[..., 0], raw[..., -1]) else raw
        if raw.dtype == np.uint8:
            if self.ndsm_scale is not None:
                return raw.astype(np.float32) * np.float32(self.ndsm_scale)
            grey = torch.from_numpy(raw.astype(np.float64) / 255.0)
            return decode_log_depth(grey, MAX_DEPTH_M).numpy().astype(np.float32)
        return raw.astype(np.float32)

    def prepare(self) -> Path:
        """Write the crops (once; skipped when ``crops.json`` is there) and return their folder.

        Every tile problem (unpaired, undecodable, a size differing from its twin's) is collected: with
        ``on_bad_file="raise"`` one :class:`DatasetError` lists them all; with ``"skip"`` those tiles are left out
        with one warning naming them, recorded in ``crops.json`` (crops cut so are reused without them, with the
        warning again, and refused with ``"raise"``).
        """
        index = self.out / "crops.json"
        if index.is_file():
            skipped = json.loads(index.read_text()).get("skipped", [])
            if skipped and self.on_bad_file != "skip":
                raise DatasetError(self.root, skipped, fix=(
                    f"Fix: delete {self.out} (its crops were cut with on_bad_file skip, without the tiles listed) "
                    "to cut them again once the tiles are corrected, or leave them out with "
                    "--data.init_args.on_bad_file skip."))
            self._warn_skipped(skipped)
            return self.out
        pairs, problems = self.pairs()  # first: a root that is not there is not made
        (self.out / "rgb").mkdir(parents=True, exist_ok=True)
        (self.out / "height").mkdir(parents=True, exist_ok=True)
        names: list[str] = []
        small: list[str] = []  # tiles too small for one crop
        for rgb_path, height_path in pairs:
            result = self.read_pair(rgb_path, height_path)  # every tile is decoded: each one that fails is listed
            if isinstance(result, list):
                problems += result
                continue
            if problems and self.on_bad_file != "skip":  # the crops will not be used: only the checks matter
                continue
            rgb, height = result
            s = self.crop_size
            if min(rgb.shape[:2]) < s:
                small.append(f"{rgb_path}: {rgb.shape[1]}x{rgb.shape[0]} pixels, smaller than one {s}x{s} crop")
            for top in range(0, rgb.shape[0] - s + 1, s):
                for left in range(0, rgb.shape[1] - s + 1, s):
                    name = f"{rgb_path.stem}_{top}_{left}"
                    cv2.imwrite(str(self.out / "rgb" / f"{name}.png"), rgb[top:top + s, left:left + s])
                    np.save(self.out / "height" / f"{name}.npy",
                            height[top:top + s, left:left + s].astype(np.float32))
                    names.append(name)
        if problems and self.on_bad_file != "skip":
            raise DatasetError(self.root, problems, fix=TILE_FIX)
        if not names and small:  # no tile large enough for one crop
            raise DatasetError(self.root, small, fix="Fix: a smaller --data.init_args.crop_size (each tile is cut "
                               "into crops of that side; ISPRS Potsdam's tiles are 6000x6000 pixels).")
        if not names:  # every tile bad: on_bad_file skip left out all of them
            raise DatasetError(self.root, problems, fix=EVERY_FILE_SKIPPED_FIX)
        index.write_text(json.dumps({"crop_size": self.crop_size, "layout": self.kind, "ndsm_scale": self.ndsm_scale,
                                     "names": names, "skipped": problems}) + "\n")
        self._warn_skipped(problems)
        return self.out

    def _warn_skipped(self, skipped: list[str]) -> None:
        """One warning naming the tiles left out (the same text from one line: Python shows it once a process)."""
        if skipped:
            warnings.warn(f"{self.root}: leaving out {len(skipped)} bad tile(s) (on_bad_file: skip); the crops in "
                          f"{self.out} are cut without them (delete that folder to cut them again once corrected):"
                          "\n  " + "\n  ".join(skipped[:50]), stacklevel=1)


class PotsdamDataset(SkipsBadFiles, torch.utils.data.Dataset[Sample]):
    """Potsdam crops as :class:`Sample` s: depth = height above ground in metres, no pose (NaN).

    The crops of the split are checked when the data set is built: each crop's PNG (structure and every chunk's
    CRC, 8-bit colour, the crop size) and its height ``.npy`` (header and length); every problem is listed in one
    :class:`DatasetError`, or, with ``on_bad_file="skip"``, the crop is left out and listed in :attr:`skipped`.
    A file that fails when its sample is loaded raises :class:`~dapm_lightning.data.errors.BadFileError` naming
    it (``missing`` when it is gone); with ``on_bad_file="skip"`` a loader leaves the sample out instead.

    Args:
        root: the unpacked ISPRS download (``2_Ortho_RGB/`` and ``1_DSM_normalisation/`` and/or ``1_DSM/``),
            or a folder with ``rgb/`` and ``height/`` tiles (crops are cut on first use).
        split: ``"train"`` or ``"val"``: a seeded 8:2 split of the crops.
        seed: split seed.
        product: ``"ndsm"`` or ``"dsm"`` (ISPRS layout only), see :class:`PotsdamCrops`.
        ndsm_scale: how the 8-bit nDSM becomes metres, see :class:`PotsdamCrops`.
        on_bad_file: ``"raise"`` (default) or ``"skip"``.
    """

    def __init__(self, root: str | Path, split: Literal["train", "val"], transform: Transform | None = None, *,
                 crop_size: int = 512, val_fraction: float = 0.2, seed: int = 0,
                 image_dtype: Literal["float32", "uint8"] = "float32", augment_seed: int | None = None,
                 product: Product = "ndsm", ndsm_scale: float | None = None,
                 on_bad_file: Literal["raise", "skip"] = "raise") -> None:
        if on_bad_file not in ("raise", "skip"):
            raise ValueError(f"on_bad_file must be 'raise' or 'skip', got {on_bad_file!r}")
        crops = PotsdamCrops(root, crop_size=crop_size, product=product, ndsm_scale=ndsm_scale,
                             on_bad_file=on_bad_file).prepare()
        names: list[str] = json.loads((crops / "crops.json").read_text())["names"]
        order = torch.randperm(len(names), generator=torch.Generator().manual_seed(seed)).tolist()
        n_val = max(1, round(len(names) * val_fraction)) if len(names) > 1 else 0
        chosen = order[:n_val] if split == "val" else order[n_val:]
        self.crops, self.root, self.crop_size = crops, Path(root), crop_size
        self.transform, self.image_dtype = transform, image_dtype
        self.augment_seed, self.on_bad_file = augment_seed, on_bad_file
        if not chosen:
            raise DatasetError(root, [f"{crops}: no crops for split {split!r}"])
        chosen_names = [names[i] for i in sorted(chosen)]
        results = scan_files(self._check_crop, chosen_names)
        self.skipped = [problem for problem in results if problem]
        self.names = [name for name, problem in zip(chosen_names, results) if not problem]
        if self.skipped and on_bad_file != "skip":
            raise DatasetError(crops, self.skipped)
        if self.skipped:
            warnings.warn(f"{crops}: skipping {len(self.skipped)} bad crop(s):\n  " + "\n  ".join(self.skipped[:50]),
                          stacklevel=2)
        if not self.names:  # every crop bad: on_bad_file skip left out all of them
            raise DatasetError(crops, self.skipped, fix=EVERY_FILE_SKIPPED_FIX)

    def _paths(self, name: str) -> tuple[Path, Path]:
        return self.crops / "rgb" / f"{name}.png", self.crops / "height" / f"{name}.npy"

    def _check_crop(self, name: str) -> str | None:
        """What is wrong with a crop's two files, or None."""
        rgb_path, height_path = self._paths(name)
        size = (self.crop_size, self.crop_size)
        try:
            info = read_png_info(rgb_path)
            if info.bit_depth != 8 or info.color_type not in (2, 6) or (info.height, info.width) != size:
                return (f"{rgb_path}: crop must be an 8-bit RGB PNG of {size[1]}x{size[0]}, got {info.bit_depth}-bit "
                        f"{info.color} of {info.width}x{info.height}")
            shape, dtype = read_npy_header(height_path)
            if shape != size or dtype.kind != "f":
                return f"{height_path}: height crop must be a float array of shape {size}, got {dtype} {shape}"
        except ValueError as error:
            return str(error)
        return None

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, key: SampleKey) -> Sample:
        epoch, index = split_key(key)
        name = self.names[index]
        rgb_path, height_path = self._paths(name)
        bgr = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise unreadable(rgb_path, "cannot be decoded")
        rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
        try:
            height = np.load(height_path)
        except FileNotFoundError as error:
            raise unreadable(height_path) from error
        except (OSError, ValueError) as error:
            raise BadFileError(height_path, f"cannot be read as a .npy array ({error})") from error
        pose = np.full(4, np.nan, np.float32)
        if self.transform is not None:
            seed_augmentation(self.transform, self.augment_seed, epoch, index)
            result = self.transform(image=rgb, mask=height, pose=pose)
            rgb, height, pose = result["image"], result["mask"], result["pose"]
        if not np.isfinite(height).all():
            raise BadFileError(height_path, f"{int((~np.isfinite(height)).sum())} non-finite height value(s) (NaN or "
                                            "Inf) in this crop")
        depth_m = np.minimum(height, MAX_DEPTH_M - MIN_DEPTH_M)
        return make_sample(rgb, depth_m, None, name, {}, image_dtype=self.image_dtype)
