"""UAPD on disk (docs/data.md, "UAPD layout"): file-name pose parsing and the data set reading rgb/depth pairs."""

from __future__ import annotations

import json
import math
import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path, PurePath
from typing import Any, Literal

import cv2
import numpy as np
import torch

from dapm_lightning.data.errors import EVERY_FILE_SKIPPED_FIX, BadFileError, DatasetError, SkipsBadFiles, unreadable
from dapm_lightning.data.pngcheck import read_png_info, scan_files
from dapm_lightning.data.sample import Sample, SampleKey, Transform, make_sample, seed_augmentation, split_key
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_KEYS
from dapm_lightning.geometry.depth_codec import check_depth_limit, grey_to_depth
from dapm_lightning.geometry.pose import impossible_pose_value

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")
"""Image files the project reads (data sets and prediction inputs)."""
DATA_SUFFIXES = IMAGE_SUFFIXES + (".exr", ".npy", ".npz", ".pfm", ".hdr")
"""Files in rgb/ or depth/ that look meant as images or depth maps: named when they are not NAME.png."""
_IMAGE_SIGNATURES = (b"\x89PNG", b"\xff\xd8\xff")  # PNG, JPEG: an image whatever its name
KEY_ALIASES = {"z": "height", "height": "height", "pitch": "pitch", "roll": "roll", "fov": "fov"}
"""File-name keys that carry the pose, mapped to the pose component they name."""
TOKEN_OF = {"height": "z", "pitch": "pitch", "roll": "roll", "fov": "fov"}
"""The file-name key of each pose component, as UAPD writes it (``z_57.20``)."""
_NUMBER = re.compile(r"^[+-]?(\d+(\.\d*)?|\.\d+)$")
_KEY = re.compile(r"^[A-Za-z]+$")
_FLOAT32_MAX = float(np.finfo(np.float32).max)

"""Called as ``transform(image=rgb, mask=grey, pose=pose)``; returns the same keys (albumentations style)."""


def parse_uapd_filename(name: str | PurePath) -> dict[str, Any]:
    """Parse the pose (and other ``key_value`` tokens) out of a UAPD file name.

    Args:
        name: e.g. ``"Town03_000123_x_-12.5_y_40.1_z_57.20_pitch_-63.40_roll_12.75_yaw_33.0_fov_88.10.png"``;
            a directory and an image extension are ignored; tokens may come in any order.

    Returns:
        ``{"height", "pitch", "roll", "fov"}`` as floats (``z`` is the height), every other
        ``letters_number`` pair as a float under its own key (``x``, ``y``, ``yaw``, ...), and the
        remaining tokens, in order, as a list under ``"tokens"`` (``["Town03", "000123"]``).

    Raises:
        ValueError: naming the file, for a missing pose key, a pose key without a number, a number that is not
            finite (a pose value beyond float32's range included: it would train on an infinite pose), a key
            given twice with different values, or a pose no camera can have (height <= 0 m, |pitch| or |roll| above
            180 degrees, FoV outside (0, 180) degrees: :func:`~dapm_lightning.geometry.pose.impossible_pose_value`).
            Values outside the UAPD ranges but possible are accepted (the doctor counts them).
    """
    path = PurePath(name)
    stem = path.stem if path.suffix.lower() in IMAGE_SUFFIXES else path.name
    tokens = stem.split("_")
    parsed: dict[str, Any] = {}
    loose: list[str] = []
    i = 0
    while i < len(tokens):
        token = tokens[i]
        key = KEY_ALIASES.get(token.lower(), token) if _KEY.match(token) else None
        following = tokens[i + 1] if i + 1 < len(tokens) else None
        if key in POSE_KEYS and (following is None or not _NUMBER.match(following)):
            raise ValueError(f"{name}: pose key {token!r} is followed by {following!r}, not a number")
        if key is not None and following is not None and _NUMBER.match(following):
            value = float(following)
            if key in POSE_KEYS and not abs(value) <= _FLOAT32_MAX:
                raise ValueError(f"{name}: pose key {token!r} value {following} overflows float32, the pose's type "
                                 "(|value| must be at most 3.4e38)")
            if not math.isfinite(value):
                raise ValueError(f"{name}: key {token!r} value {following} is not a finite number")
            if key in parsed and parsed[key] != value:
                raise ValueError(f"{name}: key {key!r} given twice with different values "
                                 f"({parsed[key]} and {value})")
            parsed[key] = value
            i += 2
            continue
        loose.append(token)
        i += 1
    missing = [key for key in POSE_KEYS if key not in parsed]
    if missing:
        raise ValueError(f"{name}: missing pose key(s) {missing} (expected tokens z_, pitch_, roll_, fov_)")
    impossible = [f"{TOKEN_OF[key]}_{parsed[key]:g}: {key} {why}" for key in POSE_KEYS
                  if (why := impossible_pose_value(key, parsed[key])) is not None]
    if impossible:
        raise ValueError(f"{name}: a pose no camera can have ({'; '.join(impossible)}); the file name is wrong (a "
                         "sign, a unit or a column swapped where it was written)")
    parsed["tokens"] = loose
    return parsed


