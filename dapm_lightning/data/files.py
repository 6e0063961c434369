"""Files written whole or not at all, checked, and tables updated by one process at a time.

Every file goes through :func:`open_atomic` (or :func:`write_bytes`, :func:`write_text`, :func:`write_image`):
the data go to a hidden temporary file in the target's own folder, which replaces the target by a rename
(``os.replace``, atomic within one file system) only once it is written in full. A reader never sees half a
file, a failed write leaves the earlier file of that name (if any) as it was and no temporary file behind, and
every failure (a full disk, a read-only or missing folder, an image OpenCV refuses to encode, which it reports
by returning False instead of raising) raises :class:`WriteError` naming the file and the fix.

:func:`exclusive_lock` serialises the read-merge-rewrite of a table that several processes may update at once
(``fcntl.flock`` on a lock file beside it, removed again when released). :func:`check_folder_writable` finds an
output folder that cannot be made or written before any work is done; :func:`make_folder` creates one when the
first file is written, and :func:`remove_empty_folders` takes it back when nothing was written into it.
:func:`stops_deferred` keeps SIGTERM and Ctrl-C out of writes that must agree (a file and its row in a table).
"""

from __future__ import annotations

import errno
import os
import re
import secrets
import signal
import tempfile
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

try:
    import fcntl
except ImportError:  # pragma: no cover  (Windows: no advisory locks; concurrent runs into one folder unguarded)
    fcntl = None  # type: ignore[assignment]

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
"""The signals :func:`stops_deferred` holds back: Ctrl-C and a scheduler's or ``docker stop``'s SIGTERM."""

_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
_DENIED = (errno.EROFS, errno.EACCES, errno.EPERM)
_NOT_A_FOLDER = (errno.ENOTDIR, errno.EEXIST)  # a file where the path needs a folder
WRITE_ERRNOS = (*_FULL, *_DENIED, *_NOT_A_FOLDER)
"""The errors of writing a file that :func:`write_error` explains."""
_TEMP_PREFIX = "."
_TEMP_SUFFIX = ".tmp"


class WriteError(OSError, ValueError):
    """A file could not be written: ``path``, ``reason`` and ``fix`` (shown as ``PATH: cannot be written ...``).

    An ``OSError`` (the file system refused) that is also a ``ValueError``, as :class:`io.UnsupportedOperation`
    is: ``dapm-lightning`` shows a ``ValueError``'s message as it is, with no traceback, and exit status 1.
    """

    def __init__(self, path: str | Path, reason: str, fix: str | None = None) -> None:
        self.path, self.reason = Path(path), reason
        self.fix = fix or "write to another folder"
        super().__init__(f"{path}: cannot be written ({reason})\nFix: {self.fix}")

    def __reduce__(self) -> tuple[type[WriteError], tuple[Path, str, str]]:
        """Pickled as its three fields: a worker process's error reaches its parent whole (not as a broken pool)."""
        return type(self), (self.path, self.reason, self.fix)


_SHORT_WRITE = re.compile(r"\d+ requested and \d+ written")
"""numpy's (and the ONNX writer's) error for a write the disk cut short, which carries no errno: a full disk."""


def is_full_disk(error: OSError) -> bool:
    """A full disk or quota: by its errno, or numpy's and the ONNX writer's errno-less short write."""
    return error.errno in _FULL or (error.errno is None and bool(_SHORT_WRITE.search(str(error))))


def _fix(error: OSError) -> str:
    if is_full_disk(error):
        return "free space on that disk, or write to another folder"
    if error.errno in _DENIED:
        return "write to a folder you may write to (this one is read-only or not yours)"
    if error.errno in _NOT_A_FOLDER:
        return "a part of the path is a file, not a folder: write to another folder, or move that file away"
    return "check the folder, or write to another one"


def _reason(error: OSError) -> str:
    if error.errno is None and is_full_disk(error):
        return f"{os.strerror(errno.ENOSPC)}: {error}"
    return error.strerror or str(error) or type(error).__name__


def write_error(path: Path, error: OSError) -> WriteError:
    """``error`` of writing ``path`` as a :class:`WriteError`: the path, the reason and the fix."""
    if isinstance(error, WriteError):
        return error
    if isinstance(error, FileNotFoundError) and not path.parent.is_dir():
        return WriteError(path, f"its folder {path.parent} does not exist", "create the folder, or write elsewhere")
    return WriteError(path, _reason(error), _fix(error))


