"""Drone telemetry (flight metadata) in the project's pose conventions, per image, as a pose prior.

Three sources, each read into :class:`PoseTelemetry` (height m, pitch deg, roll deg, horizontal FoV deg;
NaN = unknown), with the conventions of ``docs/conventions.md`` ("Telemetry"):

- a CSV the user writes (:func:`read_telemetry_csv`): ``name,height_m,pitch_deg,roll_deg,fov_deg``;
- the image's own metadata (:func:`telemetry_from_image`): DJI XMP (``drone-dji:RelativeAltitude``,
  ``GimbalPitchDegree``, ``GimbalRollDegree``) and EXIF focal length, read with Pillow;
- DJI video subtitles (:func:`read_srt`): one subtitle per video frame.

:func:`telemetry_for_images` combines a CSV with the images' metadata, component by component.

Policy: a missing value is unknown (NaN); a value that is there but is not a number, or is physically
impossible, is an error (:class:`TelemetryError`, naming the file, the row / subtitle / tag and the fix).
A value that is a number but cannot be a height above the ground (a relative altitude <= 0: the
drone was on the ground or below its take-off point) is left unknown with a warning.
"""

from __future__ import annotations

import csv
import math
import re
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from PIL import ExifTags, Image, UnidentifiedImageError

from dapm_lightning.data.uapd import IMAGE_SUFFIXES
from dapm_lightning.geometry.constants import POSE_KEYS

__all__ = [
    "CSV_COLUMNS",
    "FULL_FRAME_DIAGONAL_MM",
    "PoseTelemetry",
    "TelemetryError",
    "TelemetryWarning",
    "horizontal_fov_from_focal",
    "horizontal_fov_from_focal_35mm",
    "read_srt",
    "read_telemetry_csv",
    "telemetry_for_images",
    "telemetry_from_image",
]

StrPath = str | PathLike[str]

CSV_COLUMNS: tuple[str, str, str, str, str] = ("name", "height_m", "pitch_deg", "roll_deg", "fov_deg")
"""The telemetry CSV's header; only ``name`` is required, a missing value column means unknown."""

FULL_FRAME_DIAGONAL_MM: float = math.hypot(36.0, 24.0)
"""43.27 mm: the diagonal of a 36 x 24 mm frame, to which a 35-mm-equivalent focal length refers."""

CSV_NAME_SUFFIXES: tuple[str, ...] = (*IMAGE_SUFFIXES, ".dng")
"""Extensions stripped from a CSV ``name``: the images the project reads and the raw DNGs a flight log may
name (anything else after a dot is part of the name)."""

_FIELDS: tuple[str, str, str, str] = ("height_m", "pitch_deg", "roll_deg", "fov_deg")
_SHOW_NAMES = 5
_SRT_MAX_SUBTITLE_S = 0.5
"""A per-frame SRT holds one subtitle per video frame; one lasting longer than this is a per-second SRT."""


class TelemetryError(ValueError):
    """Telemetry that is there but unusable: the message names the file, the row / frame / tag and the fix."""


class TelemetryWarning(UserWarning):
    """Telemetry ignored or left unknown (names in a CSV that match no image, a relative altitude <= 0, ...)."""


def _limit_error(key: str, value: float) -> str | None:
    """Why ``value`` is impossible for pose component ``key`` (``None`` when it is possible)."""
    if not math.isfinite(value):
        return "is not finite"
    if key == "height" and value <= 0:
        return "must be > 0 m (metres above the ground under the camera)"
    if key in ("pitch", "roll") and abs(value) > 180:
        return "must be within [-180, 180] degrees"
    if key == "fov" and not 0 < value < 180:
        return "must be within (0, 180) degrees (horizontal field of view)"
    return None


