"""Telemetry from an image's own metadata: DJI XMP for height, pitch, roll; EXIF focal length for the FoV.

The fields and their meanings are rows of :data:`~dapm_lightning.inference.telemetry.fields.FIELD_MEANINGS`: the
relative altitude (never the absolute one), the gimbal's pitch and roll (never the aircraft's), the focal length.
The XMP packet is read by :mod:`~dapm_lightning.inference.telemetry.xmp` (decoded as declared, DTDs refused).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from PIL import ExifTags, Image, UnidentifiedImageError

from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.inference.telemetry.pose import (
    MIN_HEIGHT_M,
    PoseTelemetry,
    StrPath,
    TelemetryError,
    TelemetryWarning,
    horizontal_fov_from_focal,
    horizontal_fov_from_focal_35mm,
    is_equirectangular,
    limit_error,
)
from dapm_lightning.inference.telemetry.xmp import local_name, namespace, parse_xmp, qualified

SHOW_NAMES = 5
"""Names shown in a warning before ``(and N more)``."""

XMP_FIX = ("repair or strip the XMP (`exiftool -xmp= FILE`), give the pose in a --telemetry CSV, or read no image "
           "metadata (--no_metadata; read_metadata=False in Python)")
"""How to get past a bad XMP packet, in the command line's terms and the Python API's."""

XMP_POSE_TAGS = {"RelativeAltitude": "height", "GimbalPitchDegree": "pitch", "GimbalRollDegree": "roll"}
"""The DJI XMP tags read, by local name, and the component each gives (``fields.py``: their meanings)."""
_DJI_NAMESPACE = "http://www.dji.com"  # drone-dji: http://www.dji.com/drone-dji/1.0/; Zenmuse XT S: http://www.dji.com
_REVERSED = ("GimbalReverse", "CamReverse")
_GPANO = "http://ns.google.com/photos/1.0/panorama/"
_EXIF_F35 = int(ExifTags.Base.FocalLengthIn35mmFilm)  # 0xA405
_EXIF_FOCAL = int(ExifTags.Base.FocalLength)  # 0x920A
_EXIF_IFD = int(ExifTags.IFD.Exif)  # 0x8769


def _xmp_fields(packet: bytes, where: str) -> tuple[dict[str, tuple[str, str]], bool]:
    """``{local name: (name as written, value)}`` of the DJI tags read here, and whether the packet says 360-degree.

    The first value of each tag, as an attribute or a child element's text, in a DJI namespace only.
    """
    try:
        root, namespaces = parse_xmp(packet, where)
    except TelemetryError as exc:
        raise TelemetryError(f"{exc}; {XMP_FIX}") from None
    wanted = {*XMP_POSE_TAGS, *_REVERSED}
    found: dict[str, tuple[str, str]] = {}
    spherical = False

    def take(name: str, value: str | None) -> None:
        nonlocal spherical
        local = local_name(name)
        if namespace(name) == _GPANO and local == "ProjectionType":
            spherical = spherical or (value or "").strip().lower() == "equirectangular"
        elif (local in wanted and local not in found and value is not None and value.strip()
              and namespace(name).startswith(_DJI_NAMESPACE)):
            found[local] = (qualified(name, namespaces), value.strip())

    for element in root.iter():
        for attr, value in element.attrib.items():
            take(attr, value)
        take(element.tag, element.text)
    return found, spherical


def _rational(value: Any) -> float:
    """An EXIF number (int, ``IFDRational`` or ``(num, den)``) as float; NaN when it is not one."""
    try:
        if isinstance(value, tuple) and len(value) == 2:
            return float(value[0]) / float(value[1]) if float(value[1]) else math.nan
        return float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return math.nan


def _pixels_undecodable(path: Path) -> bool:
    """Whether Pillow cannot decode the image itself (cut short, damaged).

    Pillow reads a PNG's EXIF (which may follow the pixels) by decoding the image, so a PNG cut short fails there
    with ``image file is truncated``: that is the file's damage, which the image reader reports with its fix
    (replace it with an intact copy), not a broken EXIF block to strip.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as im:
                im.load()
    except Exception:  # noqa: BLE001 - any failure to decode is the image's own
        return True
    return False