_TEMP_NAME_BYTES = 200
"""The most bytes of the target's name a temporary name keeps: with the rest (18 bytes) within NAME_MAX (255)."""


def temporary_name(path: Path) -> Path:
    """A hidden, unique temporary file name beside ``path`` (``.NAME.<random>.tmp``, within NAME_MAX).

    NAME is cut to :data:`_TEMP_NAME_BYTES` bytes of the file system's encoding, at a character's end: a name of
    multi-byte characters (``深度`` is 6 bytes in UTF-8) that fits NAME_MAX must give a temporary name that does too.
    """
    name = path.name
    while len(os.fsencode(name)) > _TEMP_NAME_BYTES:
        name = name[:-1]
    return path.with_name(f"{_TEMP_PREFIX}{name}.{secrets.token_hex(6)}{_TEMP_SUFFIX}")


def _remove(path: Path) -> None:
    try:
        path.unlink()
    except OSError:
        pass


@contextmanager
def open_atomic(path: str | Path, mode: str = "wb", *, durable: bool = False) -> Iterator[IO[Any]]:
    """Open ``path`` for writing, all or nothing: a temporary file beside it, renamed over it once closed.

    Args:
        path: the file to write (its folder must exist).
        mode: ``"wb"`` (bytes) or ``"w"`` (UTF-8 text, newlines untranslated: CSV-ready).
        durable: also ``fsync`` the data before the rename (survives a power cut; costs a disk flush).

    Raises:
        WriteError: the file could not be written in full (disk full, read-only, missing folder); the
            temporary file is removed and an earlier file of that name is left as it was.
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"open_atomic writes 'wb' or 'w', not {mode!r}")
    path = Path(path)
    while True:
        temp = temporary_name(path)
        try:
            fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the umask applies, as to any file
            break
        except FileExistsError:  # pragma: no cover  (48 random bits taken: draw again)
            continue
        except OSError as error:
            raise write_error(path, error) from error
    try:
        handle: IO[Any] = (os.fdopen(fd, "wb") if mode == "wb"
                           else os.fdopen(fd, "w", encoding="utf-8", newline=""))
    except BaseException:
        os.close(fd)
        _remove(temp)
        raise
    try:
        with handle:
            yield handle
            handle.flush()
            if durable:
                os.fsync(handle.fileno())
        os.replace(temp, path)
    except OSError as error:  # a full disk shows at a write, at the flush or at the close
        _remove(temp)
        raise write_error(path, error) from error
    except BaseException:
        _remove(temp)
        raise


def write_bytes(path: str | Path, data: bytes | bytearray | memoryview | np.ndarray, *,
                durable: bool = False) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`open_atomic`); returns the path."""
    with open_atomic(path, "wb", durable=durable) as handle:
        handle.write(data)
    return Path(path)