@dataclass(frozen=True, eq=False)
class PoseTelemetry:
    """A pose prior from telemetry in the project's conventions (design.md §1); NaN = unknown.

    Args:
        height_m: metres above the ground under the camera. pitch_deg: 0 = horizontal, -90 = nadir.
        roll_deg: positive = camera turned clockwise seen from behind (horizon's right end up).
        fov_deg: horizontal field of view across the image width. source: where the known values came
            from (``"flight.csv line 4"``, ``"DJI_0001.JPG XMP/EXIF"``, ``"DJI_0002.SRT frame 12"``).

    Raises:
        ValueError: a known value that is physically impossible (height <= 0, |pitch| or |roll| > 180,
            fov outside (0, 180), or infinite).
    """

    height_m: float = math.nan
    pitch_deg: float = math.nan
    roll_deg: float = math.nan
    fov_deg: float = math.nan
    source: str = ""

    def __post_init__(self) -> None:
        for key, name in zip(POSE_KEYS, _FIELDS):
            value = float(getattr(self, name))
            object.__setattr__(self, name, value)
            if not math.isnan(value) and (why := _limit_error(key, value)) is not None:
                raise ValueError(f"PoseTelemetry{f' ({self.source})' if self.source else ''}: {name} = {value!r} "
                                 f"{why}; use NaN for unknown")

    def values(self) -> npt.NDArray[np.float64]:
        """``[4]`` float64 in ``POSE_KEYS`` order (height, pitch, roll, fov); NaN where unknown."""
        return np.array([self.height_m, self.pitch_deg, self.roll_deg, self.fov_deg], dtype=np.float64)

    def known(self) -> tuple[bool, bool, bool, bool]:
        """Which components are known, in ``POSE_KEYS`` order."""
        h, p, r, f = (not math.isnan(v) for v in (self.height_m, self.pitch_deg, self.roll_deg, self.fov_deg))
        return h, p, r, f

    def merged(self, fallback: PoseTelemetry) -> PoseTelemetry:
        """This telemetry's known components, the others from ``fallback``; ``source`` says which came whence."""
        own, other = self.known(), fallback.known()
        mine = [k for k, o in zip(POSE_KEYS, own) if o]
        theirs = [k for k, o, t in zip(POSE_KEYS, own, other) if not o and t]
        if mine and theirs:
            source = f"{self.source} ({', '.join(mine)}); {fallback.source} ({', '.join(theirs)})"
        else:
            source = self.source if mine else fallback.source if theirs else ""
        values = [a if o else b for a, b, o in zip(self.values().tolist(), fallback.values().tolist(), own)]
        return _telemetry(values, source)

    def _key(self) -> tuple[Any, ...]:
        return (*(None if math.isnan(v) else v for v in self.values().tolist()), self.source)

    def __eq__(self, other: object) -> bool:
        """Equal when the same components are known with the same values (NaN equals NaN) and the same source."""
        if not isinstance(other, PoseTelemetry):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __repr__(self) -> str:
        parts = [f"{f.name}={getattr(self, f.name)!r}" for f in fields(self)
                 if f.name == "source" or not math.isnan(getattr(self, f.name))]
        return f"PoseTelemetry({', '.join(parts)})"


def _telemetry(values: list[float], source: str) -> PoseTelemetry:
    """A :class:`PoseTelemetry` from 4 values in ``POSE_KEYS`` order."""
    h, p, r, f = values
    return PoseTelemetry(height_m=h, pitch_deg=p, roll_deg=r, fov_deg=f, source=source)


# --------------------------------------------------------------------------------------------------- FoV


def horizontal_fov_from_focal_35mm(f35_mm: float, width: int, height: int) -> float:
    """Horizontal FoV (degrees) of a ``width`` x ``height`` image from its 35-mm-equivalent focal length.

    Diagonal definition (CIPA / Exif practice): the image's diagonal is equated with a 36 x 24 mm frame's
    43.27 mm, so the image width corresponds to ``43.27 * W / sqrt(W^2 + H^2)`` mm and
    ``fov = 2 * atan(that / (2 * f35))``. For a 3:2 image that is exactly 36 mm; 24 mm on a 4000 x 3000
    image gives 2 * atan(34.62 / 48) = 71.6 degrees.
    """
    f35, w, h = float(f35_mm), float(width), float(height)
    if not (math.isfinite(f35) and f35 > 0):
        raise ValueError(f"35-mm-equivalent focal length must be a positive number of mm, got {f35_mm!r}")
    if not (math.isfinite(w) and math.isfinite(h) and w > 0 and h > 0):
        raise ValueError(f"image size must be positive, got width={width!r} height={height!r}")
    width_mm = FULL_FRAME_DIAGONAL_MM * w / math.hypot(w, h)
    return math.degrees(2.0 * math.atan(width_mm / (2.0 * f35)))