def _read_header(path: Path) -> tuple[int, int, Any, float, float] | None:
    """``(width, height, XMP packet or None, f35, focal)`` from the file's header; None when Pillow cannot open it."""
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
                    if _pixels_undecodable(path):  # a PNG's EXIF is read by decoding it: the file, not its EXIF
                        return None
                    raise TelemetryError(f"{path}: its EXIF block cannot be read ({type(exc).__name__}: {exc}); "
                                         "repair or strip it, give the pose in a --telemetry CSV, or read no image "
                                         "metadata (--no_metadata; read_metadata=False in Python)") from exc
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError):
        return None  # not an image Pillow reads: no metadata (the image reader reports damage)
    except TelemetryError:
        raise
    except Exception as exc:  # metadata Pillow refuses while opening (a PNG text chunk over MAX_TEXT_CHUNK, ...)
        raise TelemetryError(f"{path}: its metadata cannot be read ({type(exc).__name__}: {exc}); strip it "
                             "(`exiftool -all= FILE`), give the pose in a --telemetry CSV, or read no image metadata "
                             "(--no_metadata; read_metadata=False in Python)") from exc
    return width, height, packet, f35, focal


def image_telemetry(path: StrPath, sensor_width_mm: float | None) -> tuple[PoseTelemetry, dict[str, str]]:
    """Telemetry from one image's metadata, plus notes per pose key on values left unknown (for one warning).

    Raises:
        FileNotFoundError: no such file. ValueError: a sensor width that is not a positive number.
        TelemetryError: a DJI tag that is there but is not a number or is impossible, an EXIF focal length giving an
            impossible FoV; a damaged XMP / EXIF block,
            metadata Pillow refuses to open (a PNG text chunk inflating past 1 MiB).
    """
    path = Path(path)
    if sensor_width_mm is not None and not (math.isfinite(sensor_width_mm) and sensor_width_mm > 0):
        raise ValueError(f"sensor_width_mm must be a positive number of mm, got {sensor_width_mm!r}")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such image file")
    header = _read_header(path)
    notes: dict[str, str] = {}
    if header is None:
        return PoseTelemetry(), notes
    width, height, packet, f35, focal = header
    values = dict.fromkeys(POSE_KEYS, math.nan)
    provenance = dict.fromkeys(POSE_KEYS, "")
    spherical = is_equirectangular(width, height)
    parts: list[str] = []
    if packet is not None:
        raw = packet.encode("utf-8") if isinstance(packet, str) else bytes(packet)
        xmp, spherical_xmp = _xmp_fields(raw, str(path))
        spherical = spherical or spherical_xmp
        reversed_by = [xmp[tag][0] for tag in _REVERSED if tag in xmp and xmp[tag][1] not in ("0", "false", "False")]
        for tag, key in XMP_POSE_TAGS.items():
            if tag not in xmp:
                continue
            written, text = xmp[tag]
            if key != "height" and reversed_by:
                notes[key] = f"{written} with {reversed_by[0]} = 1 (gimbal upside down): {key} left unknown"
                continue
            try:
                value = float(text)
            except ValueError:
                raise TelemetryError(f"{path}: XMP {written} = {text!r} is not a number; {XMP_FIX}") from None
            if key == "height" and math.isfinite(value) and value < MIN_HEIGHT_M:
                notes["height"] = (f"XMP {written} = {text} m: below {MIN_HEIGHT_M:g} m (on the ground, or below the "
                                   "take-off point), height left unknown")
                continue
            if (why := limit_error(key, value)) is not None:
                raise TelemetryError(f"{path}: XMP {written} = {text} {why}; {XMP_FIX}")
            values[key], provenance[key] = value, f"{path.name} XMP {written}"
        if any(provenance.values()):
            parts.append("XMP")
    fov, fov_from = math.nan, ""
    if sensor_width_mm is not None and math.isfinite(focal) and focal > 0:
        fov = horizontal_fov_from_focal(focal, sensor_width_mm)
        fov_from = f"FocalLength (sensor {sensor_width_mm:g} mm)"
    elif math.isfinite(f35) and f35 > 0:  # 0 means "unknown" in Exif
        fov, fov_from = horizontal_fov_from_focal_35mm(f35, width, height), "FocalLengthIn35mmFilm"
    if fov_from and spherical:
        notes["fov"] = f"a 360-degree (equirectangular, {width}x{height}) image: no pinhole FoV, fov left unknown"
    elif fov_from:
        if (why := limit_error("fov", fov)) is not None:  # a focal length of 1e-300 mm in a damaged EXIF block
            focal_mm = focal if fov_from.startswith("FocalLength ") else f35
            raise TelemetryError(f"{path}: EXIF {fov_from.split(' ')[0]} = {focal_mm!r} mm gives a FoV that {why}; "
                                 "repair or strip the EXIF block, give the pose in a --telemetry CSV, or read no image "
                                 "metadata (--no_metadata; read_metadata=False in Python)")
        values["fov"], provenance["fov"] = fov, f"{path.name} EXIF {fov_from}"
        parts.append("EXIF")
    source = f"{path.name} {'/'.join(parts)}" if parts else ""
    return PoseTelemetry.from_values([values[k] for k in POSE_KEYS], source, [provenance[k] for k in POSE_KEYS]), notes


