"""Telemetry for a whole run, per image or video frame: one file's problem costs only that file; a summary at the end.

A CSV is the user's own instruction: its errors stop the run. One CSV may serve all of a run's inputs
(:class:`TelemetryCsv`): it is read once, and its names that match no image or frame of any input give one warning.
A drone-written file (an image's XMP/EXIF, a video's SRT) that cannot be read makes that image or video fall back to
the network, with one warning naming the file, the reason and the fix in the command line's terms; ``strict=True``
(``--strict_telemetry``) makes it an error. :class:`TelemetryReport` counts what was used from where (the run's
summary line).
"""

from __future__ import annotations

import re
import warnings
from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.inference.telemetry.csv_file import read_telemetry_csv, row_for_image, rows_by_stem, same_text
from dapm_lightning.inference.telemetry.image_metadata import SHOW_NAMES, image_telemetry, warn_notes
from dapm_lightning.inference.telemetry.pose import PoseTelemetry, StrPath, TelemetryError, TelemetryWarning
from dapm_lightning.inference.telemetry.srt import read_srt

STRICT_HINT = "--strict_telemetry stops instead; strict_telemetry=True in Python"


@dataclass
class TelemetryReport:
    """What telemetry a run uses: of how many images or frames, which components, from which kinds of source.

    Attributes:
        kind: ``"image"`` or ``"frame"``. total: images or frames predicted. with_telemetry: those with any
        component known. sources: per kind of source (the CSV's name, ``XMP``, ``EXIF``, the SRT's name), the
        images or frames it gave a component to. components: per pose key, the images or frames that know it.
        fell_back: the files whose telemetry could not be read (the network estimates their pose).
    """

    kind: str
    total: int = 0
    with_telemetry: int = 0
    sources: Counter[str] = field(default_factory=Counter)
    components: Counter[str] = field(default_factory=Counter)
    fell_back: list[str] = field(default_factory=list)

    def add(self, telemetry: PoseTelemetry) -> None:
        """Count one image's or frame's telemetry."""
        self.total += 1
        known = telemetry.provenance_dict()
        if known:
            self.with_telemetry += 1
        self.components.update(known.keys())
        self.sources.update({source_kind(where) for where in known.values()})

    def summary(self) -> str:
        """One line: ``telemetry: 3 of 5 images (height 3, pitch 2, ...) from flight.csv 2, XMP 1; ...``."""
        line = f"telemetry: {self.with_telemetry} of {self.total} {self.kind}(s) with telemetry"
        if self.with_telemetry:
            parts = ", ".join(f"{k} {self.components[k]}" for k in POSE_KEYS if self.components[k])
            line += f" ({parts}) from " + ", ".join(f"{s} {n}" for s, n in sorted(self.sources.items()))
        if self.fell_back:
            line += f"; telemetry unreadable, network pose used: {first_few(self.fell_back)}"
        return line


def first_few(names: Sequence[str], sep: str = ", ") -> str:
    """The first :data:`SHOW_NAMES` names, and how many more there are."""
    more = f" (and {len(names) - SHOW_NAMES} more)" if len(names) > SHOW_NAMES else ""
    return sep.join(names[:SHOW_NAMES]) + more


@dataclass
class TelemetryCsv:
    """A telemetry CSV read once for all of a run's inputs: its rows, and the names the inputs matched.

    Each input marks what it matched (:meth:`match_images`, :meth:`match_video`); :meth:`warn_unmatched` then warns
    once about the rows no input used.
    """

    path: Path
    rows: dict[str, PoseTelemetry]
    matched: set[str] = field(default_factory=set)
    images: bool = False
    videos: list[Path] = field(default_factory=list)
    frame_prefixes: list[str] = field(default_factory=list)
    _by_stem: dict[str, list[str]] | None = field(default=None, repr=False)

    @classmethod
    def read(cls, path: StrPath) -> TelemetryCsv:
        """The CSV's rows (:func:`read_telemetry_csv`, whose errors it raises)."""
        return cls(Path(path), read_telemetry_csv(path))

    def row_for_image(self, path: Path) -> str | None:
        """The key of the row naming image ``path`` (:func:`~.csv_file.row_for_image`, whose errors it raises)."""
        if self._by_stem is None:
            self._by_stem = rows_by_stem(self.rows)
        return row_for_image(path, self.rows, self._by_stem)

    def match_images(self, keys: Iterable[str]) -> None:
        """Images are predicted: the rows of these keys are used."""
        self.images = True
        self.matched.update(key for key in keys if key in self.rows)

    def match_video(self, video: Path, frame_name: re.Pattern[str], prefix: str | None = None) -> None:
        """A video is predicted: the rows naming any of its frames (``frame_name``, ``PREFIX_f000012``) are its."""
        self.videos.append(video)
        self.frame_prefixes.append(video.stem if prefix is None else prefix)
        self.matched.update(key for key in self.rows if frame_name.fullmatch(key.rsplit("/", 1)[-1]))

    def warn_unmatched(self) -> None:
        """One warning for the names that match no input (a flight log often covers more than one run predicts)."""
        unmatched = [name for name in self.rows if name not in self.matched]
        if not unmatched:
            return
        what = ["image"] if self.images else []
        if self.videos:
            what.append(f"frame of {first_few([v.name for v in self.videos], ' or ')} (frames are named as their "
                        f"outputs: {self.frame_prefixes[0]}_f000012)")
        warnings.warn(f"{self.path}: {len(unmatched)} of {len(self.rows)} name(s) match no {' or '.join(what)}: "
                      f"{first_few(unmatched)}; names are matched by file name with or without extension "
                      "(case-sensitive; folders in a name must be the image's), those rows are unused",
                      TelemetryWarning, stacklevel=3)