def horizontal_fov_from_focal(focal_mm: float, sensor_width_mm: float) -> float:
    """Horizontal FoV (degrees) from the real focal length and the width of the sensor area the image covers.

    ``fov = 2 * atan(sensor_width / (2 * focal))``; e.g. 8.8 mm on a 13.2 mm wide sensor gives 73.7 degrees.
    """
    f, s = float(focal_mm), float(sensor_width_mm)
    if not (math.isfinite(f) and f > 0):
        raise ValueError(f"focal length must be a positive number of mm, got {focal_mm!r}")
    if not (math.isfinite(s) and s > 0):
        raise ValueError(f"sensor width must be a positive number of mm, got {sensor_width_mm!r}")
    return math.degrees(2.0 * math.atan(s / (2.0 * f)))


# --------------------------------------------------------------------------------------------------- CSV


def _csv_key(name: str) -> str:
    """The image stem a CSV ``name`` refers to: directories dropped, a known image extension stripped."""
    base = name.replace("\\", "/").rsplit("/", 1)[-1]
    stem, dot, suffix = base.rpartition(".")
    return stem if dot and stem and f".{suffix.lower()}" in CSV_NAME_SUFFIXES else base


_CSV_FIX = {
    "height": "write the camera's height above the ground in metres (> 0)",
    "pitch": "write the pitch in degrees (0 = horizontal, -90 = nadir)",
    "roll": "write the roll in degrees (positive = horizon's right end up)",
    "fov": "write the horizontal field of view in degrees (0 < fov < 180)",
}


def read_telemetry_csv(path: StrPath) -> dict[str, PoseTelemetry]:
    """Per-image telemetry from a CSV with header ``name,height_m,pitch_deg,roll_deg,fov_deg``, keyed by stem.

    ``name`` is the image's file name with or without its extension (``DJI_0001.JPG`` or ``DJI_0001``; a
    directory part is ignored). A missing value column or an empty cell means unknown. Columns may come in any
    order; other columns are ignored with a warning. Blank lines are skipped.

    Raises:
        TelemetryError: no ``name`` column (names the expected header); a value that is not a number or is
            physically impossible (height <= 0 or not finite, |pitch| > 180, |roll| > 180, fov outside
            (0, 180)), naming the file, line and column; an empty name; the same name twice with different
            values (naming both lines).
    """
    path = Path(path)
    header_hint = f"the first line must be the header `{','.join(CSV_COLUMNS)}` (value columns optional)"
    with path.open(newline="", encoding="utf-8-sig") as stream:
        reader = csv.reader(stream)
        header = next(reader, None)
        if header is None:
            raise TelemetryError(f"{path}: the file is empty; {header_hint}")
        columns = [c.strip().lower() for c in header]
        if "name" not in columns:
            hint = " (it looks ';'-separated: save it comma-separated)" if ";" in ",".join(header) else ""
            raise TelemetryError(f"{path}: no `name` column in the header {','.join(header)!r}{hint}; {header_hint}")
        for col in set(columns):
            if col and columns.count(col) > 1:
                raise TelemetryError(f"{path}: column `{col}` appears {columns.count(col)} times in the header; "
                                     "keep one")
        index = {c: i for i, c in enumerate(columns)}
        unknown = [c for c in columns if c and c not in CSV_COLUMNS]
        if unknown:
            warnings.warn(f"{path}: column(s) {', '.join(unknown)} ignored (the telemetry columns are "
                          f"{','.join(CSV_COLUMNS)})", TelemetryWarning, stacklevel=2)
        out: dict[str, PoseTelemetry] = {}
        first_line: dict[str, int] = {}
        for row in reader:
            line = reader.line_num
            cells = [c.strip() for c in row]
            if not any(cells):
                continue

            def cell(col: str, cells: list[str] = cells) -> str:
                i = index.get(col)
                return cells[i] if i is not None and i < len(cells) else ""

            name = cell("name")
            where = f"{path}, line {line}"
            if not name:
                raise TelemetryError(f"{where}: empty `name`; write the image's file name (with or without "
                                     "its extension), or delete the row")
            values: list[float] = []
            for key, col in zip(POSE_KEYS, _FIELDS):
                text = cell(col)
                if not text:
                    values.append(math.nan)
                    continue
                try:
                    value = float(text)
                except ValueError:
                    raise TelemetryError(f"{where}, column {col}: {text!r} is not a number; {_CSV_FIX[key]}, "
                                         "or leave the cell empty for unknown") from None
                if (why := _limit_error(key, value)) is not None:
                    raise TelemetryError(f"{where}, column {col}: {text} {why}; {_CSV_FIX[key]}, or leave the "
                                         "cell empty for unknown")
                values.append(value)
            key = _csv_key(name)
            telemetry = _telemetry(values, f"{path.name} line {line}")
            if key in out:
                previous = out[key]
                if not np.array_equal(previous.values(), telemetry.values(), equal_nan=True):
                    raise TelemetryError(f"{where}: `{name}` is already on line {first_line[key]} with different "
                                         f"values ({_show(previous)} there, {_show(telemetry)} here); keep one "
                                         "row per image")
                continue
            out[key], first_line[key] = telemetry, line
    return out