def format_uapd_filename(tokens: Sequence[str], pose: Sequence[float] | np.ndarray, *, x: float = 0.0,
                         y: float = 0.0, yaw: float = 0.0, extra: Mapping[str, float] | None = None,
                         suffix: str = ".png") -> str:
    """The UAPD file name :func:`parse_uapd_filename` reads back (docs/data.md, "UAPD layout").

    ``tokens`` (e.g. ``["Town03", "000123"]``) come first, then ``x, y, z`` (the height), ``pitch, yaw, roll,
    fov`` with 2 decimals (the precision the renderers place the camera with), then ``extra`` keys with 3
    decimals, in the given order; e.g. ``Town03_000123_x_1.00_y_2.00_z_57.20_pitch_-63.40_yaw_33.00_roll_12.75
    _fov_88.10.png`` (one line). The pose keys follow the published UAPD set's order, ``z, pitch, yaw, roll,
    fov``, which the authors' evaluation matches as one pattern; the parser takes any order.

    Raises:
        ValueError: a token or an ``extra`` key that the parser would misread.
    """
    height, pitch, roll, fov = (float(v) for v in pose)
    for token in tokens:
        if not token or "_" in token or _KEY.match(token) and token.lower() in KEY_ALIASES:
            raise ValueError(f"token {token!r} would not read back (empty, with '_', or a pose key)")
    for key in extra or {}:
        if not _KEY.match(key) or key.lower() in KEY_ALIASES or key in ("x", "y", "yaw"):
            raise ValueError(f"extra key {key!r} must be letters and not a pose, x, y or yaw key")
    fields = [*tokens, f"x_{x:.2f}", f"y_{y:.2f}", f"z_{height:.2f}", f"pitch_{pitch:.2f}", f"yaw_{yaw:.2f}",
              f"roll_{roll:.2f}", f"fov_{fov:.2f}", *(f"{k}_{v:.3f}" for k, v in (extra or {}).items())]
    return "_".join(fields) + suffix


def pose_from_parsed(parsed: dict[str, Any]) -> np.ndarray:
    """The ``[4]`` float32 pose (height, pitch, roll, fov) of a :func:`parse_uapd_filename` result."""
    return np.array([parsed[key] for key in POSE_KEYS], dtype=np.float32)


