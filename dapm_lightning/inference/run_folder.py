"""Where a prediction run writes: a new folder per run by default, never an earlier run's folder by surprise.

Without an output folder named, each run writes to a new one: ``runs/predict``, then ``runs/predict2``,
``runs/predict3``, ... (the first that does not exist or is empty). A folder named that already holds files is
refused in one line unless ``exist_ok``: then the run adds to it, each of its images' files rewritten together
(:func:`remove_stale_files`) and its rows replacing theirs in the poses table.

A folder a run wrote to is marked as a prediction run's (:data:`OUTPUT_MARKER`, written with its first file), so
that a later run given a folder or pattern that reaches it does not read its pictures back as drone images
(:func:`is_output_folder`, :func:`written_by_predict`).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

DEFAULT_RUN_FOLDER = Path("runs") / "predict"
"""The first run's folder when none is named; later runs add 2, 3, ..."""
PER_IMAGE_FILES = {"depth_npy": "{}_depth.npy", "depth_tiff": "{}_depth.tif", "depth16": "{}_depth16.png",
                   "depth_color": "{}_depth_color.png", "sky": "{}_sky.png", "camera": "{}_camera.json",
                   "points": "{}_points.ply", "npz": "{}.npz"}
"""Each per-image kind's file name, ``NAME`` as ``{}``."""
OUTPUT_MARKER = ".dapm_predict"
"""The hidden file that marks a folder as a prediction run's output (written with the folder's first file)."""
MARKER_TEXT = ("This folder holds the files of a dapm-lightning predict run. predict leaves out the pictures it wrote "
               "here when a folder or pattern given as SOURCE reaches it.\n")
RUN_PICTURES = ("contact_sheet.png",)
"""The run's own pictures, beside the per-image ones (:data:`PER_IMAGE_FILES`) and the videos' ``STEM_depth.mp4``."""


def holds_files(folder: Path) -> bool:
    """Whether ``folder`` exists and holds anything (hidden files included)."""
    return folder.is_dir() and any(folder.iterdir())


def new_run_folder(base: str | Path = DEFAULT_RUN_FOLDER) -> Path:
    """``base``, else ``base2``, ``base3``, ...: the first that does not exist or is an empty folder."""
    base = Path(base)
    folder, number = base, 1
    while folder.exists() and (not folder.is_dir() or holds_files(folder)):
        number += 1
        folder = base.with_name(f"{base.name}{number}")
    return folder


def run_folder(out: str | Path | None, exist_ok: bool = False, option: str = "--out",
               exist_ok_option: str = "--exist_ok") -> Path:
    """The folder a run writes to: ``out``, or a new one per run (:func:`new_run_folder`) when None.

    Raises:
        ValueError: ``out`` already holds files and not ``exist_ok`` (one line naming the way out).
    """
    if out is None:
        return new_run_folder()
    folder = Path(out)
    if not exist_ok and holds_files(folder):
        raise ValueError(f"{option} {folder} already holds files (an earlier run's?): give a new folder, leave "
                         f"{option} out (a new runs/predict<N> per run), or add {exist_ok_option} to add to it")
    return folder


def is_output_folder(folder: Path) -> bool:
    """Whether ``folder`` is a prediction run's output.

    It holds :data:`OUTPUT_MARKER`, or both ``poses.csv`` and ``poses.json`` (a run's tables, also of runs made
    before the marker).
    """
    return (folder / OUTPUT_MARKER).is_file() or ((folder / "poses.csv").is_file()
                                                   and (folder / "poses.json").is_file())


def written_by_predict(name: str) -> bool:
    """Whether a file name is one that predict writes: a per-image picture, the contact sheet, a video preview."""
    suffixes = [pattern.format("") for pattern in PER_IMAGE_FILES.values()] + ["_depth.mp4"]
    return name in RUN_PICTURES or any(name.endswith(suffix) and len(name) > len(suffix) for suffix in suffixes)


def remove_stale_files(out: Path, name: str, written: Iterable[Path]) -> list[Path]:
    """Remove ``NAME``'s per-image files that this run did not write (an earlier run's); returns them.

    So an image's files always come from one run: no depth of an earlier run beside a new ``camera.json``.
    """
    keep = {Path(p).name for p in written}
    removed = []
    for pattern in PER_IMAGE_FILES.values():
        path = out / pattern.format(name)
        if path.name not in keep and path.is_file():
            path.unlink()
            removed.append(path)
    return removed
