"""Imported first by the loaders' fork server (:func:`~dapm_lightning.data.workers.loader_context`), and only there.

The fork server is a child of the training process in its process group, so a SIGTERM to the whole job (SLURM,
``timeout``) reaches it too. Had it died of it, the workers it forked would take its death for their training
process's (PyTorch's worker watchdog follows the parent process) and stop serving batches, and the run would
fail on its next batch instead of stopping cleanly after the step (docs/long_jobs.md). The server ignores the
signal; it still ends with the training process, whose end closes the pipe it waits on. Workers forked from it
set their own handler (:func:`~dapm_lightning.data.workers.loader_worker_init`).

The server is ``multiprocessing``'s, one a process, and starts every process of the ``forkserver`` start method,
not only loader workers (a user's ``Pool``, ``ProcessPoolExecutor``...; Python 3.14's default start method):
those get the default SIGTERM back as they start (:func:`_restore_sigterm`), so that ``terminate()`` ends them.
"""

from __future__ import annotations

import functools
import multiprocessing
import multiprocessing.util
import signal
import sys
from typing import Any


def in_fork_server() -> bool:
    """Whether this process is multiprocessing's fork server (started as ``python -c 'from multiprocessing...'``)."""
    return sys.argv[:1] == ["-c"] and "multiprocessing.forkserver" in sys.modules


def _is_loader_worker(process: Any) -> bool:
    """Whether ``process`` is a worker of this project's loaders (its ``worker_init_fn`` sets its SIGTERM handler)."""
    from dapm_lightning.data.workers import loader_worker_init

    return any(isinstance(arg, functools.partial) and arg.func is loader_worker_init
               for arg in getattr(process, "_args", ()))


def _restore_sigterm(_: object) -> None:
    """In a process the server forked, as it starts: the default SIGTERM back, unless it is a loader worker."""
    if not _is_loader_worker(multiprocessing.current_process()):
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


class _Registration:
    """The object ``multiprocessing.util.register_after_fork`` keeps a weak reference to."""


_REGISTRATION = _Registration()

if in_fork_server():
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    multiprocessing.util.register_after_fork(_REGISTRATION, _restore_sigterm)