def read_rgb(path: Path, *, expected_hw: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image as ``[H, W, 3]`` uint8 RGB.

    Raises:
        BadFileError: naming the file: missing (deleted or moved after the scan), unreadable, cannot be decoded
            (damaged), or not of ``expected_hw``.
    """
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise unreadable(path)
    if expected_hw is not None and image.shape[:2] != expected_hw:
        raise BadFileError(path, f"size {image.shape[1]}x{image.shape[0]} differs from its depth "
                                 f"{expected_hw[1]}x{expected_hw[0]}")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


DEPTH_CONTAINERS = {0: "grey", 2: "RGB", 4: "grey+alpha", 6: "RGBA"}
"""8-bit PNG colour types a depth map may come in, by PNG colour type: the colour channels must be equal (the
authors read depth with OpenCV's grayscale flag, so an RGB(A) copy of the grey map loads the same)."""

CARLA_RAW_DEPTH_HINT = (
    "UAPD depth is 8-bit grey in the log encoding g = floor(255 log2(d + 1) / log2(1001)) (docs/conventions.md, "
    "Depth encoding); unequal channels look like CARLA's raw 24-bit depth (metres = 1000 (R + 256 G + 65536 B) / "
    "(256^3 - 1)). Convert each file with dapm_lightning.geometry.depth_codec.depth_to_grey("
    "dapm_lightning.tools.carla_collect.decode_carla_depth(cv2.imread(path, cv2.IMREAD_UNCHANGED))), save the "
    "grey image, and set depth_kind: planar (CARLA's depth is planar) in the data and in model.net.igd")
"""The fix for a depth PNG whose colour channels differ."""


def read_depth_grey(path: Path) -> np.ndarray:
    """Read a UAPD depth PNG as ``[H, W]`` uint8 grey; a clear error naming the file otherwise.

    Grey, or RGB / RGBA (and grey+alpha) whose colour channels are equal, 8-bit (:data:`DEPTH_CONTAINERS`); the
    alpha channel is ignored. Unequal colour channels are refused with how to convert CARLA's raw depth.

    Raises:
        BadFileError: naming the file: missing (deleted or moved after the scan), unreadable, cannot be decoded
            (damaged), or not such a depth map.
    """
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise unreadable(path)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)):
        raise BadFileError(path, f"depth must be 8-bit grey, RGB or RGBA with equal colour channels, got shape "
                                 f"{image.shape} {image.dtype}")
    if image.ndim == 2:
        return image
    colour = image[..., :3]
    grey = np.ascontiguousarray(colour[..., 0])
    if not (np.array_equal(grey, colour[..., 1]) and np.array_equal(grey, colour[..., 2])):
        spread = int((colour.max(axis=2).astype(np.int16) - colour.min(axis=2)).max())
        raise BadFileError(path, f"depth PNG with {image.shape[2]} channels whose colours differ (by up to "
                                 f"{spread} levels). {CARLA_RAW_DEPTH_HINT}")
    return grey


def is_uapd_image(path: Path) -> bool:
    """Whether the UAPD reader pairs this file: ``NAME.png`` in any case, not a folder, not hidden.

    macOS leaves hidden ``._NAME.png`` files on FAT drives.
    """
    return path.suffix.lower() == ".png" and not path.name.startswith(".") and not path.is_dir()


def _looks_like_data(path: Path) -> bool:
    """Whether a file that is not ``NAME.png`` looks meant as an image or a depth map (its suffix or first bytes).

    Other files (notes, OS metadata) are not the data set's to judge.
    """
    if path.suffix.lower() in DATA_SUFFIXES:
        return True
    try:
        with path.open("rb") as file:
            return file.read(4).startswith(_IMAGE_SIGNATURES)
    except OSError:
        return False