def _show(t: PoseTelemetry) -> str:
    return ", ".join(f"{k}={'' if math.isnan(v) else f'{v:g}'}" for k, v in zip(_FIELDS, t.values().tolist()))


# ------------------------------------------------------------------------------------------ image metadata

_XMP_HEIGHT, _XMP_PITCH, _XMP_ROLL = "RelativeAltitude", "GimbalPitchDegree", "GimbalRollDegree"
_EXIF_F35 = int(ExifTags.Base.FocalLengthIn35mmFilm)  # 0xA405
_EXIF_FOCAL = int(ExifTags.Base.FocalLength)  # 0x920A
_EXIF_IFD = int(ExifTags.IFD.Exif)  # 0x8769


def _local(tag: str) -> str:
    return tag.rsplit("}", 1)[-1]


def _xmp_fields(packet: bytes, path: Path, wanted: Iterable[str]) -> dict[str, str]:
    """The first value of each wanted local name, as an attribute or a child element of any XMP element."""
    data = packet.rstrip(b"\x00 \t\r\n")
    if b"<!DOCTYPE" in data or b"<!ENTITY" in data:
        raise TelemetryError(f"{path}: its XMP packet declares a DTD / entities, which XMP never does; refusing "
                             "to parse it (strip the XMP, or read without metadata: read_metadata=False)")
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise TelemetryError(f"{path}: its XMP packet is not well-formed XML ({exc}); repair or strip the XMP "
                             "(e.g. `exiftool -xmp= FILE`), or read without metadata (read_metadata=False)") from None
    wanted = set(wanted)
    found: dict[str, str] = {}
    for element in root.iter():
        for attr, value in element.attrib.items():
            name = _local(attr)
            if name in wanted and name not in found:
                found[name] = value.strip()
        name = _local(element.tag)
        if name in wanted and name not in found and element.text is not None and element.text.strip():
            found[name] = element.text.strip()
    return found


def _rational(value: Any) -> float:
    """An EXIF number (int, ``IFDRational`` or ``(num, den)``) as float; NaN when it is not one."""
    try:
        if isinstance(value, tuple) and len(value) == 2:
            return float(value[0]) / float(value[1]) if float(value[1]) else math.nan
        return float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return math.nan


