"""DJI video subtitles (``.SRT``): per frame (``[name: value]`` fields) or per second (captions), onto video frames.

Four steps: :func:`~dapm_lightning.inference.telemetry.srt_text.subtitles` streams the file's numbered, timed
subtitles; :func:`srt_field_pairs` tokenizes a subtitle's text into (field name, value text) pairs
(:data:`SRT_TOKEN_RULES`); the tables say which field gives which pose component and how its value converts --
:data:`SRT_FIELDS` for DJI's per-frame layout, :data:`SRT_CAPTION_FIELDS` for its one-per-second captions, each
field's meaning a row of :data:`~dapm_lightning.inference.telemetry.fields.FIELD_MEANINGS`; the values are placed
on frames by their timing, given the video's frame rate (``srt_frames.py``). A new DJI variant is a row in a table, a
new way of writing fields a rule in :data:`SRT_TOKEN_RULES`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from dapm_lightning.inference.telemetry.pose import (
    MIN_HEIGHT_M,
    PoseTelemetry,
    StrPath,
    TelemetryError,
    horizontal_fov_from_focal_35mm,
    is_equirectangular,
    limit_error,
)
from dapm_lightning.inference.telemetry.srt_frames import MAX_SUBTITLE_S, SrtReading
from dapm_lightning.inference.telemetry.srt_text import subtitles

_MARKUP = re.compile(r"<[^>]*>")

SRT_TOKEN_RULES: tuple[tuple[re.Pattern[str], bool], ...] = (
    # `[rel_alt: 54.821 abs_alt: 535.407]`, `[fnum : 280]`, `BAROMETER:1.9`: a name, a colon, the value up to
    # the next space or bracket, empty where the next name follows (`EV: Fnum:2.2`); the name in lower case (DJI
    # writes `Fnum`, `fnum`, `BAROMETER`)
    (re.compile(r"(?P<name>[A-Za-z_]\w*)\s*:\s*(?P<value>(?![A-Za-z_]\w*\s*:)[^\s\[\]]+)?", re.ASCII), True),
    # `H 45.60m`, `EV -1.7`, `GPS (8.2090, 47.4692, 18)`, `G.PRY (-24.4°, 0.0°, 110.4°)`: an upper-case label as
    # written, then a number (up to the next space or comma) or a parenthesised list
    (re.compile(r"(?<![\w.])(?P<name>[A-Z][A-Z.]*)(?!\w)\s*(?P<value>\([^()]*\)|-?\d[^\s,]*)"), False),
)
"""How DJI writes a field in a subtitle's text: a regular expression with groups ``name`` and ``value``, and
whether the name is read in lower case. Lower-cased names and upper-case labels never coincide."""

NOTE_ON_GROUND = "with a height <= 0 (on the ground or below the take-off point): height left unknown there"
NOTE_NEAR_GROUND = (f"with a height below {MIN_HEIGHT_M:g} m (on the ground, within a barometer's accuracy): height "
                    "left unknown there")
NOTE_ALTITUDE_SRTCNT = ("give `altitude` in the Air 2 / Air 2S layout (`SrtCnt`), which those models write as metres "
                        "above the take-off point: read as the height")
NOTE_ALTITUDE_BARE = ("give `altitude` without `rel_alt` in a layout not known here: read as metres above the take-off "
                      "point (as the Air 2 / Air 2S write it); if your model writes the altitude above sea level there "
                      "(the Mavic 2 family does), give heights in a --telemetry CSV instead")
NOTE_ALTITUDE_SEA_LEVEL = ("give `altitude` in the Mavic 2 layout (`longtitude`), where it is the altitude above sea "
                           "level, never a height: height left unknown (give heights in a --telemetry CSV naming the "
                           "frames as their outputs, e.g. DJI_0005_f000012)")
NOTE_AMBIGUOUS_FOCAL = ("give `focal_len` as an integer without an integer `fnum`: mm or tenths of mm cannot be "
                        "told apart, FoV left unknown there")
NOTE_SPHERICAL = "are frames of a 360-degree (2:1 equirectangular) video: no pinhole FoV, FoV left unknown there"
NOTES = (NOTE_ON_GROUND, NOTE_NEAR_GROUND, NOTE_ALTITUDE_SRTCNT, NOTE_ALTITUDE_BARE, NOTE_ALTITUDE_SEA_LEVEL,
         NOTE_AMBIGUOUS_FOCAL, NOTE_SPHERICAL)
"""The file's warning lists these first, in this order (others after them)."""


