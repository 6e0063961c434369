"""Progress and quiet: a progress bar for people at a terminal, none of Lightning's tips and foreign warnings.

:func:`progress_bar` shows images done, images/s and the time left (tqdm, on stderr) when stdout and stderr are
terminals and not ``quiet``; :func:`quiet_lightning` drops Lightning's advertising tips ("💡 Tip: ... litlogger"),
its note on callbacks a checkpoint was trained with ("Please add the following callbacks") and a deprecation
warning Lightning raises inside itself, which say nothing about the user's run.
"""

from __future__ import annotations

import logging
import sys
import warnings
from typing import Any

FOREIGN_WARNINGS = (
    r"(?s).*Please add the following callbacks",  # callbacks of training, restored into predict / test
    r"(?s).*isinstance\(treespec, LeafSpec\)",  # Lightning's own use of a torch API it deprecated
)
"""Warnings raised inside Lightning that a user can do nothing about (regular expressions)."""
RANK_ZERO_LOGGER = "lightning.pytorch.utilities.rank_zero"


class _NoTips(logging.Filter):
    """Drops Lightning's "💡 Tip:" lines (advertising litlogger / litmodels)."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.getMessage()).startswith("💡 Tip")


_NO_TIPS = _NoTips()


def quiet_lightning() -> None:
    """No Lightning tips and no :data:`FOREIGN_WARNINGS` in this process (idempotent)."""
    logger = logging.getLogger(RANK_ZERO_LOGGER)
    if _NO_TIPS not in logger.filters:
        logger.addFilter(_NO_TIPS)
    for pattern in FOREIGN_WARNINGS:
        warnings.filterwarnings("ignore", message=pattern)


def quiet_notes(quiet: bool) -> None:
    """With ``quiet``, Lightning's informational lines (the telemetry summary, notes) are not shown."""
    logging.getLogger(RANK_ZERO_LOGGER).setLevel(logging.WARNING if quiet else logging.NOTSET)


def show_progress(quiet: bool = False) -> bool:
    """Whether to draw a progress bar: not ``quiet``, and stdout and stderr are terminals."""
    return not quiet and sys.stdout.isatty() and sys.stderr.isatty()


def progress_bar(total: int | None, quiet: bool = False, unit: str = "image") -> Any:
    """A tqdm bar on stderr counting ``unit`` s: the rate in units/s, the time left when ``total`` is known.

    Disabled when :func:`show_progress` says so. Use as a context manager, ``update(n)`` as work is done.
    """
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, disable=not show_progress(quiet), file=sys.stderr, dynamic_ncols=True,
                smoothing=0.1, desc="predict")