def _image_telemetry(path: StrPath, sensor_width_mm: float | None) -> tuple[PoseTelemetry, dict[str, str]]:
    """Telemetry from one image's metadata, plus notes per pose key on values left unknown."""
    path = Path(path)
    if sensor_width_mm is not None and not (math.isfinite(sensor_width_mm) and sensor_width_mm > 0):
        raise ValueError(f"sensor_width_mm must be a positive number of mm, got {sensor_width_mm!r}")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such image file")
    notes: dict[str, str] = {}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)  # only the header is read
            with Image.open(path) as im:
                width, height = im.size
                packet: Any = im.info.get("xmp") or im.info.get("XML:com.adobe.xmp")
                if packet is None and hasattr(im, "tag_v2"):
                    packet = im.tag_v2.get(700)  # TIFF XMP tag
                try:
                    exif = im.getexif()
                    exif_ifd: Mapping[int, Any] = exif.get_ifd(_EXIF_IFD)
                    f35 = _rational(exif_ifd.get(_EXIF_F35, exif.get(_EXIF_F35)))
                    focal = _rational(exif_ifd.get(_EXIF_FOCAL, exif.get(_EXIF_FOCAL)))
                except Exception as exc:  # Pillow raises many kinds on a damaged EXIF block
                    raise TelemetryError(f"{path}: its EXIF block cannot be read ({type(exc).__name__}: {exc}); "
                                         "repair or strip it, or read without metadata (read_metadata=False)") from exc
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError):
        return PoseTelemetry(), notes  # not an image Pillow reads: no metadata (the image reader reports damage)

    values = dict.fromkeys(POSE_KEYS, math.nan)
    parts: list[str] = []
    if packet is not None:
        raw = packet.encode("utf-8") if isinstance(packet, str) else bytes(packet)
        xmp = _xmp_fields(raw, path, (_XMP_HEIGHT, _XMP_PITCH, _XMP_ROLL))
        for key, tag in (("height", _XMP_HEIGHT), ("pitch", _XMP_PITCH), ("roll", _XMP_ROLL)):
            if tag not in xmp:
                continue
            text = xmp[tag]
            try:
                value = float(text)
            except ValueError:
                raise TelemetryError(f"{path}: XMP drone-dji:{tag} = {text!r} is not a number; repair the tag, "
                                     "or give the value in a telemetry CSV and read without metadata "
                                     "(read_metadata=False)") from None
            if key == "height" and math.isfinite(value) and value <= 0:
                notes["height"] = (f"XMP drone-dji:{tag} = {text} m <= 0 (on the ground or below the take-off "
                                   "point), height left unknown")
                continue
            if (why := _limit_error(key, value)) is not None:
                raise TelemetryError(f"{path}: XMP drone-dji:{tag} = {text} {why}; repair the tag, or give the "
                                     "value in a telemetry CSV and read without metadata (read_metadata=False)")
            values[key] = value
        if any(not math.isnan(values[k]) for k in ("height", "pitch", "roll")):
            parts.append("XMP")
    if sensor_width_mm is not None and math.isfinite(focal) and focal > 0:
        values["fov"] = horizontal_fov_from_focal(focal, sensor_width_mm)
    elif math.isfinite(f35) and f35 > 0:  # 0 means "unknown" in Exif
        values["fov"] = horizontal_fov_from_focal_35mm(f35, width, height)
    if not math.isnan(values["fov"]):
        parts.append("EXIF")
    source = f"{path.name} {'/'.join(parts)}" if parts else ""
    return _telemetry([values[k] for k in POSE_KEYS], source), notes


def _warn_notes(notes: Mapping[str, Mapping[str, str]], stacklevel: int) -> None:
    if not notes:
        return
    shown = [f"{name}: {'; '.join(n.values())}" for name, n in list(notes.items())[:_SHOW_NAMES]]
    more = f" (and {len(notes) - _SHOW_NAMES} more)" if len(notes) > _SHOW_NAMES else ""
    warnings.warn(f"telemetry: {len(notes)} image(s) with metadata left unknown: {' | '.join(shown)}{more}",
                  TelemetryWarning, stacklevel=stacklevel + 1)


def telemetry_from_image(path: StrPath, sensor_width_mm: float | None = None) -> PoseTelemetry:
    """Telemetry from an image's own metadata: DJI XMP for height, pitch, roll; EXIF focal length for the FoV.

    - height: ``drone-dji:RelativeAltitude`` (metres above the take-off point: the height above the ground
      only where the ground is level with the take-off point); <= 0 is left unknown with a warning.
    - pitch, roll: ``drone-dji:GimbalPitchDegree`` / ``GimbalRollDegree``, the gimbal's attitude relative to
      the horizon; DJI's conventions equal the project's (pitch -90 = nadir; roll positive = right side down
      = clockwise seen from behind), so the values are taken as they are.
    - fov: from EXIF ``FocalLength`` (0x920A) and ``sensor_width_mm`` when both are there (the width of the
      sensor area the stored image covers), else from ``FocalLengthIn35mmFilm`` (0xA405) and the stored
      pixel size (:func:`horizontal_fov_from_focal_35mm`). The EXIF Orientation tag is not applied (the
      predict reader does not rotate either).

    The XMP tags may be attributes or child elements of ``rdf:Description``. A file Pillow cannot open or
    without metadata gives all-unknown telemetry.

    Raises:
        FileNotFoundError: no such file.
        TelemetryError: a tag that is there but is not a number or is impossible, a damaged XMP / EXIF block.
    """
    telemetry, notes = _image_telemetry(path, sensor_width_mm)
    _warn_notes({Path(path).name: notes} if notes else {}, stacklevel=2)
    return telemetry


