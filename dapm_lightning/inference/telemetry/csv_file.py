"""The telemetry CSV the user writes: ``name,height_m,pitch_deg,roll_deg,fov_deg``, one row per image."""

from __future__ import annotations

import codecs
import csv
import difflib
import io
import math
import unicodedata
import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from dapm_lightning.data.uapd import IMAGE_SUFFIXES
from dapm_lightning.geometry.constants import POSE_FIELDS, POSE_KEYS
from dapm_lightning.inference.telemetry.pose import (
    PoseTelemetry,
    StrPath,
    TelemetryError,
    TelemetryWarning,
    limit_error,
)
from dapm_lightning.training.checkpoint_files import IMAGE_HEADS, looks_like_onnx

CSV_COLUMNS: tuple[str, ...] = ("name", *POSE_FIELDS)
"""The telemetry CSV's header; only ``name`` is required, a missing value column means unknown."""

CSV_NAME_SUFFIXES: tuple[str, ...] = (*IMAGE_SUFFIXES, ".dng")
"""Extensions stripped from a CSV ``name``: the images the project reads and the raw DNGs a flight log may
name (anything else after a dot is part of the name)."""

_CSV_FIX = {
    "height": "write the camera's height above the ground in metres (> 0)",
    "pitch": "write the pitch in degrees (0 = horizontal, -90 = nadir)",
    "roll": "write the roll in degrees (positive = horizon's right end up)",
    "fov": "write the horizontal field of view in degrees (0 < fov < 180)",
}


def same_text(name: str) -> str:
    """``name`` in Unicode's composed form (NFC): ``föto`` typed in a CSV matches a file macOS named decomposed."""
    return unicodedata.normalize("NFC", name)


def _csv_key(name: str) -> str:
    """The image a CSV ``name`` refers to: its ``/``-separated path, a known image extension stripped, composed.

    ``DJI_0001.JPG`` -> ``DJI_0001``; ``100MEDIA/DJI_0001.JPG`` (Windows separators alike) -> ``100MEDIA/DJI_0001``
    (the folders tell apart images of one name in several folders: :func:`row_for_image`); letters with accents
    in composed form (:func:`same_text`), as image paths are compared.
    """
    name = same_text(name)
    parts = [part for part in name.replace("\\", "/").split("/") if part not in ("", ".")] or [name]
    stem, dot, suffix = parts[-1].rpartition(".")
    if dot and stem and f".{suffix.lower()}" in CSV_NAME_SUFFIXES:
        parts[-1] = stem
    return "/".join(parts)


def rows_by_stem(rows: Mapping[str, PoseTelemetry]) -> dict[str, list[str]]:
    """The keys of :func:`read_telemetry_csv`'s rows grouped by the image stem they end in."""
    grouped: dict[str, list[str]] = {}
    for key in rows:
        grouped.setdefault(key.rsplit("/", 1)[-1], []).append(key)
    return grouped


def row_for_image(path: Path, rows: Mapping[str, PoseTelemetry], by_stem: Mapping[str, list[str]]) -> str | None:
    """The key of the row naming the image ``path``, None when no row does.

    A row names an image by its stem; a row that also names folders names only an image in its last folder
    (``100MEDIA/DJI_0001`` names ``.../100MEDIA/DJI_0001.JPG``, not ``.../101MEDIA/DJI_0001.JPG``), and a row of
    the bare name any image of that name. Of the rows that name the image, the one sharing the most trailing folders
    with its path is its (``D:/card/DCIM/101MEDIA/DJI_0001`` and ``DCIM/101MEDIA/DJI_0001`` share two with
    ``/data/DCIM/101MEDIA/DJI_0001.JPG``).

    Raises:
        TelemetryError: two rows of different values share as many folders with the image's path, so the CSV does
            not say which is the image's (naming both).
    """
    keys = by_stem.get(same_text(path.stem), [])
    if not keys:
        return None
    folders = [same_text(folder) for folder in path.absolute().parent.parts[::-1]]

    def shared(key: str) -> int:
        count = 0
        for mine, theirs in zip(folders, key.split("/")[-2::-1]):
            if mine != theirs:
                break
            count += 1
        return count

    naming = {key: shared(key) for key in keys if "/" not in key or shared(key) > 0}
    if not naming:
        return None
    best = max(naming.values())
    chosen = [key for key, count in naming.items() if count == best]
    if any(not np.array_equal(rows[chosen[0]].values(), rows[key].values(), equal_nan=True) for key in chosen[1:]):
        lines = ", ".join(f"`{key}` ({rows[key].source})" for key in chosen)
        raise TelemetryError(f"{path}: the telemetry CSV has rows of different values that fit this image equally "
                             f"({lines}); name the rows by more of their folders")
    return chosen[0]


