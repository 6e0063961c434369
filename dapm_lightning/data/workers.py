"""Loader workers: how they start, and SIGTERM: a signal to the whole job reaches the training process, not them.

Workers are started by a fork server (:func:`loader_context`), not forked from the training process: a process
forked from one that runs threads (DDP's communication, a logger's writer, pytest-xdist's) inherits any lock one
of those threads held at that moment, never to be released, and a worker then hung at its start, seen twice on
the 2-core build machine under load. The server is a single-threaded process started once per training process,
with PyTorch and the data code imported; a worker forked from it starts as fast as one forked from the training
process. ``worker_start_method: fork`` gives PyTorch's default back (for data sets that cannot be pickled).

SLURM sends SIGTERM to every process of a job step before it pre-empts or ends it (``timeout`` and a terminal
signal the whole process group): to the data loader workers too. PyTorch's workers die of it, and the training
process then stops with a DataLoader error (status 1) instead of saving ``last.ckpt`` and exiting with 143.
:func:`loader_worker_init` makes every worker ignore a SIGTERM from outside, and the warning signals SLURM's
``--signal`` sends (``SIGUSR1``, Lightning's auto-requeue); the training process decides, and its workers stop when
it stops them. One SIGTERM still ends a worker: the one its process sends it while it exits
(``multiprocessing`` terminates its daemonic children, then joins them).
"""

from __future__ import annotations

import atexit
import contextlib
import multiprocessing
import os
import select
import signal
import sys
import threading
import time
import warnings
from functools import partial
from types import FrameType
from typing import Any

from lightning.fabric.utilities.seed import pl_worker_init_function

from dapm_lightning.data.worker_server import FOLDER_OWNED, JOB_WARNING_SIGNALS

WORKER_START_METHODS = ("forkserver", "fork", "spawn")
"""How loader workers start (``multiprocessing`` start methods): the fork server is the default."""
SERVER_PRELOAD = ["dapm_lightning.data.worker_server", "torch", "dapm_lightning.data.datamodules",
                  "dapm_lightning.inference.inputs"]
"""What the fork server imports before it forks workers (the first makes it ignore SIGTERM)."""

_EXITING: list[Any] = []
"""One event per loader with workers, set when this process exits (:func:`_exiting`). Kept for the process's life
(a few bytes each): a worker can outlive its loader's Python objects (one whose shutdown it ignored while it
was busy), and at exit it must still hear that this time SIGTERM is meant."""
_AT_EXIT: list[bool] = []
_OWN_SERVERS: set[int] = set()
"""Process ids of the fork servers this process started with :data:`SERVER_PRELOAD` (:func:`_start_server`)."""


def _exiting() -> None:
    """At exit, before ``multiprocessing`` terminates the workers (``atexit`` runs the later registration first)."""
    for event in list(_EXITING):
        event.set()


def loader_context(method: str = "forkserver") -> multiprocessing.context.BaseContext:
    """The ``multiprocessing_context`` of a loader with workers: the fork server by default.

    Args:
        method: one of :data:`WORKER_START_METHODS`. A platform without a fork server (Windows) spawns instead.

    Returns:
        The context; for the fork server, with :data:`SERVER_PRELOAD` to import when it starts (the first loader
        of this process starts it, once; a server already started by other code keeps its own imports). Its
        processes start with SLURM's warning signals blocked (:func:`_warning_signals_blocked`).
    """
    if method not in WORKER_START_METHODS:
        raise ValueError(f"worker_start_method: {method!r}, but it must be one of {', '.join(WORKER_START_METHODS)}."
                         "\nFix: e.g. --data.init_args.worker_start_method forkserver")
    if method != "spawn" and method not in multiprocessing.get_all_start_methods():
        method = "spawn"
    context = _CONTEXTS.get(method) or multiprocessing.get_context(method)
    if method == "forkserver":
        context.set_forkserver_preload(SERVER_PRELOAD)
    return context


