"""Drone telemetry (flight metadata) in the project's pose conventions, per image, as a pose prior.

Three sources, each read into :class:`PoseTelemetry` (``pose.py``: height m, pitch deg, roll deg, horizontal
FoV deg; NaN = unknown; per component its provenance, the file and the place in it), with the conventions of
``docs/conventions.md`` ("Telemetry"):

- a CSV the user writes (``csv_file.py``, :func:`read_telemetry_csv`): ``name,height_m,pitch_deg,roll_deg,fov_deg``;
- the image's own metadata (``image_metadata.py``, :func:`telemetry_from_image`): DJI XMP
  (``drone-dji:RelativeAltitude``, ``GimbalPitchDegree``, ``GimbalRollDegree``; read safely by ``xmp.py``) and
  EXIF focal length, read with Pillow;
- DJI video subtitles (``srt.py``, :func:`read_srt`): per-frame fields, or per-second captions placed on the
  frames by their timing (``srt_text.py`` streams the file, ``srt_frames.py`` places the values).

What each DJI field means comes first (``fields.py``, :data:`FIELD_MEANINGS`): an altitude above sea level is
never a height, the aircraft's attitude never the gimbal's, a field whose meaning depends on the model is read
only where the model is known. :func:`telemetry_for_images` / :func:`images_telemetry` and
:func:`video_telemetry` (``gather.py``) read a run's files, a CSV first and each unknown component from the
drone's own files, with a :class:`TelemetryReport` of what was used from where; a CSV shared by a run's inputs is
read once (:class:`TelemetryCsv`).

Policy: a missing value is unknown (NaN). In the CSV the user writes, a value that is there but is not a number,
or is physically impossible, is an error (:class:`TelemetryError`, naming the file, the row and the fix); in a
drone's file it is an error of that file, which then falls back to the network with one warning (an error with
``strict``). A value that is a number but cannot be a height above the ground (a relative altitude below 1 m:
the drone on the ground) is left unknown with a warning.
"""

from dapm_lightning.inference.telemetry.csv_file import CSV_COLUMNS, read_telemetry_csv
from dapm_lightning.inference.telemetry.fields import FIELD_MEANINGS, FieldMeaning
from dapm_lightning.inference.telemetry.gather import (
    TelemetryCsv,
    TelemetryReport,
    images_telemetry,
    telemetry_for_images,
    video_telemetry,
)
from dapm_lightning.inference.telemetry.image_metadata import telemetry_from_image
from dapm_lightning.inference.telemetry.pose import (
    CROP_SENSOR_ASPECT,
    FULL_FRAME_DIAGONAL_MM,
    MIN_HEIGHT_M,
    PoseTelemetry,
    Provenance,
    TelemetryError,
    TelemetryWarning,
    horizontal_fov_from_focal,
    horizontal_fov_from_focal_35mm,
)
from dapm_lightning.inference.telemetry.srt import read_srt

__all__ = [
    "CROP_SENSOR_ASPECT",
    "CSV_COLUMNS",
    "FIELD_MEANINGS",
    "FULL_FRAME_DIAGONAL_MM",
    "MIN_HEIGHT_M",
    "FieldMeaning",
    "PoseTelemetry",
    "Provenance",
    "TelemetryCsv",
    "TelemetryError",
    "TelemetryReport",
    "TelemetryWarning",
    "horizontal_fov_from_focal",
    "horizontal_fov_from_focal_35mm",
    "images_telemetry",
    "read_srt",
    "read_telemetry_csv",
    "telemetry_for_images",
    "telemetry_from_image",
    "video_telemetry",
]
