"""Loader workers and SIGTERM: a signal to the whole job reaches the training process, not the workers.

SLURM sends SIGTERM to every process of a job step before it pre-empts or ends it (``timeout`` and a terminal
signal the whole process group): to the data loader workers too. PyTorch's workers die of it, and the training
process then stops with a DataLoader error (status 1) instead of saving ``last.ckpt`` and exiting with 143.
:func:`loader_worker_init` makes every worker ignore a SIGTERM from outside; the training process decides, and
its workers stop when it stops them. One SIGTERM still ends a worker: the one its process sends it while it exits
(``multiprocessing`` terminates its daemonic children, then joins them).
"""

from __future__ import annotations

import atexit
import multiprocessing
import os
import signal
from functools import partial
from types import FrameType
from typing import Any

from lightning.fabric.utilities.seed import pl_worker_init_function

_EXITING: list[Any] = []
"""One event per loader with workers, set when this process exits (:func:`_exiting`). Kept for the process's life
(a few bytes each): a worker can outlive its loader's Python objects (one whose shutdown it ignored while it
was busy), and at exit it must still hear that this time SIGTERM is meant."""
_AT_EXIT: list[bool] = []


def _exiting() -> None:
    """At exit, before ``multiprocessing`` terminates the workers (``atexit`` runs the later registration first)."""
    for event in list(_EXITING):
        event.set()


def loader_worker_init(worker_id: int, rank: int = 0, exiting: Any = None) -> None:
    """Start of every loader worker: SIGTERM from outside ignored; seeded as Lightning would when asked to.

    Args:
        worker_id: the worker's number in its loader.
        rank: the process's global rank.
        exiting: an event the training process sets when it exits (:func:`worker_init_fn`): a SIGTERM then
            ends the worker (``multiprocessing`` terminating it), before it is ignored.
    """

    def on_sigterm(signum: int, frame: FrameType | None) -> None:
        if exiting is not None and exiting.is_set():
            os._exit(0)

    signal.signal(signal.SIGTERM, on_sigterm)
    if int(os.environ.get("PL_SEED_WORKERS", 0)):  # seed_everything(workers=True): Lightning adds its own
        pl_worker_init_function(worker_id, rank)  # worker_init_fn only to loaders without one


def worker_init_fn(rank: int = 0) -> partial[None]:
    """The ``worker_init_fn`` of a loader: :func:`loader_worker_init` with a fresh exit event of this process.

    Args:
        rank: the process's global rank (for Lightning's worker seeding).

    Returns:
        The function a ``DataLoader`` calls at the start of each worker.
    """
    if not _AT_EXIT:  # registered after multiprocessing's own exit handler (imported with torch): runs before it
        atexit.register(_exiting)
        _AT_EXIT.append(True)
    exiting = multiprocessing.Event()
    _EXITING.append(exiting)
    return partial(loader_worker_init, rank=rank, exiting=exiting)


__all__ = ["loader_worker_init", "worker_init_fn"]