def write_text(path: str | Path, text: str, *, durable: bool = False) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically (:func:`open_atomic`); returns the path."""
    with open_atomic(path, "w", durable=durable) as handle:
        handle.write(text)
    return Path(path)


def encode_image(path: str | Path, image: np.ndarray) -> np.ndarray:
    """``image`` encoded in the format of ``path``'s suffix (as ``cv2.imwrite`` would write it).

    Raises:
        WriteError: OpenCV cannot encode it (a size the format refuses, e.g. libpng's 1,000,000-pixel rows, or
            a pixel type the format lacks) -- OpenCV itself only returns False.
    """
    path = Path(path)
    detail = ""
    try:
        ok, encoded = cv2.imencode(path.suffix, image)
    except cv2.error as error:
        ok, encoded = False, None
        detail = f": {str(error).strip().splitlines()[-1]}" if str(error).strip() else ""
    if not ok or encoded is None:
        shape = "x".join(str(s) for s in image.shape)
        raise WriteError(path, f"OpenCV cannot encode a {shape} {image.dtype} image as {path.suffix}{detail}",
                         "a smaller image, or another format")
    return np.asarray(encoded)


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """``cv2.imwrite`` that raises: encoded first (:func:`encode_image`), then written atomically."""
    return write_bytes(path, encode_image(path, image))


@contextmanager
def exclusive_lock(path: str | Path) -> Iterator[Path]:
    """Hold an exclusive lock on ``path`` (a file that others read, merge and rewrite) while the block runs.

    ``fcntl.flock`` on ``.NAME.lock`` beside it; other processes (and threads with their own lock) wait. The
    lock file is removed on release, so nothing is left in the folder: a waiter that then finds its lock file
    gone or replaced takes the lock again on the current one. Without ``fcntl`` (Windows) nothing is locked.

    Raises:
        WriteError: the lock file cannot be created (a read-only or missing folder).
    """
    path = Path(path)
    lock = path.with_name(f".{path.name}.lock")
    if fcntl is None:  # pragma: no cover
        yield lock
        return
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as error:
            raise write_error(lock, error) from error
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            try:
                current = os.stat(lock)
            except FileNotFoundError:
                current = None
            held = os.fstat(fd)
            if current is not None and (current.st_dev, current.st_ino) == (held.st_dev, held.st_ino):
                break
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)  # the holder before us removed (or replaced) this lock file: lock the current one
    try:
        yield lock
    finally:
        _remove(lock)  # removed while still held: a process waiting on it sees it gone and locks afresh
        os.close(fd)


def check_folder_writable(folder: str | Path, option: str | None = None) -> Path:
    """Refuse, before any work is done, an output ``folder`` that cannot be created or written; nothing is left made.

    The nearest existing folder on the way must be a folder (not a file) that this process may write in (read-only
    file systems included), and a uniquely named folder is made in it and removed again, which finds a place where
    even root cannot write (``/proc``, ``/sys``); ``folder`` itself is not made. Returns the folder. ``option``: the
    setting that chose it, named in the fix.

    Raises:
        WriteError: naming the folder, why, and the fix.
    """
    folder = Path(folder)
    fix = f"give another output folder{f' ({option})' if option else ''}"
    existing = folder
    while not existing.exists() and existing != existing.parent:
        if existing.is_symlink():  # a dangling link: mkdir cannot follow it
            raise WriteError(folder, f"{existing} is a link to nothing", fix)
        existing = existing.parent
    if not existing.is_dir():
        what = "is" if existing == folder else f"lies under {existing}, which is"
        raise WriteError(folder, f"it {what} a file, not a folder", fix)
    if not os.access(existing, os.W_OK | os.X_OK):
        where = "it is" if existing == folder else f"{existing} is"
        raise WriteError(folder, f"{where} read-only or not yours", fix)
    # a uniquely named folder made and removed in the nearest existing one: what os.access does not know (root under
    # /proc or /sys); the target itself is never made or removed, so processes checking one folder at once agree
    try:
        os.rmdir(tempfile.mkdtemp(prefix=_TEMP_PREFIX + "probe-", suffix=_TEMP_SUFFIX, dir=existing))
    except OSError as error:
        raise WriteError(folder, f"nothing can be made in {existing}: {_reason(error)}", fix) from error
    return folder


def make_folder(folder: str | Path) -> list[Path]:
    """Create ``folder`` and any missing parents; returns the folders created (outermost first).

    Raises:
        WriteError: it cannot be created.
    """
    folder = Path(folder)
    missing = []
    existing = folder
    while not existing.is_dir() and existing != existing.parent:
        missing.append(existing)
        existing = existing.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise WriteError(folder, f"the folder cannot be created: {_reason(error)}", _fix(error)) from error
    return missing[::-1]


def remove_empty_folders(folders: Sequence[Path]) -> None:
    """Remove the ``folders`` (outermost first, as :func:`make_folder` returns them) that are empty, innermost first.

    A folder that holds anything, or that another process is filling, is left alone, and the others are still
    removed: ``folders`` may join the lists of several :func:`make_folder` calls (sibling folders).
    """
    for folder in reversed(folders):
        with suppress(OSError):
            folder.rmdir()


@contextmanager
def stops_deferred() -> Iterator[None]:
    """Meanwhile SIGTERM and Ctrl-C wait; as it ends, each one that arrived goes to the handler it would have reached.

    For writes that must agree, such as an image's files and its row in the run's table: a stop raised between
    the two (the one-line ``predict``'s SIGTERM, Ctrl-C's KeyboardInterrupt) left a file that the tables written on
    stopping did not describe. A stop is held for as long as the writes take, never dropped; nested uses hold it
    until the outermost ends. Outside the main thread (where Python runs no handler) or for a signal whose handler
    was not set from Python, nothing is held.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    arrived: list[int] = []
    previous = {number: signal.getsignal(number) for number in STOP_SIGNALS}
    held = [number for number, handler in previous.items() if handler is not None]
    for number in held:
        signal.signal(number, lambda signum, frame: arrived.append(signum))
    try:
        yield
    finally:
        for number in held:
            signal.signal(number, previous[number])
        for signum in dict.fromkeys(arrived):  # each once, in the order they came
            signal.raise_signal(signum)
