"""The poses table (``poses.csv`` / ``poses.json``): one row per image, merged under a lock with earlier runs'."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from dapm_lightning.data.files import (
    exclusive_lock,
    open_atomic,
    write_text,
)
from dapm_lightning.geometry.constants import POSE_FIELDS, POSE_KEYS, pose_field
from dapm_lightning.inference.postprocess import Prediction

POSE_COLUMNS = ["name", *POSE_FIELDS]


def pose_row(prediction: Prediction) -> dict[str, Any]:
    """One poses-table row: the pose used; with telemetry also each component's source and the network's value.

    A row of the network's pose alone gets those columns from :func:`write_poses` when others in the table have them.
    """
    assert prediction.pose is not None
    row: dict[str, Any] = {"name": prediction.name,
                           **{pose_field(k): round(v, 4) for k, v in prediction.pose.items()}}
    if prediction.time_s is not None:  # a video frame: its time in the video
        row["time_s"] = round(prediction.time_s, 3)
    if prediction.pose_source and set(prediction.pose_source.values()) != {"network"}:
        network = prediction.pose_network or prediction.pose
        provenance = prediction.pose_provenance or {}
        for key in POSE_KEYS:
            row[f"{pose_field(key)}_source"] = prediction.pose_source.get(key, "network")
            row[f"{pose_field(key)}_provenance"] = provenance.get(key, "")
            row[f"{pose_field(key)}_network"] = round(network[key], 4)
    return row


def table_columns(rows: Iterable[dict[str, Any]]) -> list[str]:
    """The poses table's columns in their order.

    Name, a video frame's time, the pose (height, pitch, roll, FoV), then per component the sources, the provenance
    and the network's values, then any other column.
    """
    present = {key for row in rows for key in row}
    ordered = ["name", "time_s", *POSE_COLUMNS[1:], *(f"{field}_{kind}" for kind in ("source", "provenance", "network")
                                                      for field in POSE_FIELDS)]
    return [c for c in ordered if c in present or c in POSE_COLUMNS] + sorted(present - set(ordered))


def write_poses(out: Path, rows: list[dict[str, Any]]) -> Path:
    """``poses.csv`` and ``.json``, merged with the folder's earlier ones.

    A row of the same name is replaced, the others are kept (a run added with ``--exist_ok`` adds to the table).
    The read, merge and rewrite hold a lock (:func:`~dapm_lightning.data.files.exclusive_lock`), so runs into
    one folder at once keep every row; both tables are written whole from the same merged rows, so a reader
    never sees half a table and a failed write leaves the earlier tables as they were.

    Raises:
        WriteError: a table could not be written.
        ValueError: the earlier ``poses.csv`` is not a whole poses table (:func:`read_poses`).
    """
    path = out / "poses.csv"
    with exclusive_lock(path):
        merged = read_poses(path)
        merged.update({row["name"]: row for row in rows})
        columns = table_columns(merged.values())
        for row in merged.values():  # rows of images without telemetry: their pose is the network's
            for column in columns[len(POSE_COLUMNS):]:
                if row.get(column) in (None, "") and column.endswith(("_source", "_network")):
                    row[column] = "network" if column.endswith("_source") else row.get(column[:-len("_network")], "")
        with open_atomic(path, "w") as handle:
            writer = csv.DictWriter(handle, fieldnames=columns, restval="")
            writer.writeheader()
            writer.writerows(merged.values())
        values = [{column: row.get(column, "") if _text_column(column) else _number(row.get(column))
                   for column in columns} for row in merged.values()]  # every row with every column, as the CSV
        write_text(out / "poses.json", json.dumps(values, indent=2) + "\n")
    return path


def read_poses(path: Path, option: str = "--out") -> dict[str, dict[str, Any]]:
    """The rows of an earlier run's ``poses.csv`` by name, as text; {} when there is none.

    Checked whole, so that a run adding to the folder (``--exist_ok``) refuses it before writing anything rather
    than replace it and lose its rows.

    Raises:
        ValueError: the file cannot be read, is not UTF-8 text, is empty, is another table (no ``name`` and pose
            columns), or is damaged or cut short (a row without all its cells or its name, no line end after the
            last row); naming the file and the fix (``option``: the setting that names the folder).
    """
    if not path.exists():
        return {}
    try:
        text = path.read_bytes().decode("utf-8-sig")  # a spreadsheet's byte-order mark allowed
    except UnicodeDecodeError as error:
        line = error.object[:error.start].count(b"\n") + 1
        raise _earlier_table_error(path, f"not UTF-8 text (byte 0x{error.object[error.start]:02x} on line {line})",
                                   option) from None
    except OSError as error:
        reason = "permission denied" if isinstance(error, PermissionError) else error.strerror or str(error)
        raise _earlier_table_error(path, f"cannot be read ({reason})", option) from None
    if not text.strip():
        raise _earlier_table_error(path, "empty (cut short?)", option)
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = next(reader)
        if header[:1] != ["name"] or not set(POSE_FIELDS) <= set(header):
            raise _earlier_table_error(path, f"not a poses table (its header {','.join(header)[:80]!r} lacks the "
                                             f"columns {','.join(POSE_COLUMNS)})", option)
        rows: dict[str, dict[str, Any]] = {}
        for cells in filter(None, reader):  # blank lines skipped
            if len(cells) != len(header) or not cells[0]:
                got = "no name" if len(cells) == len(header) else f"{len(cells)} cells, its header {len(header)}"
                raise _earlier_table_error(path, f"damaged or cut short (line {reader.line_num}: {got})", option)
            rows[cells[0]] = dict(zip(header, cells))
    except csv.Error as error:  # a field past the csv module's size limit, ...
        raise _earlier_table_error(path, f"damaged (line {reader.line_num}: {error})", option) from None
    if not text.endswith("\n"):
        raise _earlier_table_error(path, "cut short (no line end after its last row)", option)
    return rows


def _earlier_table_error(path: Path, problem: str, option: str) -> ValueError:
    return ValueError(f"{path}: {problem}; this run would replace that table and lose its rows\nFix: move it out "
                      f"of the folder (or put back an intact copy), or give another {option}")


def _text_column(column: str) -> bool:
    """Whether a column holds text: the name (``000123``, ``20230514_101502`` stay names), sources, provenance."""
    return column == "name" or column.endswith(("_source", "_provenance"))


def _number(value: Any) -> Any:
    """A CSV cell back to a number where it is one (rows merged from an earlier run's file are text); empty: null."""
    if value in (None, ""):
        return None
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value