@contextlib.contextmanager
def _warning_signals_blocked() -> Any:
    """:data:`JOB_WARNING_SIGNALS` blocked in this thread meanwhile (a process started then inherits the mask).

    One arriving meanwhile waits and is then delivered here (Lightning's handler); a process started then (a
    loader worker, the fork server, ``multiprocessing``'s resource tracker) keeps them blocked, across ``exec``
    too, until it ignores them (:func:`loader_worker_init`): a forked worker would otherwise run the training
    process's handler (Lightning's auto-requeue: a save and ``scontrol requeue``) before its ``worker_init_fn``,
    and a spawned one, or the tracker, die of the signal while Python starts (seconds).
    """
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, JOB_WARNING_SIGNALS) if hasattr(signal, "pthread_sigmask") else None
    try:
        yield
    finally:
        if mask is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def _loader_process(base: type) -> type:
    """A subclass of the start method's process class that starts with the warning signals blocked."""

    def start(self: Any) -> None:
        with _warning_signals_blocked():
            base.start(self)  # type: ignore[attr-defined]

    return type(f"Loader{base.__name__}", (base,), {"start": start, "__module__": __name__,
                                                    "__qualname__": f"Loader{base.__name__}"})


def _make_loader_contexts() -> dict[str, multiprocessing.context.BaseContext]:
    """One context per start method, its ``Process`` a :func:`_loader_process` (module attributes: picklable)."""
    contexts = {}
    for method in multiprocessing.get_all_start_methods():
        context = multiprocessing.get_context(method)
        process = _loader_process(context.Process)  # type: ignore[attr-defined]
        globals()[process.__name__] = process  # a spawned or fork server's worker unpickles it by name
        contexts[method] = type(f"Loader{type(context).__name__}", (type(context),), {"Process": process})()
    return contexts


_CONTEXTS = _make_loader_contexts()


def _follow_training_process(pid: int) -> None:
    """End this worker when the training process ``pid`` ends, though that is not its parent.

    PyTorch's worker watches its parent process only: a fork server's worker would then outlive a training process
    killed without its exit handlers (SIGKILL, the OOM killer, a crash), and the server, which waits for every
    worker to close its pipe, with it: for ever, each holding a copy of PyTorch and the data set.
    """
    try:
        handle: int | None = os.pidfd_open(pid)  # readable once the process has ended
    except ProcessLookupError:
        os._exit(0)
    except (AttributeError, OSError):  # no pidfd (Linux < 5.3, not Linux): poll
        handle = None

    def follow() -> None:
        if handle is not None:
            select.select([handle], [], [])
        else:
            while True:
                time.sleep(1.0)
                try:
                    os.kill(pid, 0)
                except ProcessLookupError:
                    break
                except PermissionError:
                    pass
        remove_shared_socket()
        os._exit(0)

    threading.Thread(target=follow, name="follow-training-process", daemon=True).start()


def remove_shared_socket() -> None:
    """Remove this process's socket for handing file descriptors (each batch tensor's) to the training process.

    ``multiprocessing`` removes it as a worker exits normally; a worker that ends with ``os._exit`` (its training
    process gone) must, or it stays in the training process's temporary folder, which that process, killed, no
    longer removes.
    """
    from multiprocessing import resource_sharer

    address = getattr(getattr(resource_sharer, "_resource_sharer", None), "_address", None)  # not public
    if isinstance(address, str):
        with contextlib.suppress(OSError):
            os.unlink(address)


def _quiet_broken_pipe(previous: Any, kind: type[BaseException], value: BaseException, trace: Any) -> None:
    """A worker's ``sys.excepthook``: a batch's file handle its training process no longer takes is no error.

    ``multiprocessing``'s resource sharer hands each batch tensor's file descriptor to the training process from a
    thread of the worker and reports its errors through ``sys.excepthook``: a training process stopping (SIGTERM,
    the tables written, exit 143) made it print a ``BrokenPipeError`` traceback. Other errors are reported as before.
    """
    if not issubclass(kind, (BrokenPipeError, ConnectionResetError)):
        previous(kind, value, trace)


