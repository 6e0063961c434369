"""No Lightning tips and foreign warnings: what Lightning prints that says nothing about the user's run.

:func:`quiet_lightning` drops its advertising tips ("💡 Tip: ... litlogger"), its note on callbacks a checkpoint
was trained with ("Please add the following callbacks"), a deprecation warning Lightning raises inside itself, and
its warning that a mid-epoch resume is unreliable (the data modules resume exactly), and its hint on a
``--ckpt_path last`` that finds nothing (the CLI says the run starts from scratch).
"""

from __future__ import annotations

import logging
import warnings

FOREIGN_WARNINGS = (
    r"(?s).*Please add the following callbacks",  # callbacks of training, restored into predict / test
    r"(?s).*isinstance\(treespec, LeafSpec\)",  # Lightning's own use of a torch API it deprecated
    # mid-epoch resumes are exact: the data modules save the position and their sampler skips to it
    # (docs/long_jobs.md); Lightning asks the DataLoader itself for a state, which it does not need
    r"(?s).*your dataloader is not resumable",
    # `--ckpt_path last` with nothing to resume: its hint (`save_last=True`) names a setting LastCheckpoint replaces;
    # the CLI says instead that the run starts from scratch
    r"(?s).*there is no last checkpoint available",
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