def check_pair(name: str, rgb_path: Path, depth_path: Path) -> tuple[dict[str, Any], str]:
    """Check one pair the way the start-up scan does, without decoding it.

    The name's pose (:func:`parse_uapd_filename`), both PNGs' structure and every chunk's CRC
    (:func:`~dapm_lightning.data.pngcheck.read_png_info`), the depth's container, the RGB's type, equal sizes.

    Returns:
        ``(parsed name, depth container)``.

    Raises:
        DatasetError: every problem of the pair, each naming its file (the name's under the RGB file).
    """
    problems, infos = [], []
    try:
        parsed = parse_uapd_filename(name)
    except ValueError as error:
        problems.append(f"{rgb_path}: {error}")
    for path in (rgb_path, depth_path):
        try:
            infos.append(read_png_info(path))
        except ValueError as error:
            problems.append(str(error))
    if not problems:
        rgb_info, depth_info = infos
        if depth_info.bit_depth != 8 or depth_info.color_type not in DEPTH_CONTAINERS:
            problems.append(f"{depth_path}: depth must be 8-bit grey, RGB or RGBA with equal colour channels, got "
                            f"{depth_info.bit_depth}-bit {depth_info.color}")
        elif rgb_info.color_type not in (2, 6) or rgb_info.bit_depth != 8:
            problems.append(f"{rgb_path}: rgb must be 8-bit RGB or RGBA, got {rgb_info.bit_depth}-bit "
                            f"{rgb_info.color}")
        elif (rgb_info.width, rgb_info.height) != (depth_info.width, depth_info.height):
            problems.append(f"{rgb_path}: size {rgb_info.width}x{rgb_info.height} differs from its depth "
                            f"{depth_info.width}x{depth_info.height}")
    if problems:
        raise DatasetError(rgb_path, problems)
    return parsed, DEPTH_CONTAINERS[infos[1].color_type]


SYNTH_SETTINGS = "synth.json"
"""The file in which ``dapm-lightning synth`` records a rendered set's settings, its depth limit among them."""
BAD_DEPTH_RECORD_FIX = ("write the limit the set was rendered with into its max_depth (`dapm-lightning synth "
                        "--max_depth`; UAPD: 1000), or remove max_depth from it to give the limit yourself")
"""The fix for a ``synth.json`` whose ``max_depth`` cannot be a limit (the data set and the doctor refuse it)."""


def recorded_depth_limit(root: str | Path) -> float | None:
    """The depth limit (metres of grey 255) ``ROOT/synth.json`` records; None when no readable record names one.

    Raises:
        ValueError: the record names a value that cannot be a depth limit (the message names the file; callers add
            the fix of their own setting).
    """
    record = Path(root) / SYNTH_SETTINGS
    try:
        recorded = json.loads(record.read_text()).get("max_depth")
    except (OSError, ValueError, AttributeError):  # none, unreadable, or not an object: not a synth set's record
        return None
    if recorded is None:
        return None
    if isinstance(recorded, bool) or not isinstance(recorded, (int, float)):
        raise ValueError(f"{record}: max_depth {recorded!r} is not a number of metres")
    try:
        return check_depth_limit(recorded, "max_depth")
    except ValueError as error:
        reason = str(error).partition("\n")[0].rstrip(".")  # without the fix, which names another setting
        raise ValueError(f"{record}: {reason}") from None


