"""What each DJI telemetry field means, before anything is parsed: the component it gives, its reference, who writes it.

:data:`FIELD_MEANINGS` is the one table; docs/conventions.md ("What each DJI field means") shows it with its
sources, and the readers' tables (``SRT_FIELDS`` and ``SRT_CAPTION_FIELDS`` in ``srt.py``, the XMP tags in
``image_metadata.py``) may read a field only for the component given here (a test holds them to it). The rules:

- a height is read only from a field measured from the take-off point (or the ground); an altitude above sea level
  is never a height;
- a field whose reference depends on the drone model is read only in a layout whose model is known, else the
  component is unknown, with one warning naming the field and how to give the height instead (a CSV);
- the aircraft's own attitude is never the camera's: only the gimbal's pitch and roll are read.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Reference = Literal["take-off", "sea level", "by layout", "gimbal", "aircraft", "lens", "none"]
"""What a field is measured from: ``take-off`` (height above the take-off point, barometric), ``sea level``
(absolute altitude), ``by layout`` (depends on the model; see ``families``), ``gimbal`` (the camera's attitude to
the horizon, north-east-down), ``aircraft`` (the airframe's attitude), ``lens`` (focal length, zoom), ``none``."""


@dataclass(frozen=True)
class FieldMeaning:
    """One DJI field: where it is written, what it measures, from what, the pose component it gives, who writes it.

    Attributes:
        name: as written (``rel_alt``; ``H`` for the caption ``H 45.60m``; ``drone-dji:RelativeAltitude``).
        file: ``SRT`` (one subtitle per frame), ``SRT caption`` (one per second), ``XMP`` or ``EXIF``.
        measures: what the value is. reference: :data:`Reference`.
        component: the pose key it gives (``height``, ``pitch``, ``roll``, ``fov``); ``""``: never read.
        families: the drones (and the layouts) that write it, from the real files and DJI's manuals.
    """

    name: str
    file: str
    measures: str
    reference: Reference
    component: str
    families: str


FIELD_MEANINGS: tuple[FieldMeaning, ...] = (
    # ---------------------------------------------------------------- SRT, one subtitle per frame (`[name: value]`)
    FieldMeaning("rel_alt", "SRT", "metres above the take-off point (barometric)", "take-off", "height",
                 "Mavic 3 / 3T / 3E, Mini 4 / 5 Pro, Air 3S, Avata 360, Neo 2, M300 RTK, Mavic 2 Enterprise Advanced"),
    FieldMeaning("abs_alt", "SRT", "altitude above sea level (barometric, weather-dependent)", "sea level", "",
                 "written beside rel_alt"),
    FieldMeaning("altitude", "SRT", "in the `SrtCnt` layout: metres above the take-off point", "by layout", "height",
                 "Air 2, Air 2S (DJI Fly, `SrtCnt : N`): 27-29 m where the ground is ~250 m above sea level"),
    FieldMeaning("altitude", "SRT", "in the `longtitude` layout: altitude above sea level", "by layout", "",
                 "Mavic 2 Zoom / Pro / Enterprise (DJI GO 4, `[longtitude : ...]`): 214 m at Lahore, 458 m where "
                 "the take-off point is 481 m above sea level"),
    FieldMeaning("gb_pitch", "SRT", "gimbal pitch, degrees (0 horizontal, -90 nadir)", "gimbal", "pitch",
                 "Mavic 3T, M300 RTK, Avata 360, DJI.SRT (ruz76)"),
    FieldMeaning("gb_roll", "SRT", "gimbal roll, degrees (right side down > 0)", "gimbal", "roll", "as gb_pitch"),
    FieldMeaning("gb_yaw", "SRT", "gimbal heading, degrees", "gimbal", "", "as gb_pitch"),
    FieldMeaning("drone_pitch", "SRT", "aircraft pitch (with drone_roll, drone_yaw)", "aircraft", "",
                 "M300 RTK, DJI.SRT (ruz76)"),
    FieldMeaning("Drone: Pitch", "SRT", "aircraft pitch (`[Drone: Yaw:.., Pitch:.., Roll:..]`)", "aircraft", "",
                 "Mavic 2 Enterprise Advanced, Mavic (ruz76)"),
    FieldMeaning("focal_len", "SRT", "35-mm-equivalent focal length: mm (`24.00`), or tenths of mm in the "
                 "fixed-point layout (`240` with `fnum : 280`)", "lens", "fov", "all but Neo 2 and Mavic Air"),
    FieldMeaning("dzoom_ratio", "SRT", "digital zoom: `10746` = 1.0746x in the fixed-point layout, where focal_len "
                 "is the lens's; `4.00` in the decimal layout, where focal_len already includes it", "lens", "fov",
                 "Mavic 2 Enterprise (Advanced), Mavic 3T, Avata 360"),
    # ---------------------------------------------------------------- SRT captions, one subtitle per second
    FieldMeaning("H", "SRT caption", "height above the home (take-off) point, `H 85.80m`", "take-off", "height",
                 "Phantom 4 Pro, Phantom 4 RTK, Mavic Mini"),
    FieldMeaning("BAROMETER", "SRT caption", "barometric height above the take-off point, `BAROMETER:1.9`",
                 "take-off", "height", "Mavic Pro (2017), Matrice 300 (`BAROMETER:0.3M`)"),
    FieldMeaning("Hb", "SRT caption", "barometric height above the take-off point, `Hb:1.9`", "take-off", "height",
                 "Mavic Pro, older firmware"),
    FieldMeaning("Hs", "SRT caption", "satellite (GNSS) height, reference not stated", "sea level", "",
                 "Mavic Pro, older firmware"),
    FieldMeaning("G.PRY", "SRT caption", "gimbal (pitch, roll, yaw) in degrees", "gimbal", "pitch, roll",
                 "Phantom 4 RTK"),
    FieldMeaning("F.PRY", "SRT caption", "aircraft (flight) pitch, roll, yaw", "aircraft", "", "Phantom 4 RTK"),
    FieldMeaning("D", "SRT caption", "horizontal distance from the home point", "none", "", "Phantom 4, Mavic Mini"),
    # ---------------------------------------------------------------- image XMP and EXIF
    FieldMeaning("drone-dji:RelativeAltitude", "XMP", "metres above the take-off point", "take-off", "height",
                 "every DJI drone camera; Zenmuse XT S writes `DJI:RelativeAltitude`"),
    FieldMeaning("drone-dji:AbsoluteAltitude", "XMP", "altitude above sea level (\"geodetic\")", "sea level", "",
                 "every DJI drone camera"),
    FieldMeaning("drone-dji:GimbalPitchDegree", "XMP", "gimbal pitch, NED frame, ZYX order", "gimbal", "pitch",
                 "every DJI gimbal camera"),
    FieldMeaning("drone-dji:GimbalRollDegree", "XMP", "gimbal roll, NED frame, ZYX order", "gimbal", "roll",
                 "every DJI gimbal camera"),
    FieldMeaning("drone-dji:FlightPitchDegree", "XMP", "aircraft pitch (with FlightRollDegree, FlightYawDegree)",
                 "aircraft", "", "every DJI drone camera"),
    FieldMeaning("drone-dji:GimbalReverse", "XMP", "1: the gimbal is mounted upside down (pitch, roll not read)",
                 "gimbal", "", "Matrice / Zenmuse"),
    FieldMeaning("GPano:ProjectionType", "XMP", "`equirectangular`: a 360-degree image (no pinhole FoV)", "lens", "",
                 "360-degree cameras and panoramas"),
    FieldMeaning("FocalLengthIn35mmFilm", "EXIF", "35-mm-equivalent focal length (0 = unknown)", "lens", "fov",
                 "most cameras"),
    FieldMeaning("FocalLength", "EXIF", "real focal length, with your --sensor_width_mm", "lens", "fov",
                 "every camera"),
)
"""Every DJI field the project knows, read or not, with its meaning (docs/conventions.md shows it)."""


def meanings(name: str, file: str | None = None) -> list[FieldMeaning]:
    """The rows of :data:`FIELD_MEANINGS` for field ``name`` (in ``file`` when given), in table order."""
    return [m for m in FIELD_MEANINGS if m.name == name and (file is None or m.file == file)]
