"""DJI video subtitles (``.SRT``): one subtitle per video frame, its text a list of ``name: value`` fields.

Three steps: :func:`_subtitles` splits the file into numbered, timed subtitles; :func:`srt_field_pairs`
tokenizes a subtitle's text into (field name, value text) pairs (:data:`SRT_TOKEN_RULES`); the table
:data:`SRT_FIELDS` says which DJI field gives which pose component and how its value converts. A new DJI
variant is a row in the table, a new way of writing fields a rule in :data:`SRT_TOKEN_RULES`.
"""

from __future__ import annotations

import math
import re
import warnings
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.inference.telemetry.pose import (
    PoseTelemetry,
    StrPath,
    TelemetryError,
    TelemetryWarning,
    horizontal_fov_from_focal_35mm,
    limit_error,
)

MAX_SUBTITLE_S = 0.5
"""A per-frame SRT holds one subtitle per video frame; one lasting longer than this is a per-second SRT."""

_TIMING = re.compile(r"^\s*(\d+):(\d+):(\d+)[,.](\d+)\s*-->\s*(\d+):(\d+):(\d+)[,.](\d+)")
_MARKUP = re.compile(r"<[^>]*>")

SRT_TOKEN_RULES: tuple[tuple[re.Pattern[str], bool], ...] = (
    # `[rel_alt: 54.821 abs_alt: 535.407]`, `[fnum : 280]`, `BAROMETER:1.9`: a name, a colon, the value up to
    # the next space or bracket; the name in lower case (DJI writes `Fnum`, `fnum`, `BAROMETER`)
    (re.compile(r"(?P<name>[A-Za-z_][A-Za-z0-9_]*)\s*:\s*(?P<value>[^\s\[\]]+)"), True),
    # `H 45.60m`, `EV -1.7`, `GPS (8.2090, 47.4692, 18)`, `HOME(149.0251,-20.2532)`: an upper-case label as
    # written, then a number (up to the next space or comma) or a parenthesised list
    (re.compile(r"(?<![\w.])(?P<name>[A-Z][A-Z.]*)(?!\w)\s*(?P<value>\([^()]*\)|-?\d[^\s,]*)"), False),
)
"""How DJI writes a field in a subtitle's text: a regular expression with groups ``name`` and ``value``, and
whether the name is read in lower case. Lower-cased names and upper-case labels never coincide."""

_NOTE_ON_GROUND = "with a height <= 0 (on the ground or below the take-off point): height left unknown there"
_NOTE_ALTITUDE = ("give `altitude` (no `rel_alt`): read as metres above the take-off point; if your model writes "
                  "the altitude above sea level there, give heights in a CSV instead")
_NOTE_AMBIGUOUS_FOCAL = ("give `focal_len` as an integer without an integer `fnum`: mm or tenths of mm cannot be "
                         "told apart, FoV left unknown there")
_NOTES = (_NOTE_ON_GROUND, _NOTE_ALTITUDE, _NOTE_AMBIGUOUS_FOCAL)
"""The file's warning lists these first, in this order (others after them)."""


def srt_field_pairs(text: str) -> list[tuple[str, str]]:
    """A subtitle's text as (field name, value text) pairs, markup such as ``<font size="28">`` removed.

    The pairs of each rule of :data:`SRT_TOKEN_RULES` in turn, each rule's in the order written:
    ``"[REL_ALT: 54.821 abs_alt: 535.407] H 45.60m"`` gives ``("rel_alt", "54.821")``,
    ``("abs_alt", "535.407")``, ``("H", "45.60m")``.
    """
    plain = _MARKUP.sub(" ", text)
    return [(match["name"].lower() if lower_case else match["name"], match["value"])
            for rule, lower_case in SRT_TOKEN_RULES for match in rule.finditer(plain)]


def srt_fields(text: str) -> dict[str, str]:
    """A subtitle's fields: the first value text of each field name (:func:`srt_field_pairs`)."""
    fields: dict[str, str] = {}
    for name, value in srt_field_pairs(text):
        fields.setdefault(name, value)
    return fields


@dataclass
class Subtitle:
    """One subtitle being read: its fields, where it is (for messages), the video size, notes for the warning."""

    fields: dict[str, str]
    where: str
    size: tuple[int, int] | None
    notes: list[str] = field(default_factory=list)

    def number(self, name: str) -> float:
        """Field ``name``'s value as a finite number; :class:`TelemetryError` when it is not one."""
        text = self.fields[name]
        try:
            value = float(text)
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


def _height(subtitle: Subtitle, name: str, key: str) -> float:
    """Metres above the take-off point, read as the height above the ground; <= 0 is left unknown."""
    value = subtitle.number(name)
    return value if value > 0 else subtitle.unknown(_NOTE_ON_GROUND)


def _angle(subtitle: Subtitle, name: str, key: str) -> float:
    """Gimbal pitch or roll in degrees, taken as written (DJI's conventions equal the project's)."""
    value = subtitle.number(name)
    if (why := limit_error(key, value)) is not None:
        raise TelemetryError(f"{subtitle.where}: `{name}` = {subtitle.fields[name]} {why}; correct or delete it")
    return value


