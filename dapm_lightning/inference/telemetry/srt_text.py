"""An SRT file's subtitles, read as a stream in bounded memory: number, timing, text.

A subtitle starts where a line holding only its number (1, 2, ...) is followed by a timing line
(``00:00:00,000 --> 00:00:00,033``); everything up to the next such pair is its text, empty lines and lines holding
only ``0`` included (DJI's multi-line layout puts both inside a subtitle). A file without timing lines (2017 DJI
SRTs) is split at its empty lines, each part starting with its number: an *untimed* subtitle. The file is read a
line at a time; a line or a subtitle longer than :data:`MAX_SUBTITLE_CHARS` is an error, so a damaged or hostile
file of any size costs at most that much memory.
"""

from __future__ import annotations

import codecs
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from dapm_lightning.inference.telemetry.pose import TelemetryError

MAX_SUBTITLE_CHARS = 1 << 16
"""The most text one subtitle may hold (DJI writes under 2,000 characters)."""

TIMING = re.compile(r"^\s*(\d+):(\d+):(\d+)[,.](\d+)\s*-->\s*(\d+):(\d+):(\d+)[,.](\d+)")
_DAMAGED = "the file is not an SRT or is damaged"


@dataclass
class RawSubtitle:
    """One subtitle as written: its number, the line it starts on, its start and end in seconds (None: untimed)."""

    number: int
    line: int
    start: float | None = None
    end: float | None = None
    lines: list[str] = field(default_factory=list)
    chars: int = 0

    @property
    def text(self) -> str:
        """The subtitle's text (the lines after its timing line)."""
        return "\n".join(self.lines)


def _seconds(groups: tuple[str | None, ...]) -> float:
    """``hours, minutes, seconds, fraction`` of an SRT time as seconds."""
    h, m, s, frac = (g or "0" for g in groups)
    return float(int(h) * 3600 + int(m) * 60 + int(s)) + int(frac) / 10.0 ** len(frac)


def _open(path: Path) -> TextIO:
    """The file as text: UTF-16 / UTF-32 when its byte-order mark says so, else UTF-8 (bad bytes replaced)."""
    with path.open("rb") as stream:
        head = stream.read(4)
    encoding = "utf-8-sig"
    for bom, name in ((codecs.BOM_UTF32_LE, "utf-32"), (codecs.BOM_UTF32_BE, "utf-32"),
                      (codecs.BOM_UTF16_LE, "utf-16"), (codecs.BOM_UTF16_BE, "utf-16")):
        if head.startswith(bom):
            encoding = name
            break
    return path.open(encoding=encoding, errors="replace", newline=None)


def _lines(stream: TextIO, path: Path) -> Iterator[tuple[int, str]]:
    """``(line number, line without its end)``, refusing a line longer than :data:`MAX_SUBTITLE_CHARS`."""
    number = 0
    while True:
        line = stream.readline(MAX_SUBTITLE_CHARS + 1)
        if not line:
            return
        number += 1
        if len(line) > MAX_SUBTITLE_CHARS:
            raise TelemetryError(f"{path}, line {number}: longer than {MAX_SUBTITLE_CHARS} characters; {_DAMAGED}")
        yield number, line.rstrip("\r\n")


def subtitles(path: Path) -> Iterator[RawSubtitle]:
    """The file's subtitles in order (see the module's description).

    Raises:
        TelemetryError: text before the first subtitle number, a line or a subtitle longer than
            :data:`MAX_SUBTITLE_CHARS` (naming the file and the line).
    """
    current: RawSubtitle | None = None
    pending: tuple[int, str] | None = None  # a line holding only a number: a header if a timing line follows
    after_blank = True

    def add(lineno: int, text: str) -> Iterator[RawSubtitle]:
        nonlocal current
        untimed_header = text.strip().isdecimal() and int(text) >= 1 and (current is None or (
            current.start is None and after_blank))
        if untimed_header:
            if current is not None:
                yield current
            current = RawSubtitle(int(text), lineno)
            return
        if current is None:
            raise TelemetryError(f"{path}, line {lineno}: expected a subtitle number (1, 2, ...), found "
                                 f"{text.strip()[:40]!r}; {_DAMAGED}")
        current.lines.append(text)
        current.chars += len(text) + 1
        if current.chars > MAX_SUBTITLE_CHARS:
            raise TelemetryError(f"{path}, subtitle {current.number} (line {current.line}): more than "
                                 f"{MAX_SUBTITLE_CHARS} characters of text; {_DAMAGED}")

    with _open(path) as stream:
        for lineno, line in _lines(stream, path):
            stripped = line.strip()
            if pending is not None:
                header_line, number = pending
                pending = None
                timing = TIMING.match(line)
                if timing is not None:
                    if current is not None:
                        yield current
                    times = timing.groups()
                    current = RawSubtitle(int(number), header_line, _seconds(times[:4]), _seconds(times[4:]))
                    after_blank = False
                    continue
                yield from add(header_line, number)
                after_blank = False
            if not stripped:
                after_blank = True
                continue
            if stripped.isdecimal():
                pending = (lineno, stripped)
                continue
            yield from add(lineno, line)
            after_blank = False
        if pending is not None:
            yield from add(*pending)
    if current is not None:
        yield current