def srt_field_pairs(text: str) -> list[tuple[str, str]]:
    """A subtitle's text as (field name, value text) pairs, markup such as ``<font size="28">`` removed.

    The pairs of each rule of :data:`SRT_TOKEN_RULES` in turn, each rule's in the order written:
    ``"[REL_ALT: 54.821 abs_alt: 535.407] H 45.60m"`` gives ``("rel_alt", "54.821")``,
    ``("abs_alt", "535.407")``, ``("H", "45.60m")``; an empty field gives an empty value (``"EV: Fnum:2.2"``:
    ``("ev", "")``, ``("fnum", "2.2")``).
    """
    plain = _MARKUP.sub(" ", text)
    return [(match["name"].lower() if lower_case else match["name"], match["value"] or "")
            for rule, lower_case in SRT_TOKEN_RULES for match in rule.finditer(plain)]


def srt_fields(text: str) -> dict[str, str]:
    """A subtitle's fields: the first value text of each field name (:func:`srt_field_pairs`).

    An empty field (``EV:``) is left out: unknown, as a missing one.
    """
    fields: dict[str, str] = {}
    for name, value in srt_field_pairs(text):
        if value:
            fields.setdefault(name, value)
    return fields


@dataclass
class Subtitle:
    """One subtitle being read: its fields, where it is (for messages), the video size, notes for the warning.

    ``read_from``: per pose key, the fields a conversion read when more than its row's (``focal_len x dzoom_ratio``).
    """

    fields: dict[str, str]
    where: str
    size: tuple[int, int] | None
    notes: list[str] = field(default_factory=list)
    read_from: dict[str, str] = field(default_factory=dict)

    def number(self, name: str, units: str = "") -> float:
        """Field ``name``'s value as a finite number (a trailing unit in ``units`` dropped); else an error."""
        text = self.fields[name]
        try:
            value = float(text.rstrip(units) if units else text)
        except ValueError:
            raise TelemetryError(f"{self.where}: `{name}` = {text!r} is not a number; correct or delete it (a "
                                 "missing field is read as unknown)") from None
        if not math.isfinite(value):
            raise TelemetryError(f"{self.where}: `{name}` = {text!r} is not finite; correct or delete it")
        return value

    def unknown(self, note: str) -> float:
        """NaN: the component is left unknown, for the reason ``note`` (counted in the file's warning)."""
        self.notes.append(note)
        return math.nan


def _above_ground(subtitle: Subtitle, value: float) -> float:
    """A height above the take-off point as the height, or unknown (with its note) when the drone is on the ground."""
    if value <= 0:
        return subtitle.unknown(NOTE_ON_GROUND)
    return value if value >= MIN_HEIGHT_M else subtitle.unknown(NOTE_NEAR_GROUND)


def _height(subtitle: Subtitle, name: str, key: str) -> float:
    """Metres above the take-off point (``rel_alt``), read as the height above the ground."""
    return _above_ground(subtitle, subtitle.number(name))


def _altitude(subtitle: Subtitle, name: str, key: str) -> float:
    """``altitude``, whose reference depends on the layout (``fields.py``).

    Above the take-off point in the ``SrtCnt`` layout (Air 2 / Air 2S); above sea level with ``longtitude`` (the
    Mavic 2 family): never a height; elsewhere read as above the take-off point, with a warning.
    """
    if "longtitude" in subtitle.fields and "srtcnt" not in subtitle.fields:
        return subtitle.unknown(NOTE_ALTITUDE_SEA_LEVEL)
    subtitle.notes.append(NOTE_ALTITUDE_SRTCNT if "srtcnt" in subtitle.fields else NOTE_ALTITUDE_BARE)
    return _above_ground(subtitle, subtitle.number(name))


def _caption_height(subtitle: Subtitle, name: str, key: str) -> float:
    """A caption's height above the take-off point: ``H 85.80m``, ``BAROMETER:0.3M``, ``Hb:1.9``."""
    return _above_ground(subtitle, subtitle.number(name, units="mM"))


def _angle(subtitle: Subtitle, name: str, key: str) -> float:
    """Gimbal pitch or roll in degrees, taken as written (DJI's conventions equal the project's)."""
    value = subtitle.number(name)
    if (why := limit_error(key, value)) is not None:
        raise TelemetryError(f"{subtitle.where}: `{name}` = {subtitle.fields[name]} {why}; correct or delete it")
    return value


