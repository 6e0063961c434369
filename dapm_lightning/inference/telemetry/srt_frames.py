"""An SRT's values onto video frames: per-frame subtitles by number, per-second ones by their timing; one warning.

:class:`SrtReading` collects what ``read_srt`` (``srt.py``) reads from each subtitle, then :meth:`SrtReading.frames`
gives ``{frame: PoseTelemetry}``: subtitle ``k`` of a per-frame SRT is frame ``k - 1``; a per-second subtitle's value
holds at its start time and is interpolated linearly to the next subtitle's start when the two follow each other
(each frame ``f`` at time ``f / fps``, as a per-frame subtitle ``f + 1`` starts), held to its own end otherwise.
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


@dataclass(frozen=True)
class Sample:
    """A per-second subtitle's values: its number, start and end (s), values and the field each came from."""

    number: int
    start: float
    end: float
    values: tuple[float, ...]
    read: tuple[str, ...]


class SrtReading:
    """What one SRT file gave, subtitle by subtitle; :meth:`frames` places it on frames and warns once."""

    def __init__(self, path: Path, notes_first: Sequence[str] = ()) -> None:
        self.path = path
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

    def add_frame(self, number: int, values: Sequence[float], read: Sequence[str], notes: Sequence[str]) -> None:
        """A per-frame subtitle: frame ``number - 1``."""
        self._count(notes)
        known = not all(math.isnan(v) for v in values)
        where = f"{self.path.name} subtitle {number}"
        provenance = [f"{where} {name}" if name else "" for name in read]
        self.per_frame[number - 1] = PoseTelemetry.from_values(
            values, f"{self.path.name} frame {number - 1}" if known else "", provenance)

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

    def frames(self, fps: float | None) -> dict[int, PoseTelemetry]:
        """``{frame: PoseTelemetry}`` of the whole file; warns once about what was left unknown, and why.

        Raises:
            ValueError: per-second subtitles with values but no ``fps`` to place them with.
        """
        out: dict[int, PoseTelemetry] = {}
        if self.samples:
            if fps is not None and fps > 0:
                out = self._place(fps)
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