def loader_worker_init(worker_id: int, rank: int = 0, exiting: Any = None, seed_workers: bool = False,
                       training_pid: int | None = None) -> None:
    """Start of every loader worker: SIGTERM and SLURM's warning signals from outside ignored; seeded as asked.

    Args:
        worker_id: the worker's number in its loader.
        rank: the process's global rank.
        exiting: an event the training process sets when it exits (:func:`worker_init_fn`): a SIGTERM then
            ends the worker (``multiprocessing`` terminating it), before it is ignored.
        seed_workers: seed as Lightning's ``seed_everything(workers=True)`` asks (read in the training process:
            a fork server's environment is that of its start).
        training_pid: the process whose loader this worker serves: a worker that is not its child (a fork
            server's) ends when it ends (:func:`_follow_training_process`).
    """

    def on_sigterm(signum: int, frame: FrameType | None) -> None:
        if exiting is not None and exiting.is_set():
            os._exit(0)

    signal.signal(signal.SIGTERM, on_sigterm)
    for number in JOB_WARNING_SIGNALS:  # SLURM's --signal (USR1: Lightning's auto-requeue), for the training process
        signal.signal(number, signal.SIG_IGN)  # one pending since the worker started (blocked) is dropped
    if hasattr(signal, "pthread_sigmask"):  # blocked as it started (_warning_signals_blocked): its children get
        signal.pthread_sigmask(signal.SIG_UNBLOCK, JOB_WARNING_SIGNALS)  # them ignored, not blocked
    sys.excepthook = partial(_quiet_broken_pipe, sys.excepthook)
    if training_pid is not None and os.getppid() != training_pid:
        _follow_training_process(training_pid)
    if seed_workers:  # seed_everything(workers=True): Lightning adds its own worker_init_fn only to loaders without one
        pl_worker_init_function(worker_id, rank)


def worker_init_fn(rank: int = 0, context: multiprocessing.context.BaseContext | None = None) -> partial[None]:
    """The ``worker_init_fn`` of a loader: :func:`loader_worker_init` with a fresh exit event of this process.

    Args:
        rank: the process's global rank (for Lightning's worker seeding).
        context: the loader's ``multiprocessing_context`` (its workers must be able to open the event).

    Returns:
        The function a ``DataLoader`` calls at the start of each worker.
    """
    if not _AT_EXIT:  # registered after multiprocessing's own exit handler (imported with torch): runs before it
        atexit.register(_exiting)
        _AT_EXIT.append(True)
    exiting = (context or multiprocessing).Event()
    _EXITING.append(exiting)
    return partial(loader_worker_init, rank=rank, exiting=exiting,
                   seed_workers=bool(int(os.environ.get("PL_SEED_WORKERS", 0))), training_pid=os.getpid())


def _start_server() -> None:
    """Start the fork server now, with :data:`SERVER_PRELOAD`; warn if other code started it without.

    ``multiprocessing`` has one fork server a process, started with the preload of its first use: one started by
    other code (a ``forkserver`` ``Pool`` of the user's) does not ignore a SIGTERM to the whole job, and dies of it
    with the loader's workers (the loader then fails instead of the run stopping after its step).
    """
    from multiprocessing import forkserver

    server: Any = forkserver._forkserver  # multiprocessing's own (not public)
    running = getattr(server, "_forkserver_pid", None)  # multiprocessing's own record (not public)
    if running is not None and not _own_child(running):
        # the server of the process this one was forked from (Lightning's ddp_fork / ddp_notebook after a loader of
        # the notebook's), whose status multiprocessing cannot ask (ChildProcessError), or a server that ended: this
        # process starts its own, as multiprocessing would have started a new one in the second case
        alive_fd = getattr(server, "_forkserver_alive_fd", None)
        if alive_fd is not None:
            with contextlib.suppress(OSError):
                os.close(alive_fd)
        server._forkserver_pid = server._forkserver_address = server._forkserver_alive_fd = None
        running = None
    if running is not None and running not in _OWN_SERVERS:
        warnings.warn(f"Loader workers: the fork server (pid {running}) was started by other code before the first "
                      "loader, without this project's preload: a SIGTERM to the whole job (SLURM, timeout) ends it, "
                      "and its loader workers with it.\nFix: start no forkserver process before the first loader, "
                      "or set data.init_args.worker_start_method to fork", RuntimeWarning, stacklevel=3)
        return
    # the server imports SERVER_PRELOAD from this process's sys.path (Python 3.11's ignores it: a sys.path
    # changed here, a notebook's, had it import another copy of this package, an installed one, or none at all)
    before = {name: os.environ.get(name) for name in ("PYTHONPATH", FOLDER_OWNED)}
    os.environ["PYTHONPATH"] = os.pathsep.join(path or os.getcwd() for path in sys.path)
    os.environ[FOLDER_OWNED] = "1" if _owns_temp_folder() else "0"  # "1": the server may remove it (worker_server)
    # SLURM's warning signals blocked while the server and multiprocessing's resource tracker start (both inherit
    # the mask): the tracker, a process of the job too, died of them and was started again with a warning
    try:
        with _warning_signals_blocked():
            forkserver.ensure_running()
    finally:
        for name, value in before.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    if getattr(server, "_forkserver_pid", None) is not None:
        _OWN_SERVERS.add(server._forkserver_pid)