def telemetry_for_images(paths: Iterable[StrPath], csv_path: StrPath | None = None, *, read_metadata: bool = True,
                         sensor_width_mm: float | None = None) -> list[PoseTelemetry]:
    """Telemetry for each image: its CSV row, each unknown component falling back to the image's metadata.

    A CSV row matches an image when its ``name``, with or without extension, equals the image's file name
    or stem (case-sensitive). CSV names that match no image give one :class:`TelemetryWarning` naming the
    CSV, their count and the first few. ``read_metadata=False`` reads no image metadata (CSV only).

    Raises:
        TelemetryError: see :func:`read_telemetry_csv` and :func:`telemetry_from_image`.
    """
    image_paths = [Path(p) for p in paths]
    rows = read_telemetry_csv(csv_path) if csv_path is not None else {}
    out: list[PoseTelemetry] = []
    notes: dict[str, dict[str, str]] = {}
    for p in image_paths:
        row = rows.get(p.stem, PoseTelemetry())
        meta = PoseTelemetry()
        if read_metadata and not all(row.known()):
            meta, image_notes = _image_telemetry(p, sensor_width_mm)
            used = {k: v for k, v in image_notes.items() if not row.known()[POSE_KEYS.index(k)]}
            if used:
                notes[p.name] = used
        out.append(row.merged(meta))
    if csv_path is not None:
        stems = {p.stem for p in image_paths}
        unmatched = [k for k in rows if k not in stems]
        if unmatched:
            shown = ", ".join(unmatched[:_SHOW_NAMES]) + (f" (and {len(unmatched) - _SHOW_NAMES} more)"
                                                          if len(unmatched) > _SHOW_NAMES else "")
            warnings.warn(f"{csv_path}: {len(unmatched)} of {len(rows)} name(s) match no image: {shown}; names "
                          "are matched by file name with or without extension (case-sensitive), those rows are "
                          "unused", TelemetryWarning, stacklevel=2)
    _warn_notes(notes, stacklevel=2)
    return out


# --------------------------------------------------------------------------------------------------- SRT

_SRT_TIME = re.compile(r"^\s*(\d+):(\d+):(\d+)[,.](\d+)\s*-->\s*(\d+):(\d+):(\d+)[,.](\d+)")
_SRT_PAIR = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)\s*:\s*([^\s\[\]]+)")
_SRT_TAG = re.compile(r"<[^>]*>")


def _srt_seconds(groups: tuple[str, ...]) -> float:
    h, m, s, frac = groups
    return float(int(h) * 3600 + int(m) * 60 + int(s)) + int(frac) / 10.0 ** len(frac)