def _show(t: PoseTelemetry) -> str:
    """The row's values as ``height_m=45.2, pitch_deg=, ...`` (empty = unknown), for error messages."""
    return ", ".join(f"{k}={'' if math.isnan(v) else f'{v:g}'}" for k, v in zip(POSE_FIELDS, t.values().tolist()))


_BINARY_HEADS = {b"PK\x03\x04": "a zip archive (a PyTorch checkpoint is one)", b"\x80": "a pickle (a checkpoint)",
                 **IMAGE_HEADS}


def _binary_kind(data: bytes) -> str | None:
    """What a file that is not text is, by its first bytes (a checkpoint, an image, an ONNX model), or None."""
    if looks_like_onnx(data[:16]):
        return "an ONNX model"
    return next((kind for head, kind in _BINARY_HEADS.items() if data.startswith(head)), None)


def _csv_text(path: Path) -> str:
    """The file as text: UTF-8 (a byte-order mark allowed), or UTF-16 with its mark (Excel's "Unicode text")."""
    data = path.read_bytes()
    if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
        return data.decode("utf-16")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        kind = _binary_kind(data)
        if kind is not None:
            raise TelemetryError(f"{path}: {kind}, not a telemetry table; --telemetry takes a CSV with the header "
                                 "name,height_m,pitch_deg,roll_deg,fov_deg (or a video's .SRT)") from None
        line = data[:error.start].count(b"\n") + 1
        raise TelemetryError(f"{path}: not UTF-8 text (byte 0x{data[error.start]:02x} on line {line}); save it as "
                             "CSV UTF-8 (in a spreadsheet: CSV UTF-8, comma-delimited)") from None


