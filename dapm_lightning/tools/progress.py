"""Progress and quiet: a progress bar for people at a terminal, none of Lightning's tips and foreign warnings.

:func:`progress_bar` shows the count done, the rate (images/s) and the time left (tqdm, on stderr) when stdout and
stderr are terminals and not ``quiet``: in a job log, a pipe or CI nothing is drawn, so logs stay one line per
event. Used by ``predict``, ``synth`` and ``doctor``. :func:`~dapm_lightning.training.quiet.quiet_lightning`
drops Lightning's tips and foreign warnings.
"""

from __future__ import annotations

import logging
import sys
from typing import Any

from dapm_lightning.training.quiet import RANK_ZERO_LOGGER
from dapm_lightning.training.quiet import quiet_lightning as quiet_lightning


def quiet_notes(quiet: bool) -> None:
    """With ``quiet``, Lightning's informational lines (the telemetry summary, notes) are not shown."""
    logging.getLogger(RANK_ZERO_LOGGER).setLevel(logging.WARNING if quiet else logging.NOTSET)


def show_progress(quiet: bool = False) -> bool:
    """Whether to draw a progress bar: not ``quiet``, and stdout and stderr are terminals."""
    return not quiet and sys.stdout.isatty() and sys.stderr.isatty()


def progress_bar(total: int | None, quiet: bool = False, unit: str = "image", what: str = "predict") -> Any:
    """A tqdm bar on stderr labelled ``what``, counting ``unit`` s: the rate, and the time left when ``total`` is known.

    Disabled (the same calls, drawing nothing) when :func:`show_progress` says so. Use as a context manager,
    ``update(n)`` as work is done.
    """
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, disable=not show_progress(quiet), file=sys.stderr, dynamic_ncols=True,
                smoothing=0.1, desc=what)
