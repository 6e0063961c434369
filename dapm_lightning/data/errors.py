"""Errors that name the files at fault, and how a loader leaves out a file that fails after the scan."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any


class DatasetError(ValueError):
    """A data set has problems; ``problems`` lists every one as ``"<file>: <what is wrong>"``."""

    def __init__(self, root: object, problems: Sequence[str], *, shown: int = 50, fix: str | None = None) -> None:
        self.problems = list(problems)
        self.fix = fix
        """The fix when it is not to correct or leave out the files listed (a missing folder, a wrong root)."""
        listed = "\n  ".join(self.problems[:shown])
        more = f"\n  ... and {len(self.problems) - shown} more" if len(self.problems) > shown else ""
        super().__init__(f"{root}: {len(self.problems)} problem(s) found:\n  {listed}{more}")


EVERY_FILE_SKIPPED_FIX = ("Fix: correct or replace the files listed: on_bad_file is skip already and it left out "
                          "every one, so no file is left to load.")
"""The fix when ``on_bad_file="skip"`` left out every file (skipping more cannot help)."""

MISSING = "missing (deleted or moved after the data set was scanned)"
"""What a file that went away after the scan is reported as (not as "cannot be decoded")."""


class BadFileError(ValueError):
    """One file of a data set cannot be used when its sample is loaded: missing, unreadable, or damaged.

    The message is ``"<file>: <what is wrong>"``; ``missing`` says whether the file is gone (deleted or moved
    after the data set was scanned). With ``on_bad_file="skip"`` a loader leaves the sample out (see
    :class:`SkipsBadFiles`).
    """

    def __init__(self, path: str | Path, reason: str | None = None, *, missing: bool = False) -> None:
        if reason is None:  # one message, as a DataLoader rebuilds an error raised in a worker: keep the type
            self.path, self.reason, self.missing = "", str(path), MISSING in str(path)
            super().__init__(str(path))
            return
        self.path, self.reason, self.missing = str(path), reason, missing
        super().__init__(f"{path}: {reason}")


def unreadable(path: str | Path, what: str = "cannot be decoded as an image") -> BadFileError:
    """The error for a file that failed to load: missing, not readable, or else ``what`` (damaged).

    A decoder that returns nothing (OpenCV's ``imread``) does not say why; this looks at the file.
    """
    try:
        Path(path).stat()
    except FileNotFoundError:
        return BadFileError(path, MISSING, missing=True)
    except OSError as error:
        return BadFileError(path, f"cannot be read ({error.strerror or error})")
    if not os.access(path, os.R_OK):
        return BadFileError(path, "cannot be read (no read permission)")
    return BadFileError(path, what)


@dataclass(frozen=True)
class SkippedFile:
    """In a loader's list of samples, a sample left out because its file failed (``on_bad_file="skip"``).

    :func:`~dapm_lightning.data.datamodules.collate_samples` drops it and lists ``problem`` under the batch's
    ``skipped``; the data module warns once per file.
    """

    problem: str


class SkipsBadFiles:
    """Mixin of a map-style data set whose loader leaves out samples whose files fail after the scan.

    With ``on_bad_file == "skip"``, :meth:`__getitems__` (what a ``DataLoader`` calls for a batch) puts a
    :class:`SkippedFile` in place of each sample whose loading raises :class:`BadFileError`. The batch is then
    smaller; nothing is put in a left-out sample's place, except when every sample of a batch fails: the next
    sample of the data set that loads then stands in (and is listed as such), so that a step always has a
    sample. Indexing (``dataset[i]``) always raises.
    """

    on_bad_file: str

    def __getitems__(self, keys: Sequence[Any]) -> list[Any]:
        get: Any = self  # a data set: indexable, with a length
        if self.on_bad_file != "skip":
            return [get[key] for key in keys]
        loaded: list[Any] = []
        for key in keys:
            try:
                loaded.append(get[key])
            except BadFileError as error:
                loaded.append(SkippedFile(f"{error}; left out (on_bad_file: skip)"))
        if keys and all(isinstance(item, SkippedFile) for item in loaded):
            loaded += self._stand_in(keys[-1], [item.problem for item in loaded])
        return loaded

    def _stand_in(self, last: Any, problems: list[str]) -> list[Any]:
        """The first sample after ``last`` (same epoch) that loads, and a note; a :class:`DatasetError` when none."""
        get: Any = self
        epoch, index = (int(last[0]), int(last[1])) if isinstance(last, tuple) else (None, int(last))
        for step in range(1, len(get)):
            other = (index + step) % len(get)
            try:
                sample = get[other if epoch is None else (epoch, other)]
            except BadFileError as error:
                problems.append(str(error))
                continue
            return [SkippedFile(f"{sample['name']}: stands in for a batch whose every file failed (on_bad_file: "
                                "skip)"), sample]
        raise DatasetError(getattr(self, "root", "data set"), [*problems, "no file of the data set loads any more "
                                                               "(on_bad_file: skip leaves out single files)"],
                           fix=EVERY_FILE_SKIPPED_FIX)