def frame_rows(rows: dict[str, PoseTelemetry]) -> dict[str, PoseTelemetry]:
    """The rows by their last name, for video frames.

    A frame is named by its output name (``100MEDIA_DJI_0005_f000012``), so folders in a row's name
    (``frames/DJI_0005_f000012.png``) do not count for it.
    """
    return {key.rsplit("/", 1)[-1]: row for key, row in rows.items()}


def _table(csv: StrPath | TelemetryCsv | None) -> TelemetryCsv | None:
    """The CSV's rows: a run's shared :class:`TelemetryCsv` as it is, a path read here."""
    return csv if isinstance(csv, TelemetryCsv) or csv is None else TelemetryCsv.read(csv)


def source_kind(provenance: str) -> str:
    """The kind of source a provenance names: ``XMP``, ``EXIF``, or the CSV's or SRT's file name."""
    for marker in (" XMP ", " EXIF "):
        if marker in provenance:
            return marker.strip()
    for marker in (" line ", " subtitle"):
        if marker in provenance:
            return provenance.split(marker, 1)[0]
    return provenance


def fall_back(error: Exception, what: str, strict: bool) -> None:
    """One file's telemetry could not be read: an error with ``strict``, else one warning (``what``: its kind)."""
    if strict:
        raise TelemetryError(f"{error} (stopped by --strict_telemetry)") from error
    warnings.warn(f"{error}; this {what}'s telemetry is not used, the network estimates its pose "
                  f"({STRICT_HINT})", TelemetryWarning, stacklevel=3)


def images_telemetry(paths: Iterable[StrPath], csv_path: StrPath | TelemetryCsv | None = None, *,
                     read_metadata: bool = True, sensor_width_mm: float | None = None,
                     strict: bool = False,
                     priors: Sequence[PoseTelemetry] | None = None) -> tuple[list[PoseTelemetry], TelemetryReport]:
    """Per image its CSV row, each unknown component from the image's own metadata; and the run's report.

    ``priors``: per image what is already known (the Python API's prior), winning over its CSV row and its
    metadata; a note on a component it gives (an XMP height below 1 m left unknown) is not warned about.

    An image whose metadata cannot be read (a damaged XMP or EXIF block, an impossible DJI value) falls back to
    the network with one warning, or stops the run with ``strict``. CSV errors always stop it. CSV names that
    match no image are warned about here when ``csv_path`` is a path; a :class:`TelemetryCsv` the run's inputs
    share is only marked (its owner warns once, after the last input).
    """
    image_paths = [Path(p) for p in paths]
    given = list(priors) if priors is not None else None
    if given is not None and len(given) != len(image_paths):
        raise ValueError(f"{len(given)} priors for {len(image_paths)} images")
    table, shared = _table(csv_path), isinstance(csv_path, TelemetryCsv)
    report = TelemetryReport("image")
    out: list[PoseTelemetry] = []
    notes: dict[str, dict[str, str]] = {}
    served: dict[str, set[Path]] = {}  # row key -> the images it serves
    for k, p in enumerate(image_paths):
        key = table.row_for_image(p) if table is not None else None
        row = table.rows[key] if table is not None and key is not None else PoseTelemetry()
        if key is not None:
            served.setdefault(key, set()).add(p.absolute())
        if given is not None:
            row = given[k].merged(row)
        meta = PoseTelemetry()
        if read_metadata and not all(row.known()):
            try:
                meta, image_notes = image_telemetry(p, sensor_width_mm)
            except TelemetryError as exc:
                fall_back(exc, "image", strict)
                report.fell_back.append(p.name)
            else:
                used = {k: v for k, v in image_notes.items() if not row.known()[POSE_KEYS.index(k)]}
                if used:
                    notes[p.name] = used
        out.append(row.merged(meta))
        report.add(out[-1])
    if table is not None:
        table.match_images(served)
        if not shared:
            table.warn_unmatched()
        if shared_rows := {key: images for key, images in served.items() if len(images) > 1}:
            key, images = next(iter(shared_rows.items()))
            warnings.warn(f"{table.path}: {len(shared_rows)} row(s) serve several images of one name in different "
                          f"folders, e.g. `{key}` ({table.rows[key].source}) for {first_few(sorted(map(str, images)))}"
                          "; name each row by folder and file (100MEDIA/DJI_0001.JPG) to give each its own",
                          TelemetryWarning, stacklevel=2)
    warn_notes(notes, stacklevel=2)
    return out, report


