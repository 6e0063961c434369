"""Telemetry from an image's own metadata (DJI XMP, EXIF focal length), and combined with a CSV per image."""

from __future__ import annotations

import math
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from PIL import ExifTags, Image, UnidentifiedImageError

from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.inference.telemetry.csv_file import read_telemetry_csv
from dapm_lightning.inference.telemetry.pose import (
    PoseTelemetry,
    StrPath,
    TelemetryError,
    TelemetryWarning,
    horizontal_fov_from_focal,
    horizontal_fov_from_focal_35mm,
    limit_error,
)

_SHOW_NAMES = 5
"""Names shown in a warning before ``(and N more)``."""

_XMP_HEIGHT, _XMP_PITCH, _XMP_ROLL = "RelativeAltitude", "GimbalPitchDegree", "GimbalRollDegree"
_EXIF_F35 = int(ExifTags.Base.FocalLengthIn35mmFilm)  # 0xA405
_EXIF_FOCAL = int(ExifTags.Base.FocalLength)  # 0x920A
_EXIF_IFD = int(ExifTags.IFD.Exif)  # 0x8769


def _local(tag: str) -> str:
    """An XML name without its ``{namespace}``: ``drone-dji:RelativeAltitude`` -> ``RelativeAltitude``."""
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
            if (why := limit_error(key, value)) is not None:
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
    return PoseTelemetry.from_values([values[k] for k in POSE_KEYS], source), notes


def _warn_notes(notes: Mapping[str, Mapping[str, str]], stacklevel: int) -> None:
    """One warning for all images with metadata left unknown (``{image name: {pose key: why}}``)."""
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