def _gimbal_pry(subtitle: Subtitle, name: str, key: str) -> float:
    """Pitch or roll from a caption's gimbal ``G.PRY (pitch°, roll°, yaw°)``."""
    text = subtitle.fields[name]
    parts = [p.strip().rstrip("°") for p in text.strip("()").split(",")]
    if len(parts) != 3:
        raise TelemetryError(f"{subtitle.where}: `{name}` = {text!r} is not (pitch, roll, yaw); correct or delete it")
    angles = Subtitle({f"{name} {key}": parts[0 if key == "pitch" else 1]}, subtitle.where, subtitle.size)
    return _angle(angles, f"{name} {key}", key)


def _digital_zoom(subtitle: Subtitle, fixed_point: bool) -> float:
    """The digital zoom to apply to ``focal_len``.

    ``dzoom_ratio`` (10000 = 1x) in the fixed-point layout, where ``focal_len`` is the lens's (Mavic 2 Enterprise
    Advanced: ``focal_len : 240``, ``dzoom_ratio: 10746``); 1 where ``focal_len`` is decimal, as it already includes
    the zoom (Mavic 3T: ``focal_len: 643.30`` at ``dzoom_ratio: 4.00``, 4 x its 160.8 mm tele).
    """
    text = subtitle.fields.get("dzoom_ratio", "").rstrip(",")
    if not text or not fixed_point:
        return 1.0
    zoom = Subtitle({"dzoom_ratio": text}, subtitle.where, subtitle.size).number("dzoom_ratio")
    zoom = zoom / 10000.0 if "." not in text else zoom
    if not zoom > 0:
        raise TelemetryError(f"{subtitle.where}: `dzoom_ratio` = {text} must be > 0; correct or delete it")
    return zoom


def _fov_from_focal_35mm(subtitle: Subtitle, name: str, key: str) -> float:
    """Horizontal FoV from the 35-mm-equivalent focal length (and digital zoom) and the video size.

    Written as an integer, the focal length is tenths of a mm when ``fnum`` is an integer >= 100 (hundredths:
    Air 2S / Mini style ``focal_len: 240``, ``fnum: 280`` = 24 mm, f/2.8), else it is ambiguous, left unknown.
    Unknown without the video size, and for a 360-degree (2:1) video.
    """
    f35 = subtitle.number(name)
    fixed_point = "." not in subtitle.fields[name]
    if fixed_point:
        fnum = subtitle.fields.get("fnum", "")
        if not (fnum.isdecimal() and int(fnum) >= 100):
            return subtitle.unknown(NOTE_AMBIGUOUS_FOCAL)
        f35 /= 10.0
    zoom = _digital_zoom(subtitle, fixed_point)
    if subtitle.size is None or not f35 > 0:
        return math.nan
    if is_equirectangular(*subtitle.size):
        return subtitle.unknown(NOTE_SPHERICAL)
    if zoom != 1.0:
        subtitle.read_from[key] = f"{name} x dzoom_ratio"
    return horizontal_fov_from_focal_35mm(f35 * zoom, *subtitle.size)


@dataclass(frozen=True)
class SrtField:
    """A row of :data:`SRT_FIELDS`: a DJI field, the pose component (``POSE_KEYS``) it gives, its conversion.

    ``name`` is as :func:`srt_field_pairs` gives it (``rel_alt``; ``H`` for the caption label ``H 45.60m``).
    ``convert(subtitle, name, key)`` gives the component's value in the project's units (NaN = unknown) or
    raises :class:`TelemetryError`; ``note`` is counted in the file's warning on each subtitle it is read from.
    """

    name: str
    key: str
    convert: Callable[[Subtitle, str, str], float]
    note: str = ""


SRT_FIELDS: tuple[SrtField, ...] = (
    SrtField("rel_alt", "height", _height),
    SrtField("altitude", "height", _altitude),
    SrtField("gb_pitch", "pitch", _angle),
    SrtField("gb_roll", "roll", _angle),
    SrtField("focal_len", "fov", _fov_from_focal_35mm),
)
"""DJI's per-frame layout (``[name: value]``): which field gives which pose component (the first row whose field is
there); ``abs_alt``, ``drone_*`` and ``Drone:`` (the aircraft) are never read (``fields.py``)."""

SRT_CAPTION_FIELDS: tuple[SrtField, ...] = (
    SrtField("H", "height", _caption_height),
    SrtField("barometer", "height", _caption_height),
    SrtField("hb", "height", _caption_height),
    SrtField("G.PRY", "pitch", _gimbal_pry),
    SrtField("G.PRY", "roll", _gimbal_pry),
)
"""DJI's one-per-second captions (Phantom 4, Mavic Pro, Mavic Mini, Matrice 300), in subtitles over
:data:`MAX_SUBTITLE_S` (or shorter, holding no per-frame field: a clip's last, cut short), placed on frames by their
timing. ``F.PRY`` (the aircraft), ``Hs``, ``D`` are never read."""