def telemetry_for_images(paths: Iterable[StrPath], csv_path: StrPath | None = None, *, read_metadata: bool = True,
                         sensor_width_mm: float | None = None, strict: bool = False) -> list[PoseTelemetry]:
    """Telemetry for each image: its CSV row, each unknown component falling back to the image's metadata.

    A CSV row matches an image when its ``name``, with or without extension, equals the image's file name
    or stem (case-sensitive). CSV names that match no image give one :class:`TelemetryWarning` naming the
    CSV, their count and the first few. ``read_metadata=False`` reads no image metadata (CSV only). An image
    whose metadata cannot be read gets none from it, with one warning (an error with ``strict``).

    Raises:
        TelemetryError: see :func:`read_telemetry_csv`; with ``strict``, :func:`telemetry_from_image`'s errors.
    """
    return images_telemetry(paths, csv_path, read_metadata=read_metadata, sensor_width_mm=sensor_width_mm,
                            strict=strict)[0]


def video_telemetry(video: Path, frames: Sequence[int] | None, srt_path: StrPath | None = None,
                    csv_path: StrPath | TelemetryCsv | None = None, *, size: tuple[int, int] | None = None,
                    fps: float | None = None, strict: bool = False,
                    name: str | None = None) -> tuple[dict[int, PoseTelemetry], TelemetryReport]:
    """Per frame to be predicted (``frames``), its telemetry: a CSV row, each unknown component from the SRT.

    The CSV names frames as their outputs are named (``DJI_0005_f000012``); its names that match no frame of the
    video are warned about as :func:`images_telemetry` says. ``fps``: the video's frame rate, to place the SRT's
    subtitles on frames by their timing (:func:`read_srt`). An SRT that cannot be read falls back to the network
    with one warning (an error with ``strict``); one that covers fewer frames than are predicted gives one warning
    naming the frames left to the network. ``size``: the video's ``(width, height)``;
    ``frames`` None: the video's frame count is not known, every frame the SRT or the CSV names. ``name``: the
    frames' output name before ``_f<frame>`` (default: the video's stem; a video found by a pattern in a sub-folder
    is ``100MEDIA_DJI_0005``), by which the CSV names them.
    """
    report = TelemetryReport("frame")
    srt: dict[int, PoseTelemetry] = {}
    if srt_path is not None:
        width, height = size if size is not None else (None, None)
        try:
            srt = read_srt(srt_path, width, height, fps=fps if fps and fps > 0 else None)
        except (ValueError, OSError) as exc:  # TelemetryError is a ValueError; so is "no frame rate"
            fall_back(exc, "video", strict)
            report.fell_back.append(Path(srt_path).name)
    table, shared = _table(csv_path), isinstance(csv_path, TelemetryCsv)
    rows = frame_rows(table.rows) if table is not None else {}
    prefix = same_text(video.stem if name is None else name)  # the CSV names frames as their outputs are named
    frame_name = re.compile(re.escape(prefix) + r"_f(\d{6,})")
    if frames is None:
        named = (frame_name.fullmatch(k) for k in rows)
        frames = sorted(set(srt) | {int(m.group(1)) for m in named if m is not None})
    out: dict[int, PoseTelemetry] = {}
    for frame in frames:
        telemetry = rows.get(f"{prefix}_f{frame:06d}", PoseTelemetry()).merged(srt.get(frame, PoseTelemetry()))
        report.add(telemetry)
        if any(telemetry.known()):
            out[frame] = telemetry
    if any(any(t.known()) for t in srt.values()):
        missing = [f for f in frames if f not in srt]
        if missing:
            warnings.warn(f"{srt_path}: its subtitles cover frames up to {max(srt)} of {video.name}; {len(missing)} "
                          f"of the {len(frames)} frame(s) predicted (the first: {missing[0]}) have none, the network "
                          "estimates their pose (is it this video's SRT?)", TelemetryWarning, stacklevel=2)
    if table is not None:
        table.match_video(video, frame_name, prefix)
        if not shared:
            table.warn_unmatched()
    return out, report
