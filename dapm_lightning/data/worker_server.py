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

A scheduler's warning signal reaches the whole job too (SLURM's ``--signal``: ``SIGUSR1`` for Lightning's
auto-requeue): meant for the training process, it would end the server and its workers (the default action), so
both ignore :data:`JOB_WARNING_SIGNALS` as well.

The server's socket lies in a folder of the training process's (``/tmp/pymp-*``), which that process removes as it
exits; one killed (SIGKILL, pre-emption, the OOM killer) leaves it behind, so the server, as it ends after it, reaps
its workers (they remove their own sockets there: :func:`~dapm_lightning.data.workers.remove_shared_socket`),
then removes its own socket, and the folder if nothing else is in it and the training process made it
(:func:`_remove_socket_at_exit`).
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import multiprocessing
import multiprocessing.util
import os
import signal
import socket
import stat
import sys
import time
from typing import Any

JOB_WARNING_SIGNALS = (signal.SIGUSR1, signal.SIGUSR2)
"""Signals a scheduler sends the whole job as a warning (SLURM's ``--signal``), meant for the training process:
ignored by loader workers and their server."""


_WORKERS_MODULE = "dapm_lightning.data.workers"
FOLDER_OWNED = "DAPM_FORKSERVER_FOLDER_OWNED"
"""Set for the fork server where the training process's ``/tmp/pymp-*`` folder is its own (``data.workers``)."""


def in_fork_server() -> bool:
    """Whether this process is multiprocessing's fork server (started as ``python -c 'from multiprocessing...'``)."""
    return sys.argv[:1] == ["-c"] and "multiprocessing.forkserver" in sys.modules


def _is_loader_worker(process: Any) -> bool:
    """Whether ``process`` is a worker of this project's loaders (its ``worker_init_fn`` sets its SIGTERM handler).

    Named, not imported: :mod:`dapm_lightning.data.workers` imports this module.
    """
    return any(isinstance(arg, functools.partial) and getattr(arg.func, "__module__", None) == _WORKERS_MODULE
               and getattr(arg.func, "__qualname__", None) == "loader_worker_init"
               for arg in getattr(process, "_args", ()))


def _restore_sigterm(_: object) -> None:
    """In a process the server forked, as it starts: the default SIGTERM and warning signals back, but in loaders'."""
    if not _is_loader_worker(multiprocessing.current_process()):
        for number in (signal.SIGTERM, *JOB_WARNING_SIGNALS):
            signal.signal(number, signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, JOB_WARNING_SIGNALS)  # blocked as the server started


def listening_socket_path() -> str | None:
    """The path of this process's listening Unix socket, the server's; None where ``/proc`` lists no descriptors.

    ``multiprocessing`` passes the server its socket's descriptor, not its name.
    """
    try:
        descriptors = [int(name) for name in os.listdir("/proc/self/fd")]
    except OSError:
        return None
    for fd in descriptors:
        with contextlib.suppress(OSError):
            if not stat.S_ISSOCK(os.fstat(fd).st_mode):
                continue
            with socket.fromfd(fd, socket.AF_UNIX, socket.SOCK_STREAM) as sock:  # a duplicate, closed here
                name = sock.getsockname()
                if isinstance(name, str) and name and sock.getsockopt(socket.SOL_SOCKET, socket.SO_ACCEPTCONN):
                    return name
    return None


def _training_process_ended(parent: int, wait_s: float = 0.5) -> bool:
    """Whether the server's parent, the training process ``parent``, has ended (this server was handed to another).

    The server also ends while it still runs: ``multiprocessing``'s ``_stop()`` (which then removes the socket
    itself) or a request the server failed on. Its parent's end closes the pipe the server waits on a moment before
    the server is handed to another parent: that moment is waited for, ``wait_s`` at most.
    """
    deadline = time.monotonic() + wait_s
    while os.getppid() == parent:
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True


def _remove_socket_at_exit(path: str, server: int, parent: int, folder_owned: bool, wait_s: float = 5.0) -> None:
    """At the server's exit, once its training process has ended (was killed): remove its socket and the folder.

    First its workers end (or ``wait_s`` passes). The folder goes only if the training process made it (one
    started by another process shares its parent's, which the parent removes) and it is empty: a process forked
    from the training one may keep a server of its own there. Nothing happens in a process forked from the server
    that exits without ``os._exit`` (it inherits this handler), nor while the training process still runs.
    """
    if os.getpid() != server or not _training_process_ended(parent):
        return
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        try:
            if os.waitpid(-1, os.WNOHANG)[0] == 0:
                time.sleep(0.05)
        except ChildProcessError:  # no child left
            break
    with contextlib.suppress(OSError):
        os.unlink(path)
    if folder_owned:  # not the folder of a process that still runs
        with contextlib.suppress(OSError):
            os.rmdir(os.path.dirname(path))


class _Registration:
    """The object ``multiprocessing.util.register_after_fork`` keeps a weak reference to."""


_REGISTRATION = _Registration()

if in_fork_server():
    for _number in (signal.SIGTERM, *JOB_WARNING_SIGNALS):
        signal.signal(_number, signal.SIG_IGN)
    multiprocessing.util.register_after_fork(_REGISTRATION, _restore_sigterm)
    _FOLDER_OWNED = os.environ.pop(FOLDER_OWNED, None) == "1"  # not for its workers
    _SOCKET = listening_socket_path()
    if _SOCKET is not None and os.path.basename(os.path.dirname(_SOCKET)).startswith("pymp-"):
        atexit.register(_remove_socket_at_exit, _SOCKET, os.getpid(), os.getppid(), _FOLDER_OWNED)