def read_srt(path: StrPath, width: int | None = None, height: int | None = None, *,
             fps: float | None = None) -> dict[int, PoseTelemetry]:
    """Per-frame telemetry from a DJI video's subtitle file: ``{frame index (0-based): PoseTelemetry}``.

    Per-frame subtitles (up to 0.5 s), read through :data:`SRT_FIELDS` (height from ``rel_alt``, else
    ``altitude`` as its layout says; ``gb_pitch``, ``gb_roll``; FoV from ``focal_len`` and the fixed-point
    ``dzoom_ratio`` when ``width`` and ``height`` are given, not for a 2:1 360-degree video), are placed by their
    timing when ``fps`` is given, as a player shows them: each on the frames whose centre time ``(f + 0.5) / fps``
    it covers (a Mavic 2 Pro subtitle lasting 80 ms at 25 fps is two frames; frames none covers are absent);
    without ``fps``, subtitle ``k`` is frame ``k - 1``. Per-second subtitles: their captions
    (:data:`SRT_CAPTION_FIELDS`: ``H``, ``BAROMETER``, ``Hb``, ``G.PRY``) interpolated onto the frames by their
    timing at ``fps``. A height below 1 m is left unknown. Each component's ``provenance`` names the file, subtitle
    and field (``DJI_0005.SRT subtitle 215 rel_alt``). Nothing usable (also: no timing lines and no field read
    here) gives one "no usable telemetry" warning, not an error.

    Raises:
        TelemetryError: text that is not an SRT, a subtitle number twice, a field read here that is not a number
            or is impossible (naming the file, subtitle number and field), a per-frame field in a subtitle longer
            than 0.5 s, a read field in a subtitle without a timing line, a subtitle longer than 64 KiB.
        ValueError: only one of ``width`` and ``height``; per-second values without ``fps``.
    """
    path = Path(path)
    if (width is None) != (height is None):
        raise ValueError("read_srt: give both width and height of the video (or neither)")
    if width is not None and height is not None and not (width > 0 and height > 0):
        raise ValueError(f"read_srt: width and height must be positive, got {width} x {height}")
    size = (width, height) if width is not None and height is not None else None
    reading = SrtReading(path, fps, NOTES)
    for raw in subtitles(path):
        where = f"{path}, subtitle {raw.number} (line {raw.line})"
        subtitle = Subtitle(srt_fields(raw.text), where, size)
        reading.check_number(raw.number, where)
        if raw.start is None or raw.end is None:
            if any(row.name in subtitle.fields for row in (*SRT_FIELDS, *SRT_CAPTION_FIELDS)):
                raise TelemetryError(f"{where}: expected a timing line `00:00:00,000 --> 00:00:00,033`; the file is "
                                     "damaged")
            reading.untimed += 1
            continue
        values, read = _pose_values(subtitle, SRT_FIELDS)
        caption = (not any(row.name in subtitle.fields for row in SRT_FIELDS)
                   and any(row.name in subtitle.fields for row in SRT_CAPTION_FIELDS))
        if raw.end - raw.start <= MAX_SUBTITLE_S and not caption:  # a caption cut short (a clip's last) is one
            reading.add_frame(raw.number, raw.start, raw.end, values, read, subtitle.notes)
            continue
        if not all(math.isnan(v) for v in values):
            raise TelemetryError(f"{where}: the subtitle lasts {raw.end - raw.start:.3f} s; DJI writes these fields "
                                 "(`[name: value]`) one subtitle per video frame, so the file's timing was changed "
                                 "or it is damaged; give per-frame telemetry in a CSV instead")
        values, read = _pose_values(subtitle, SRT_CAPTION_FIELDS)
        reading.add_sample(raw.number, raw.start, raw.end, values, read, subtitle.notes)
    return reading.frames()


def _pose_values(subtitle: Subtitle, table: tuple[SrtField, ...]) -> tuple[list[float], list[str]]:
    """The subtitle's pose components in ``POSE_KEYS`` order through ``table``, and the field each was read from."""
    keys = ("height", "pitch", "roll", "fov")
    values, read = [math.nan] * 4, [""] * 4
    for row in table:
        i = keys.index(row.key)
        if read[i] or row.name not in subtitle.fields:
            continue
        read[i] = row.name
        values[i] = row.convert(subtitle, row.name, row.key)
        if row.note:
            subtitle.notes.append(row.note)
    read = [subtitle.read_from.get(k, name) if not math.isnan(v) else "" for k, name, v in zip(keys, read, values)]
    return values, read
