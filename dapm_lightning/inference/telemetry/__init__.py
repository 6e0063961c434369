"""Drone telemetry (flight metadata) in the project's pose conventions, per image, as a pose prior.

Three sources, each read into :class:`PoseTelemetry` (``pose.py``: height m, pitch deg, roll deg, horizontal
FoV deg; NaN = unknown), with the conventions of ``docs/conventions.md`` ("Telemetry"):

- a CSV the user writes (``csv_file.py``, :func:`read_telemetry_csv`): ``name,height_m,pitch_deg,roll_deg,fov_deg``;
- the image's own metadata (``image_metadata.py``, :func:`telemetry_from_image`): DJI XMP
  (``drone-dji:RelativeAltitude``, ``GimbalPitchDegree``, ``GimbalRollDegree``) and EXIF focal length, read
  with Pillow;
- DJI video subtitles (``srt.py``, :func:`read_srt`): one subtitle per video frame.

:func:`telemetry_for_images` (``image_metadata.py``) combines a CSV with the images' metadata, component by
component.

Policy: a missing value is unknown (NaN); a value that is there but is not a number, or is physically
impossible, is an error (:class:`TelemetryError`, naming the file, the row / subtitle / tag and the fix).
A value that is a number but cannot be a height above the ground (a relative altitude <= 0: the
drone was on the ground or below its take-off point) is left unknown with a warning.
"""

from dapm_lightning.inference.telemetry.csv_file import CSV_COLUMNS, read_telemetry_csv
from dapm_lightning.inference.telemetry.image_metadata import telemetry_for_images, telemetry_from_image
from dapm_lightning.inference.telemetry.pose import (
    FULL_FRAME_DIAGONAL_MM,
    PoseTelemetry,
    TelemetryError,
    TelemetryWarning,
    horizontal_fov_from_focal,
    horizontal_fov_from_focal_35mm,
)
from dapm_lightning.inference.telemetry.srt import read_srt

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