def warn_notes(notes: Mapping[str, Mapping[str, str]], stacklevel: int) -> None:
    """One warning for all images with metadata left unknown (``{image name: {pose key: why}}``)."""
    if not notes:
        return
    shown = [f"{name}: {'; '.join(n.values())}" for name, n in list(notes.items())[:SHOW_NAMES]]
    more = f" (and {len(notes) - SHOW_NAMES} more)" if len(notes) > SHOW_NAMES else ""
    warnings.warn(f"telemetry: {len(notes)} image(s) with metadata left unknown: {' | '.join(shown)}{more}",
                  TelemetryWarning, stacklevel=stacklevel + 1)


def telemetry_from_image(path: StrPath, sensor_width_mm: float | None = None) -> PoseTelemetry:
    """Telemetry from an image's own metadata: DJI XMP for height, pitch, roll; EXIF focal length for the FoV.

    - height: ``drone-dji:RelativeAltitude`` (metres above the take-off point: the height above the ground
      only where the ground is level with the take-off point); below 1 m (on the ground) it is left unknown with a
      warning. ``AbsoluteAltitude`` (above sea level) is never read.
    - pitch, roll: ``drone-dji:GimbalPitchDegree`` / ``GimbalRollDegree``, the gimbal's attitude relative to
      the horizon; DJI's conventions equal the project's (pitch -90 = nadir; roll positive = right side down
      = clockwise seen from behind), so the values are taken as they are. The aircraft's ``Flight*Degree`` are
      never read; with ``GimbalReverse`` / ``CamReverse`` = 1 (upside down) pitch and roll are left unknown.
    - fov: from EXIF ``FocalLength`` (0x920A) and ``sensor_width_mm`` when both are there (the width of the
      sensor area the stored image covers), else from ``FocalLengthIn35mmFilm`` (0xA405) and the stored
      pixel size (:func:`horizontal_fov_from_focal_35mm`). The EXIF Orientation tag is not applied (the
      predict reader does not rotate either). A 360-degree image (2:1, or ``GPano:ProjectionType`` =
      equirectangular) has no pinhole FoV: unknown, with a warning.

    The DJI tags may be attributes or child elements, in the ``drone-dji:`` namespace or Zenmuse XT S's ``DJI:``.
    Each known component's ``provenance`` names the image and the tag (``DJI_0001.JPG XMP
    drone-dji:RelativeAltitude``). A file Pillow cannot open or without metadata gives all-unknown telemetry.

    Raises:
        FileNotFoundError: no such file.
        TelemetryError: a tag that is there but is not a number or is impossible, a damaged XMP / EXIF block,
            metadata Pillow refuses to open (a PNG text chunk inflating past 1 MiB).
    """
    telemetry, notes = image_telemetry(path, sensor_width_mm)
    warn_notes({Path(path).name: notes} if notes else {}, stacklevel=2)
    return telemetry