def _owns_temp_folder() -> bool:
    """Whether this process's ``multiprocessing`` folder (``/tmp/pymp-*``) is its own, to remove as it exits.

    A process started by another (``spawn``, ``forkserver``, ``fork``) inherits its parent's, which the parent
    removes; it is made here otherwise (the server's socket is the first thing in it).
    """
    from multiprocessing import util

    folder = multiprocessing.current_process()._config.get("tempdir")  # type: ignore[attr-defined]
    return folder is None or any(
        getattr(finalizer, "_callback", None) is util._remove_temp_dir  # type: ignore[attr-defined]
        and tuple(getattr(finalizer, "_args", ()))[1:] == (folder,)
        for finalizer in list(util._finalizer_registry.values()))  # type: ignore[attr-defined]


def _own_child(pid: int) -> bool:
    """Whether ``pid`` is a running child process of this one (an ended one is reaped)."""
    try:
        return os.waitpid(pid, os.WNOHANG)[0] == 0
    except ChildProcessError:
        return False


def _main_cannot_be_imported(dataset: Any) -> bool:
    """Whether ``dataset``'s class is defined in a ``__main__`` a started (not forked) worker cannot import.

    A notebook's cells, ``python -`` or ``-c``, a package's ``__main__.py`` (``python -m``): ``multiprocessing``
    imports none of them again in a worker, which then cannot unpickle the data set (it died with "DataLoader
    worker exited unexpectedly").
    """
    main = sys.modules.get("__main__")
    if dataset is None or type(dataset).__module__ != "__main__" or main is None:
        return False
    name = getattr(getattr(main, "__spec__", None), "name", None)
    if name is not None:
        return str(name) == "__main__" or str(name).endswith(".__main__")
    path = getattr(main, "__file__", None)
    return path is None or not os.path.isfile(path)


def loader_workers(num_workers: int, rank: int = 0, method: str = "forkserver", dataset: Any = None) -> dict[str, Any]:
    """``DataLoader`` arguments of its workers: their number, how they start and their start function.

    Args:
        num_workers: loader worker processes (0: the loading runs in this process).
        rank: the process's global rank.
        method: how workers start (:func:`loader_context`).
        dataset: the loader's data set: one whose class a started worker could not import (defined in a notebook,
            :func:`_main_cannot_be_imported`) has its workers forked instead, with a warning.
    """
    if num_workers == 0:
        loader_context(method)  # a wrong method fails alike with and without workers
        return {"num_workers": 0}
    if method != "fork" and _main_cannot_be_imported(dataset):
        warnings.warn(f"Loader workers: {type(dataset).__name__} is defined in __main__ (a notebook, python -c), "
                      f"which a worker started by {method} cannot import: its workers are forked instead.\nFix: "
                      "define the data set in a module of its own, or set worker_start_method to fork",
                      RuntimeWarning, stacklevel=3)
        method = "fork"
    context = loader_context(method)
    if context.get_start_method() == "forkserver":
        _start_server()
    elif context.get_start_method() == "spawn":  # its loader's queues start the tracker: started here, protected
        from multiprocessing import resource_tracker

        with _warning_signals_blocked():
            resource_tracker.ensure_running()
    return {"num_workers": num_workers, "multiprocessing_context": context,
            "worker_init_fn": worker_init_fn(rank, context)}


__all__ = ["SERVER_PRELOAD", "WORKER_START_METHODS", "loader_context", "loader_worker_init", "loader_workers",
           "worker_init_fn"]
