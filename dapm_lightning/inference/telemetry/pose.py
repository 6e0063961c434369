"""What every telemetry reader produces: :class:`PoseTelemetry`, its limits, its errors and the FoV maths."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from os import PathLike
from typing import Any

import numpy as np
import numpy.typing as npt

from dapm_lightning.geometry.constants import POSE_FIELDS, POSE_KEYS
from dapm_lightning.geometry.pose import impossible_pose_value

StrPath = str | PathLike[str]
Provenance = tuple[str, str, str, str]
"""Per pose component (``POSE_KEYS`` order), where its value came from (``""`` where unknown)."""
NO_PROVENANCE: Provenance = ("", "", "", "")

FULL_FRAME_DIAGONAL_MM: float = math.hypot(36.0, 24.0)
"""43.27 mm: the diagonal of a 36 x 24 mm frame, to which a 35-mm-equivalent focal length refers."""

MIN_HEIGHT_M = 1.0
"""A drone's relative altitude below this is read as "on the ground": its barometer measures the height above the
take-off point to about +-0.5 m (up to 2 m in gusts), so a smaller value cannot be told from a drone standing there
(the Neo 2's SRT reads 0.100 m on the ground). Telemetry readers leave such heights unknown, with a warning."""

EQUIRECTANGULAR_ASPECT = 2.0
"""Width / height of a 360-degree equirectangular image (Avata 360, panoramas): no pinhole FoV applies to it."""


class TelemetryError(ValueError):
    """Telemetry that is there but unusable: the message names the file, the row / frame / tag and the fix."""


class TelemetryWarning(UserWarning):
    """Telemetry ignored or left unknown (names in a CSV that match no image, a relative altitude <= 0, ...)."""


def limit_error(key: str, value: float) -> str | None:
    """Why ``value`` is impossible for pose component ``key`` (``None`` when it is possible).

    :func:`~dapm_lightning.geometry.pose.impossible_pose_value`: the limits UAPD file names are held to too.
    """
    return impossible_pose_value(key, value)


def is_equirectangular(width: float, height: float) -> bool:
    """Whether a ``width`` x ``height`` image has the 2:1 shape of a 360-degree equirectangular image (within 1 %)."""
    return height > 0 and abs(width / height - EQUIRECTANGULAR_ASPECT) <= 0.01 * EQUIRECTANGULAR_ASPECT


@dataclass(frozen=True, eq=False, slots=True)
class PoseTelemetry:
    """A pose prior from telemetry in the project's conventions (docs/conventions.md); NaN = unknown.

    Args:
        height_m: metres above the ground under the camera. pitch_deg: 0 = horizontal, -90 = nadir.
        roll_deg: positive = camera turned clockwise seen from behind (horizon's right end up).
        fov_deg: horizontal field of view across the image width. source: where the known values came
            from (``"flight.csv line 4"``, ``"DJI_0001.JPG XMP/EXIF"``, ``"DJI_0002.SRT subtitle 13"``).
        provenance: per component, the file and the place in it its value was read from
            (``"flight.csv line 12"``, ``"DJI_0001.JPG XMP drone-dji:RelativeAltitude"``,
            ``"DJI_0005.SRT subtitle 215 rel_alt"``); by default ``source`` for each known component.

    Raises:
        ValueError: a known value that is physically impossible (height <= 0, |pitch| or |roll| > 180,
            fov outside (0, 180), or infinite).
    """

    height_m: float = math.nan
    pitch_deg: float = math.nan
    roll_deg: float = math.nan
    fov_deg: float = math.nan
    source: str = ""
    provenance: Provenance = NO_PROVENANCE

    def __post_init__(self) -> None:
        for key, name in zip(POSE_KEYS, POSE_FIELDS):
            value = float(getattr(self, name))
            object.__setattr__(self, name, value)
            if not math.isnan(value) and (why := limit_error(key, value)) is not None:
                raise ValueError(f"PoseTelemetry{f' ({self.source})' if self.source else ''}: {name} = {value!r} "
                                 f"{why}; use NaN for unknown")
        given = tuple(self.provenance)
        if len(given) != len(POSE_KEYS):
            raise ValueError(f"PoseTelemetry: provenance needs one entry per component {POSE_KEYS}, got {given!r}")
        default = self.source if not any(given) else ""
        object.__setattr__(self, "provenance", tuple(
            (str(p) or default) if known else "" for p, known in zip(given, self.known())))

    @classmethod
    def from_values(cls, values: Sequence[float], source: str,
                    provenance: Sequence[str] | None = None) -> PoseTelemetry:
        """A :class:`PoseTelemetry` from 4 values in ``POSE_KEYS`` order (height, pitch, roll, fov).

        ``provenance``: per component where it came from; None: ``source`` for each known component.
        """
        h, p, r, f = values
        prov = NO_PROVENANCE if provenance is None else tuple(provenance)
        return cls(height_m=h, pitch_deg=p, roll_deg=r, fov_deg=f, source=source,
                   provenance=prov)  # type: ignore[arg-type]

    def values(self) -> npt.NDArray[np.float64]:
        """``[4]`` float64 in ``POSE_KEYS`` order (height, pitch, roll, fov); NaN where unknown."""
        return np.array([self.height_m, self.pitch_deg, self.roll_deg, self.fov_deg], dtype=np.float64)

    def known(self) -> tuple[bool, bool, bool, bool]:
        """Which components are known, in ``POSE_KEYS`` order."""
        h, p, r, f = (not math.isnan(v) for v in (self.height_m, self.pitch_deg, self.roll_deg, self.fov_deg))
        return h, p, r, f

    def provenance_dict(self) -> dict[str, str]:
        """``{pose key: where its value came from}`` for the known components."""
        return {key: where for key, where, known in zip(POSE_KEYS, self.provenance, self.known()) if known}

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
        provenance = [a if o else b for a, b, o in zip(self.provenance, fallback.provenance, own)]
        return PoseTelemetry.from_values(values, source, provenance)

    def _key(self) -> tuple[Any, ...]:
        return (*(None if math.isnan(v) else v for v in self.values().tolist()), self.source, self.provenance)

    def __eq__(self, other: object) -> bool:
        """Equal when the same components are known with the same values (NaN equals NaN) and the same source."""
        if not isinstance(other, PoseTelemetry):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __repr__(self) -> str:
        parts = [f"{name}={getattr(self, name)!r}" for name in POSE_FIELDS if not math.isnan(getattr(self, name))]
        parts.append(f"source={self.source!r}")
        if self.provenance != NO_PROVENANCE and set(self.provenance) - {"", self.source}:
            parts.append(f"provenance={self.provenance!r}")
        return f"PoseTelemetry({', '.join(parts)})"


# --------------------------------------------------------------------------------------------------- FoV


CROP_SENSOR_ASPECT: float = 4.0 / 3.0
"""The sensor a frame wider than 3:2 is taken to be cut from when :func:`horizontal_fov_from_focal_35mm` is not told
the sensor's aspect: 4:3, DJI's Mini, Air, Mavic 3 and Mavic Pro lines (the Phantom 4 Pro, Mavic 2 Pro and Air 2S
have 3:2 sensors)."""
WIDEST_SENSOR_ASPECT: float = 1.5
"""Frames at most this wide (4:3, 3:2, a thermal camera's 5:4) are taken to fill their sensor; wider ones (16:9
video) to be crops, when the sensor's aspect is not known."""


def horizontal_fov_from_focal_35mm(f35_mm: float, width: int, height: int,
                                   sensor_aspect: float | None = None) -> float:
    """Horizontal FoV (degrees) of a ``width`` x ``height`` image from its 35-mm-equivalent focal length.

    The 35 mm equivalent is that of the whole sensor: its diagonal is equated with a 36 x 24 mm frame's 43.27 mm
    (CIPA / Exif practice), and DJI quotes the same focal length for every frame it cuts from it (``focal_len: 24``
    in a 4K video's SRT, 24 in its photos' EXIF). An image of the sensor's aspect covers it whole, so its width is
    ``43.27 * W / sqrt(W^2 + H^2)`` mm and ``fov = 2 * atan(that / (2 * f35))``: exactly 36 mm on 3:2; 24 mm on a
    4000 x 3000 image gives 2 * atan(34.62 / 48) = 71.6 degrees. A frame wider than the sensor spans its width
    (``43.27 * a / sqrt(a^2 + 1)`` mm for aspect ``a``), a narrower one its height.

    ``sensor_aspect``: the sensor's width over its height (long side over short side), when known. Without it, an
    image at most 3:2 wide (4:3, 3:2, 5:4) is taken to fill its sensor and a wider one (16:9 video, a 16:9 photo
    mode) to be cut from the full width of a :data:`CROP_SENSOR_ASPECT` (4:3) sensor: 3840 x 2160 at 24 mm is
    71.6 degrees wide, as the photos are (taking the 16:9 frame's own diagonal for 43.27 mm gave 76.3).
    """
    f35, w, h = float(f35_mm), float(width), float(height)
    if not (math.isfinite(f35) and f35 > 0):
        raise ValueError(f"35-mm-equivalent focal length must be a positive number of mm, got {f35_mm!r}")
    if not (math.isfinite(w) and math.isfinite(h) and w > 0 and h > 0):
        raise ValueError(f"image size must be positive, got width={width!r} height={height!r}")
    long_side, short_side = max(w, h), min(w, h)
    frame = long_side / short_side
    if sensor_aspect is None:
        if frame <= WIDEST_SENSOR_ASPECT + 1e-3:  # the whole sensor (3:2 written as 5472 x 3648)
            return math.degrees(2.0 * math.atan(FULL_FRAME_DIAGONAL_MM * w / math.hypot(w, h) / (2.0 * f35)))
        sensor = CROP_SENSOR_ASPECT
    else:
        sensor = float(sensor_aspect)
        if not (math.isfinite(sensor) and 1.0 <= sensor <= 3.0):
            raise ValueError(f"sensor_aspect must be the sensor's long side over its short side, from 1 to 3 "
                             f"(4:3 = 1.333), got {sensor_aspect!r}")
    sensor_long = FULL_FRAME_DIAGONAL_MM * sensor / math.hypot(sensor, 1.0)
    long_mm = sensor_long if frame >= sensor else sensor_long / sensor * frame  # its width, or cut to its height
    return math.degrees(2.0 * math.atan(long_mm * (w / long_side) / (2.0 * f35)))


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
