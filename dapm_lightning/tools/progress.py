"""Progress bars for the long commands (synth, doctor, export, predict): on a terminal only, off with ``--quiet``.

``tqdm`` (Lightning's own progress bar uses it) shows the count, the rate and the time left on stderr; where
stderr is not a terminal (a job log, a pipe, CI) nothing is drawn, so logs stay one line per event.
"""

from __future__ import annotations

import sys
from typing import Any


class NoProgress:
    """What :func:`progress_bar` gives when nothing is drawn: the same calls, doing nothing."""

    def update(self, count: int = 1) -> None:
        """Nothing to draw."""

    def set_postfix_str(self, text: str) -> None:
        """Nothing to draw."""

    def close(self) -> None:
        """Nothing to close."""

    def __enter__(self) -> NoProgress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def progress_bar(total: int | None, what: str, unit: str = "image", quiet: bool = False) -> Any:
    """A ``tqdm`` bar of ``total`` ``unit``s labelled ``what`` on a terminal; else :class:`NoProgress`.

    Args:
        total: how many steps (None: unknown, a count and a rate only).
        what: the label, e.g. ``"rendering"``.
        unit: the name of one step, shown in the rate (``images/s``).
        quiet: never draw.
    """
    if quiet or not sys.stderr.isatty():
        return NoProgress()
    from tqdm import tqdm

    return tqdm(total=total, desc=what, unit=unit, unit_scale=False, dynamic_ncols=True, leave=False)


__all__ = ["NoProgress", "progress_bar"]