def read_telemetry_csv(path: StrPath) -> dict[str, PoseTelemetry]:
    """Per-image telemetry from a CSV with header ``name,height_m,pitch_deg,roll_deg,fov_deg``, keyed by stem.

    ``name`` is the image's file name with or without its extension (``DJI_0001.JPG`` or ``DJI_0001``), and may
    name its folders (``101MEDIA/DJI_0001.JPG``, keyed ``101MEDIA/DJI_0001``), which tell apart images of one name
    (:func:`row_for_image`). A missing value column or an empty cell means unknown. Columns may come in any
    order; other columns are ignored with a warning. Blank lines are skipped. Columns are comma-separated, or
    tab-separated when the header holds tabs and no comma (a spreadsheet's "Unicode text" or "Text (Tab delimited)").

    A file without any value (only its header, or every value cell empty) gives a "no usable telemetry" warning.

    Raises:
        TelemetryError: no ``name`` column (names the expected header); a row with a (non-empty) cell beyond the
            header's columns; a value that is not a number or is
            physically impossible (height <= 0 or not finite, |pitch| > 180, |roll| > 180, fov outside
            (0, 180)), naming the file, line and column; an empty name; the same name twice with different
            values (naming both lines); text that is neither UTF-8 nor UTF-16 with a byte-order mark (naming the
            line).
    """
    path = Path(path)
    header_hint = f"the first line must be the header `{','.join(CSV_COLUMNS)}` (value columns optional)"
    text = _csv_text(path)
    first = text.split("\n", 1)[0]
    # a spreadsheet's "Unicode text" (Excel: UTF-16, like its "Text (Tab delimited)") separates columns by tabs
    delimiter = "\t" if "\t" in first and "," not in first else ","
    with io.StringIO(text, newline="") as stream:
        reader = csv.reader(stream, delimiter=delimiter)
        header = next(reader, None)
        if header is None:
            raise TelemetryError(f"{path}: the file is empty; {header_hint}")
        columns = [c.strip().lower() for c in header]
        if "name" not in columns:
            if path.suffix.lower() == ".srt":
                raise TelemetryError(f"{path}: a DJI SRT gives the telemetry of the video it was recorded with, "
                                     "not of images; predict that video (its SRT beside it is found, or give it "
                                     f"as --telemetry), or give images a CSV: {header_hint}")
            hint = " (it looks ';'-separated: save it comma-separated)" if ";" in ",".join(header) else ""
            raise TelemetryError(f"{path}: no `name` column in the header {','.join(header)!r}{hint}; {header_hint}")
        for col in set(columns):
            if col and columns.count(col) > 1:
                raise TelemetryError(f"{path}: column `{col}` appears {columns.count(col)} times in the header; "
                                     "keep one")
        index = {c: i for i, c in enumerate(columns)}
        unknown = [c for c in columns if c and c not in CSV_COLUMNS]
        value_columns = [c for c in CSV_COLUMNS if c != "name"]
        meant = {c: close[0] for c in unknown
                 if (close := difflib.get_close_matches(c, value_columns, n=1, cutoff=0.6))}
        guesses = "".join(f"; {c}: did you mean {m}?" for c, m in meant.items())
        if unknown and not any(c in columns for c in value_columns):  # no image would get the telemetry asked for
            raise TelemetryError(f"{path}: none of the telemetry columns {', '.join(value_columns)} in the header "
                                 f"{','.join(header)!r}{guesses}; {header_hint}")
        if unknown:
            warnings.warn(f"{path}: column(s) {', '.join(unknown)} ignored (the telemetry columns are "
                          f"{','.join(CSV_COLUMNS)}){guesses}", TelemetryWarning, stacklevel=2)
        out: dict[str, PoseTelemetry] = {}
        first_line: dict[str, int] = {}
        for row in reader:
            line = reader.line_num
            cells = [c.strip() for c in row]
            if not any(cells):
                continue

            def cell(col: str, cells: list[str] = cells) -> str:
                i = index.get(col)
                return cells[i] if i is not None and i < len(cells) else ""

            name = cell("name")
            where = f"{path}, line {line}"
            if any(cells[len(header):]):  # a cell beyond the header's columns: shifted or unquoted values
                raise TelemetryError(f"{where}: {len(cells)} cells but the header has {len(header)} columns "
                                     f"({','.join(header)}); remove the extra cells, add their columns to the header, "
                                     "or quote a value that holds the separator")
            if not name:
                raise TelemetryError(f"{where}: empty `name`; write the image's file name (with or without "
                                     "its extension), or delete the row")
            values: list[float] = []
            for key, col in zip(POSE_KEYS, POSE_FIELDS):
                text = cell(col)
                if not text:
                    values.append(math.nan)
                    continue
                try:
                    value = float(text)
                except ValueError:
                    raise TelemetryError(f"{where}, column {col}: {text!r} is not a number; {_CSV_FIX[key]}, "
                                         "or leave the cell empty for unknown") from None
                if (why := limit_error(key, value)) is not None:
                    raise TelemetryError(f"{where}, column {col}: {text} {why}; {_CSV_FIX[key]}, or leave the "
                                         "cell empty for unknown")
                values.append(value)
            key = _csv_key(name)
            telemetry = PoseTelemetry.from_values(values, f"{path.name} line {line}")
            if key in out:
                previous = out[key]
                if not np.array_equal(previous.values(), telemetry.values(), equal_nan=True):
                    raise TelemetryError(f"{where}: `{name}` is already on line {first_line[key]} with different "
                                         f"values ({_show(previous)} there, {_show(telemetry)} here); keep one "
                                         "row per image")
                continue
            out[key], first_line[key] = telemetry, line
    if not any(np.isfinite(t.values()).any() for t in out.values()):  # as an SRT without any field read
        detail = "every value cell is empty" if out else "no row under the header"
        warnings.warn(f"{path}: no usable telemetry in the file: {detail}; the network estimates the pose (write one "
                      "row per image under the header)", TelemetryWarning, stacklevel=2)
    elif (radians := angles_look_like_radians(out)) is not None:
        degrees_already = ("a zoom camera that narrow (FoV of 3.14 degrees or less)" if "fov_deg" in radians else
                           "a camera held within 1.57 degrees of level all flight")
        warnings.warn(f"{path}: {radians}, as radians would be; the columns are degrees (pitch_deg, roll_deg, "
                      "fov_deg): if they are radians, convert them (degrees = radians x 57.2958); "
                      f"{degrees_already} is degrees already: keep them", TelemetryWarning, stacklevel=2)
    return out


def angles_look_like_radians(rows: Mapping[str, PoseTelemetry]) -> str | None:
    """Which of the angles in ``rows`` all lie within +-pi as radians would, or None when they do not look so.

    A FoV of at most pi degrees in every row (a strong telephoto), or, without a FoV, a pitch within +-pi/2 in every
    row that averages at least 0.5 in size (a camera held within 3 degrees of level all flight), besides every
    roll within +-pi: degrees that small are rare from a drone, radians that large are every survey's.
    """
    def known(values: list[float]) -> list[float]:
        return [v for v in values if math.isfinite(v)]

    pitch = known([t.pitch_deg for t in rows.values()])
    roll = known([t.roll_deg for t in rows.values()])
    fov = known([t.fov_deg for t in rows.values()])
    if any(abs(v) > math.pi for v in pitch + roll) or not (pitch or fov):
        return None
    if fov and max(fov) <= math.pi:
        return f"every fov_deg lies within (0, pi] ({min(fov):g} to {max(fov):g}), and every pitch and roll within +-pi"
    if not fov and pitch and all(abs(v) <= math.pi / 2 + 1e-6 for v in pitch) and \
            sum(abs(v) for v in pitch) / len(pitch) >= 0.5:
        return f"every pitch_deg lies within +-pi/2 ({min(pitch):g} to {max(pitch):g}), and every roll within +-pi"
    return None