def _fov_from_focal_35mm(subtitle: Subtitle, name: str, key: str) -> float:
    """Horizontal FoV from the 35-mm-equivalent focal length and the video size (unknown without the size).

    Written as an integer, the focal length is tenths of a mm when ``fnum`` is an integer >= 100 (hundredths:
    Air 2S / Mini style ``focal_len: 240``, ``fnum: 280`` = 24 mm, f/2.8); else it is ambiguous, left unknown.
    """
    f35 = subtitle.number(name)
    if "." not in subtitle.fields[name]:
        fnum = subtitle.fields.get("fnum", "")
        if not (fnum.isdigit() and int(fnum) >= 100):
            return subtitle.unknown(_NOTE_AMBIGUOUS_FOCAL)
        f35 /= 10.0
    if subtitle.size is None or not f35 > 0:
        return math.nan
    return horizontal_fov_from_focal_35mm(f35, *subtitle.size)


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
    SrtField("altitude", "height", _height, note=_NOTE_ALTITUDE),
    SrtField("gb_pitch", "pitch", _angle),
    SrtField("gb_roll", "roll", _angle),
    SrtField("focal_len", "fov", _fov_from_focal_35mm),
)
"""Which DJI SRT field gives which pose component: a component comes from its first row whose field is there."""


def _pose_values(subtitle: Subtitle) -> list[float]:
    """The subtitle's pose components in ``POSE_KEYS`` order, read through :data:`SRT_FIELDS`."""
    values = dict.fromkeys(POSE_KEYS, math.nan)
    given: set[str] = set()
    for row in SRT_FIELDS:
        if row.key in given or row.name not in subtitle.fields:
            continue
        given.add(row.key)
        values[row.key] = row.convert(subtitle, row.name, row.key)
        if row.note:
            subtitle.notes.append(row.note)
    return list(values.values())


def _blocks(lines: list[str]) -> Iterator[tuple[int, list[str]]]:
    """The runs of non-blank lines (one per subtitle), each with its first line's number (1-based)."""
    block: list[str] = []
    for lineno, line in enumerate(lines, 1):
        if line.strip():
            block.append(line)
        elif block:
            yield lineno - len(block), block
            block = []
    if block:
        yield len(lines) + 1 - len(block), block


def _seconds(groups: Iterable[str]) -> float:
    """``hours, minutes, seconds, fraction`` of an SRT time as seconds."""
    h, m, s, frac = groups
    return float(int(h) * 3600 + int(m) * 60 + int(s)) + int(frac) / 10.0 ** len(frac)


def _subtitles(path: Path) -> Iterator[tuple[int, str, float, str]]:
    """Each subtitle: its number, where it is (``FILE, subtitle K (line N)``), its duration in s, its text."""
    text = path.read_text(encoding="utf-8-sig", errors="replace").replace("\r\n", "\n").replace("\r", "\n")
    numbers: set[int] = set()
    for start, block in _blocks(text.split("\n")):
        head = block[0].strip()
        if not head.isdigit() or int(head) < 1:
            raise TelemetryError(f"{path}, line {start}: expected a subtitle number (1, 2, ...), found {head!r}; "
                                 "the file is not an SRT or is damaged")
        number = int(head)
        where = f"{path}, subtitle {number} (line {start})"
        timing = _TIMING.match(block[1]) if len(block) > 1 else None
        if timing is None:
            raise TelemetryError(f"{where}: expected a timing line `00:00:00,000 --> 00:00:00,033`; the file is "
                                 "damaged")
        if number in numbers:
            raise TelemetryError(f"{where}: subtitle number {number} appears twice; the file is damaged")
        numbers.add(number)
        times = timing.groups()
        yield number, where, _seconds(times[4:]) - _seconds(times[:4]), "\n".join(block[2:])


def read_srt(path: StrPath, width: int | None = None, height: int | None = None) -> dict[int, PoseTelemetry]:
    """Per-frame telemetry from a DJI video's subtitle file: ``{frame index (0-based): PoseTelemetry}``.

    Subtitle ``k`` (1-based, one per video frame) is frame ``k - 1``. Fields read (:data:`SRT_FIELDS`), each
    unknown when absent: height from ``rel_alt`` (metres above the take-off point), else ``altitude`` (read the
    same way, with a warning: check that your model writes the relative altitude there); pitch and roll from
    ``gb_pitch`` and ``gb_roll`` (DJI's gimbal conventions equal the project's); FoV from ``focal_len``, the
    35-mm-equivalent focal length, when the video's ``width`` and ``height`` are given. ``focal_len`` written
    as an integer is tenths of a millimetre when the block's ``fnum`` is an integer too (hundredths; Air 2S /
    Mini style: ``focal_len: 240``, ``fnum: 280`` = 24 mm, f/2.8); an integer ``focal_len`` without that
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
    size = (width, height) if width is not None and height is not None else None
    out: dict[int, PoseTelemetry] = {}
    notes = dict.fromkeys(_NOTES, 0)  # subtitles with each note
    for number, where, duration, text in _subtitles(path):
        subtitle = Subtitle(srt_fields(text), where, size)
        values = _pose_values(subtitle)
        known = not all(math.isnan(v) for v in values)
        if known and duration > MAX_SUBTITLE_S:
            raise TelemetryError(f"{where}: the subtitle lasts {duration:.3f} s; this SRT holds one subtitle per "
                                 "time span, not one per video frame, so subtitles cannot be matched to frames; "
                                 "give per-frame telemetry in a CSV instead")
        for note in dict.fromkeys(subtitle.notes):
            notes[note] = notes.get(note, 0) + 1
        out[number - 1] = PoseTelemetry.from_values(values, f"{path.name} frame {number - 1}" if known else "")
    if any(notes.values()):
        warnings.warn(f"{path}: " + "; ".join(f"{count} subtitle(s) {note}" for note, count in notes.items() if count),
                      TelemetryWarning, stacklevel=2)
    return out
