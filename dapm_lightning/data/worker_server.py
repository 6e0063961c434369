"""Imported first by the loaders' fork server (:func:`~dapm_lightning.data.workers.loader_context`), and only there.

The fork server is a child of the training process in its process group, so a SIGTERM to the whole job (SLURM,
``timeout``) reaches it too. Had it died of it, the workers it forked would take its death for their training
process's (PyTorch's worker watchdog follows the parent process) and stop serving batches, and the run would
fail on its next batch instead of stopping cleanly after the step (docs/long_jobs.md). The server ignores the
signal; it still ends with the training process, whose end closes the pipe it waits on. Workers forked from it
set their own handler (:func:`~dapm_lightning.data.workers.loader_worker_init`).
"""

from __future__ import annotations

import signal
import sys


def in_fork_server() -> bool:
    """Whether this process is multiprocessing's fork server (started as ``python -c 'from multiprocessing...'``)."""
    return sys.argv[:1] == ["-c"] and "multiprocessing.forkserver" in sys.modules


if in_fork_server():
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
