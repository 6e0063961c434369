"""The poses table (``poses.csv`` / ``poses.json``): one row per image, merged under a lock with earlier runs'."""

from __future__ import annotations

import csv
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
    """
    path = out / "poses.csv"
    with exclusive_lock(path):
        merged: dict[str, dict[str, Any]] = {}
        if path.is_file():
            with path.open(newline="", encoding="utf-8") as handle:
                merged = {row["name"]: {k: v for k, v in row.items() if k is not None}  # no cells past the header
                          for row in csv.DictReader(handle) if row.get("name")}
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