def read_srt(path: StrPath, width: int | None = None, height: int | None = None) -> dict[int, PoseTelemetry]:
    """Per-frame telemetry from a DJI video's subtitle file: ``{frame index (0-based): PoseTelemetry}``.

    Subtitle ``k`` (1-based, one per video frame) is frame ``k - 1``. Fields read, each unknown when absent:
    height from ``rel_alt`` (metres above the take-off point), else ``altitude`` (read the same way, with a
    warning: check that your model writes the relative altitude there); pitch and roll from ``gb_pitch`` and
    ``gb_roll`` (DJI's gimbal conventions equal the project's); FoV from ``focal_len``, the 35-mm-equivalent
    focal length, when the video's ``width`` and ``height`` are given. ``focal_len`` written as an integer
    is tenths of a millimetre when the block's ``fnum`` is an integer too (hundredths; Air 2S / Mini
    style: ``focal_len: 240``, ``fnum: 280`` = 24 mm, f/2.8); an integer ``focal_len`` without that
    evidence is ambiguous and is left unknown with a warning. A height <= 0 (on the ground) is left unknown
    (one warning per file).

    Raises:
        TelemetryError: a malformed block (no subtitle number, no timing line), a subtitle number twice,
            a field that is not a number or is impossible (naming the file, subtitle number and field), or
            a subtitle longer than 0.5 s that carries a field read here (a per-second SRT: not per frame).
    """
    path = Path(path)
    if (width is None) != (height is None):
        raise ValueError("read_srt: give both width and height of the video (or neither)")
    if width is not None and height is not None and not (width > 0 and height > 0):
        raise ValueError(f"read_srt: width and height must be positive, got {width} x {height}")
    text = path.read_text(encoding="utf-8-sig", errors="replace").replace("\r\n", "\n").replace("\r", "\n")
    lines = text.split("\n")
    blocks: list[tuple[int, list[str]]] = []  # (first line number, lines)
    current: list[str] = []
    start = 0
    for lineno, line in enumerate(lines, 1):
        if line.strip():
            if not current:
                start = lineno
            current.append(line)
        elif current:
            blocks.append((start, current))
            current = []
    if current:
        blocks.append((start, current))

    out: dict[int, PoseTelemetry] = {}
    on_ground = used_altitude = ambiguous_focal = 0
    for start, block in blocks:
        head = block[0].strip()
        if not head.isdigit() or int(head) < 1:
            raise TelemetryError(f"{path}, line {start}: expected a subtitle number (1, 2, ...), found {head!r}; "
                                 "the file is not an SRT or is damaged")
        k = int(head)
        where = f"{path}, subtitle {k} (line {start})"
        timing = _SRT_TIME.match(block[1]) if len(block) > 1 else None
        if timing is None:
            raise TelemetryError(f"{where}: expected a timing line `00:00:00,000 --> 00:00:00,033`; the file is "
                                 "damaged")
        if k - 1 in out:
            raise TelemetryError(f"{where}: subtitle number {k} appears twice; the file is damaged")
        duration = _srt_seconds(timing.groups()[4:]) - _srt_seconds(timing.groups()[:4])
        fields_: dict[str, str] = {}
        for key, value in _SRT_PAIR.findall(_SRT_TAG.sub(" ", " ".join(block[2:]))):
            fields_.setdefault(key.lower(), value)

        def number(field: str, fields_: dict[str, str] = fields_, where: str = where) -> float:
            raw = fields_[field]
            try:
                value = float(raw)
            except ValueError:
                raise TelemetryError(f"{where}: `{field}` = {raw!r} is not a number; correct or delete it (a "
                                     "missing field is read as unknown)") from None
            if not math.isfinite(value):
                raise TelemetryError(f"{where}: `{field}` = {raw!r} is not finite; correct or delete it")
            return value

        values = dict.fromkeys(POSE_KEYS, math.nan)
        height_field = "rel_alt" if "rel_alt" in fields_ else "altitude" if "altitude" in fields_ else None
        if height_field is not None:
            h = number(height_field)
            used_altitude += height_field == "altitude"
            if h > 0:
                values["height"] = h
            else:
                on_ground += 1
        for key, field in (("pitch", "gb_pitch"), ("roll", "gb_roll")):
            if field in fields_:
                value = number(field)
                if (why := _limit_error(key, value)) is not None:
                    raise TelemetryError(f"{where}: `{field}` = {fields_[field]} {why}; correct or delete it")
                values[key] = value
        if "focal_len" in fields_:
            raw, f35 = fields_["focal_len"], number("focal_len")
            if "." not in raw:
                fnum = fields_.get("fnum", "")
                if fnum.isdigit() and int(fnum) >= 100:
                    f35 /= 10.0  # fixed-point format: focal_len in 0.1 mm, fnum in 0.01
                else:
                    ambiguous_focal += 1
                    f35 = math.nan
            if width is not None and height is not None and f35 > 0:
                values["fov"] = horizontal_fov_from_focal_35mm(f35, width, height)
        if duration > _SRT_MAX_SUBTITLE_S and not all(math.isnan(v) for v in values.values()):
            raise TelemetryError(f"{where}: the subtitle lasts {duration:.3f} s; this SRT holds one subtitle per "
                                 "time span, not one per video frame, so subtitles cannot be matched to frames; "
                                 "give per-frame telemetry in a CSV instead")
        known = not all(math.isnan(v) for v in values.values())
        out[k - 1] = _telemetry([values[key] for key in POSE_KEYS], f"{path.name} frame {k - 1}" if known else "")

    notes = []
    if on_ground:
        notes.append(f"{on_ground} subtitle(s) with a height <= 0 (on the ground or below the take-off point): "
                     "height left unknown there")
    if used_altitude:
        notes.append(f"{used_altitude} subtitle(s) give `altitude` (no `rel_alt`): read as metres above the "
                     "take-off point; if your model writes the altitude above sea level there, give heights "
                     "in a CSV instead")
    if ambiguous_focal:
        notes.append(f"{ambiguous_focal} subtitle(s) give `focal_len` as an integer without an integer `fnum`: "
                     "mm or tenths of mm cannot be told apart, FoV left unknown there")
    if notes:
        warnings.warn(f"{path}: " + "; ".join(notes), TelemetryWarning, stacklevel=2)
    return out