class UAPDDataset(SkipsBadFiles, torch.utils.data.Dataset[Sample]):
    """UAPD-format pairs ``ROOT/SPLIT/rgb/NAME.png`` + ``ROOT/SPLIT/depth/NAME.png``, pose in NAME.

    The folder is scanned once when the data set is built: every unpaired, unparsable (a pose value that is not a
    finite float32 included), truncated, damaged (a PNG chunk whose CRC does not match), wrongly typed or
    mismatched file, and every other image file (``.jpg``, ...) in ``rgb/`` or ``depth/``, is listed in one
    :class:`DatasetError` (or, with ``on_bad_file="skip"``, left out and listed in :attr:`skipped`).

    A file that fails when its sample is loaded later (deleted or changed after the scan, or damaged where the
    scan cannot see it) raises :class:`~dapm_lightning.data.errors.BadFileError` naming it (``missing`` when it
    is gone); with ``on_bad_file="skip"`` a loader leaves that sample out of its batch instead
    (:class:`~dapm_lightning.data.errors.SkipsBadFiles`).

    Args:
        root: data set root holding ``train/`` and ``val/``.
        split: sub-folder, e.g. ``"train"`` or ``"val"``.
        transform: albumentations-style callable applied to the decoded arrays before the sample is
            built (see :mod:`dapm_lightning.data.transforms`).
        max_depth: metres that grey 255 means.
        image_dtype: ``"float32"`` (RGB in [0, 1]) or ``"uint8"`` (4x fewer bytes per sample;
            the Lightning module normalises on the device).
        on_bad_file: ``"raise"`` (default) or ``"skip"``.
        augment_seed: seeds each sample's augmentation by (seed, epoch, index); None: not reproducible, each
            loader worker seeding the transform from its own seed
            (:func:`~dapm_lightning.data.sample.seed_augmentation`).

    :attr:`depth_containers` says per file (as :attr:`names`) which PNG container its depth uses
    (:data:`DEPTH_CONTAINERS`: ``grey``, ``RGB``, ``grey+alpha``, ``RGBA``).

    Example:
        >>> ds = UAPDDataset("data/uapd", "val")                       # doctest: +SKIP
        >>> sample = ds[0]; sample["depth"].shape, sample["pose"]      # doctest: +SKIP
    """

    rgb_dir = "rgb"
    depth_dir = "depth"

    def __init__(self, root: str | Path, split: str, transform: Transform | None = None, *,
                 max_depth: float = MAX_DEPTH_M, image_dtype: Literal["float32", "uint8"] = "float32",
                 on_bad_file: Literal["raise", "skip"] = "raise", augment_seed: int | None = None) -> None:
        self.root = Path(root)
        self.split = split
        self.transform = transform
        self.max_depth = max_depth
        if image_dtype not in ("float32", "uint8"):
            raise ValueError(f"image_dtype must be 'float32' or 'uint8', got {image_dtype!r}")
        if on_bad_file not in ("raise", "skip"):
            raise ValueError(f"on_bad_file must be 'raise' or 'skip', got {on_bad_file!r}")
        self.image_dtype = image_dtype
        self.on_bad_file = on_bad_file
        self.names, self.poses, self.meta, self.skipped, self.depth_containers = self._scan(on_bad_file)
        self.augment_seed = augment_seed

    def _scan(self, on_bad_file: str) -> tuple[list[str], np.ndarray, list[dict[str, Any]], list[str], list[str]]:
        split_dir = self.root / self.split
        rgb_dir, depth_dir = split_dir / self.rgb_dir, split_dir / self.depth_dir
        layout = f"ROOT/{self.split}/{{{self.rgb_dir},{self.depth_dir}}}/NAME.png"
        if not self.root.is_dir():
            what = "a file, not a folder" if self.root.exists() else "no such folder"
            raise DatasetError(self.root, [f"{self.root}: {what}"], fix=(
                f"Fix: give data.init_args.root the folder of a UAPD-format set ({layout}; relative paths start "
                "from the current directory); `dapm-lightning synth --out ROOT` renders a synthetic one."))
        try:
            recorded = recorded_depth_limit(self.root)
        except ValueError as error:
            raise DatasetError(self.root, [str(error)], fix=(
                f"Fix: {BAD_DEPTH_RECORD_FIX} (--data.init_args.max_depth).")) from None
        if recorded is not None and recorded != self.max_depth:
            raise DatasetError(self.root, [
                f"{self.root / SYNTH_SETTINGS}: the set was rendered with a depth limit of {recorded:g} m (grey 255), "
                f"but it would be read with {self.max_depth:g} m: every depth would be wrong"], fix=(
                f"Fix: --data.init_args.max_depth {recorded:g} --model.net.igd.max_depth {recorded:g} (the data's "
                "and the model's limit), or render the set again with `dapm-lightning synth --max_depth "
                f"{self.max_depth:g}`."))
        for folder in (split_dir, rgb_dir, depth_dir):
            if not folder.is_dir():
                found = sorted(p.name + "/" for p in folder.parent.iterdir() if p.is_dir())
                raise DatasetError(self.root, [f"{folder}: missing folder (expected {layout}; {folder.parent} "
                                               f"holds {', '.join(found) if found else 'no folder'})"], fix=(
                    f"Fix: put the {self.split} split in {layout}, or give data.init_args.root the folder that holds "
                    "it (UAPD's layout: docs/data.md)."))
        files = {folder: sorted(folder.iterdir()) for folder in (rgb_dir, depth_dir)}
        rgb = {p.name: p for p in files[rgb_dir] if is_uapd_image(p)}
        depth = {p.name: p for p in files[depth_dir] if is_uapd_image(p)}
        problems, explained = [], set()
        for folder, same, other in ((rgb_dir, rgb, depth), (depth_dir, depth, rgb)):
            for p in files[folder]:
                if p.name in same or p.name.startswith(".") or not (p.is_dir() or _looks_like_data(p)):
                    continue
                if p.is_dir():
                    problems.append(f"{p}: a folder: UAPD reads the NAME.png files directly in {folder.name}/, so "
                                    "nothing in it is read (move its files up, or move it out)")
                    continue
                unpaired = ""  # the pair this file was likely meant to complete (NAME.jpg, or NAME without .png)
                for twin in (p.stem + ".png", p.name + ".png"):
                    if twin in other and twin not in same:
                        explained.add(twin)
                        unpaired = f", and {other[twin]} has no pair"
                problems.append(f"{p}: not a PNG image by its name: UAPD reads NAME.png pairs only, so this file is "
                                f"not read{unpaired} (convert it to NAME.png, or move it out of the folder)")
        for name in sorted(rgb.keys() - depth.keys() - explained):
            problems.append(f"{rgb[name]}: no depth twin {depth_dir / name}")
        for name in sorted(depth.keys() - rgb.keys() - explained):
            problems.append(f"{depth[name]}: no rgb twin {rgb_dir / name}")

        def check(name: str) -> tuple[dict[str, Any], str] | list[str]:
            try:
                return check_pair(name, rgb[name], depth[name])
            except DatasetError as error:
                return error.problems

        pairs = sorted(rgb.keys() & depth.keys())
        results = scan_files(check, pairs)
        names, poses, meta, containers = [], [], [], []
        for name, result in zip(pairs, results):
            if isinstance(result, list):
                problems += result
                continue
            parsed, container = result
            names.append(name)
            containers.append(container)
            poses.append(pose_from_parsed(parsed))
            meta.append({k: v for k, v in parsed.items() if k not in POSE_KEYS})
        if problems and on_bad_file != "skip":
            raise DatasetError(split_dir, problems)
        if problems:
            warnings.warn(f"{split_dir}: skipping {len(problems)} bad file(s):\n  " + "\n  ".join(problems[:50]),
                          stacklevel=3)
        if not names:  # every pair bad (on_bad_file skip, or the scan raised above), or none at all
            raise DatasetError(split_dir, problems or [f"{rgb_dir}: no PNG images"], fix=EVERY_FILE_SKIPPED_FIX
                               if problems else f"Fix: put the {self.split} split's pairs in {layout}, or give "
                               "data.init_args.root the folder that holds them (UAPD's layout: docs/data.md).")
        pose_array = np.stack(poses) if poses else np.zeros((0, 4), np.float32)
        return names, pose_array, meta, problems, containers

    def __len__(self) -> int:
        return len(self.names)

    def load(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Decoded ``(rgb [H, W, 3] uint8, depth grey [H, W] uint8)`` of one pair, without the transform.

        Raises:
            BadFileError: naming the file that is missing (deleted or moved after the scan) or cannot be decoded.
        """
        name = self.names[index]
        split_dir = self.root / self.split
        grey = read_depth_grey(split_dir / self.depth_dir / name)
        rgb = read_rgb(split_dir / self.rgb_dir / name, expected_hw=grey.shape[:2])
        return rgb, grey

    def __getitem__(self, key: SampleKey) -> Sample:
        epoch, index = split_key(key)
        rgb, grey = self.load(index)
        pose = self.poses[index]
        if self.transform is not None:
            seed_augmentation(self.transform, self.augment_seed, epoch, index)
            result = self.transform(image=rgb, mask=grey, pose=pose)
            rgb, grey, pose = result["image"], result["mask"], result["pose"]
        return make_sample(rgb, grey_to_depth(grey, self.max_depth), pose, Path(self.names[index]).stem,
                           self.meta[index], image_dtype=self.image_dtype)
