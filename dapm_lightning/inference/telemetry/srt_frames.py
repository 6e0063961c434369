"""An SRT's values onto video frames, as a player shows them; one warning for the file.

:class:`SrtReading` collects what ``read_srt`` (``srt.py``) reads from each subtitle, then :meth:`SrtReading.frames`
gives ``{frame: PoseTelemetry}``. With the video's frame rate, a per-frame subtitle is the telemetry of every frame
whose centre time ``(f + 0.5) / fps`` it covers (``start <= t < end``): DJI's timings are rounded to the millisecond
(33, 66, 99, 133 ms at 30 fps), which never moves a centre across a subtitle's edge, and a subtitle lasting two
frames (many of the Mavic 2 Pro's last 80 ms at 25 fps) covers both. Without it, subtitle ``k`` is frame ``k - 1``.
A per-second subtitle's value holds at its start time and is interpolated linearly to the next subtitle's start when
the two follow each other (frame ``f`` at time ``f / fps``), held to its own end otherwise.
"""

from __future__ import annotations

import math
import warnings
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from dapm_lightning.inference.telemetry.pose import PoseTelemetry, TelemetryError, TelemetryWarning

MAX_SUBTITLE_S = 0.5
"""A per-frame SRT holds one subtitle per video frame; one lasting longer than this is a per-second subtitle."""
_GAP_S = 0.05
"""Two per-second subtitles follow each other when the second starts within this of the first's end."""


def first_frame_from(t: float, fps: float) -> int:
    """The first frame whose centre time ``(f + 0.5) / fps`` is at or after ``t`` seconds."""
    return math.ceil(t * fps - 0.5 - 1e-9)


@dataclass(frozen=True)
class Sample:
    """A per-second subtitle's values: its number, start and end (s), values and the field each came from."""

    number: int
    start: float
    end: float
    values: tuple[float, ...]
    read: tuple[str, ...]


class SrtReading:
    """What one SRT file gave a video at ``fps`` (None: not known), frame by frame; :meth:`frames` warns once."""

    def __init__(self, path: Path, fps: float | None, notes_first: Sequence[str] = ()) -> None:
        self.path = path
        self.fps = fps if fps is not None and fps > 0 else None
        self.notes: Counter[str] = Counter(dict.fromkeys(notes_first, 0))
        self.per_frame: dict[int, PoseTelemetry] = {}
        self.samples: list[Sample] = []
        self.untimed = 0
        self._numbers: set[int] = set()

    def check_number(self, number: int, where: str) -> None:
        """Refuse a subtitle number seen before in the file."""
        if number in self._numbers:
            raise TelemetryError(f"{where}: subtitle number {number} appears twice; the file is damaged")
        self._numbers.add(number)

    def _count(self, notes: Sequence[str]) -> None:
        for note in dict.fromkeys(notes):
            self.notes[note] += 1

    def add_frame(self, number: int, start: float, end: float, values: Sequence[float], read: Sequence[str],
                  notes: Sequence[str]) -> None:
        """A per-frame subtitle shown from ``start`` to ``end`` (s): on the frames whose centre it covers.

        A frame two subtitles cover gets the later one; without the frame rate, the subtitle is frame ``number - 1``.
        """
        self._count(notes)
        known = not all(math.isnan(v) for v in values)
        where = f"{self.path.name} subtitle {number}"
        provenance = [f"{where} {name}" if name else "" for name in read]
        telemetry = PoseTelemetry.from_values(values, where if known else "", provenance)
        if self.fps is None:
            self.per_frame[number - 1] = telemetry
        else:
            covered = range(first_frame_from(start, self.fps), first_frame_from(end, self.fps))
            self.per_frame.update(dict.fromkeys(covered, telemetry))

    def add_sample(self, number: int, start: float, end: float, values: Sequence[float], read: Sequence[str],
                   notes: Sequence[str]) -> None:
        """A per-second subtitle, to be placed on frames by its timing."""
        self._count(notes)
        self.samples.append(Sample(number, start, end, tuple(values), tuple(read)))

    def _place(self, fps: float) -> dict[int, PoseTelemetry]:
        """The per-second samples on the frames they cover, at ``fps``."""
        out: dict[int, PoseTelemetry] = {}
        samples = sorted(self.samples, key=lambda s: s.start)
        name = self.path.name
        for i, sample in enumerate(samples):
            after = samples[i + 1] if i + 1 < len(samples) else None
            if after is not None and not (0 <= after.start - sample.end <= _GAP_S and after.start > sample.start):
                after = None
            for frame in range(math.ceil(sample.start * fps - 1e-6), math.ceil(sample.end * fps - 1e-6)):
                t = frame / fps
                values, provenance = [], []
                for v, field, later in zip(sample.values, sample.read, after.values if after else [math.nan] * 4):
                    if math.isnan(v):
                        values.append(math.nan)
                        provenance.append("")
                    elif after is not None and not math.isnan(later) and t > sample.start:
                        w = (t - sample.start) / (after.start - sample.start)
                        values.append(v + w * (later - v))
                        provenance.append(f"{name} subtitles {sample.number}-{after.number} {field} at {t:.3f} s")
                    else:
                        values.append(v)
                        provenance.append(f"{name} subtitle {sample.number} {field}")
                known = any(provenance)
                out[frame] = PoseTelemetry.from_values(values, f"{name} frame {frame}" if known else "", provenance)
        return out

    def frames(self) -> dict[int, PoseTelemetry]:
        """``{frame: PoseTelemetry}`` of the whole file; warns once about what was left unknown, and why.

        Frames no subtitle covers are not in it.

        Raises:
            ValueError: per-second subtitles with values but no ``fps`` to place them with.
        """
        out: dict[int, PoseTelemetry] = {}
        if self.samples:
            if self.fps is not None:
                out = self._place(self.fps)
            elif any(not math.isnan(v) for s in self.samples for v in s.values):
                raise ValueError(f"{self.path}: its subtitles last about 1 s each (one per second): give the video's "
                                 "frame rate (read_srt(..., fps=...)) to place them on the frames")
            else:  # nothing to place: unknown frames, numbered as per-frame subtitles would be
                out = {s.number - 1: PoseTelemetry() for s in self.samples}
        out.update(self.per_frame)
        notes = [f"{count} subtitle(s) {note}" for note, count in self.notes.items() if count]
        if self.untimed:
            notes.append(f"{self.untimed} subtitle(s) without a timing line (and no field read here)")
        usable = any(any(t.known()) for t in out.values())
        if not usable:
            detail = f": {'; '.join(notes)}" if notes else (": no height, gimbal or focal-length field was found "
                                                           "(fields read: docs/conventions.md)")
            warnings.warn(f"{self.path}: no usable telemetry in the file{detail}; the network estimates the pose",
                          TelemetryWarning, stacklevel=3)
        elif notes:
            warnings.warn(f"{self.path}: " + "; ".join(notes), TelemetryWarning, stacklevel=3)
        return out
