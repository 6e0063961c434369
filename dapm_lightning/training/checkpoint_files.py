"""Checkpoint files: safe reading (local, ``file://``, ``http(s)``, fsspec) and atomic writing on any filesystem.

:func:`read_checkpoint` loads with ``weights_only`` and the project's allow-list (:data:`SAFE_GLOBALS`); a file that
holds pickled code is refused (:class:`UnsafeCheckpointError`) without running it, and a remote one is fetched into
the run's folder first (:func:`fetch_checkpoint`, named by a hash of the whole address). :func:`save_atomically`
writes a temporary file in the checkpoint's own folder, fsyncs it, then renames it over the target, so the previous
file stays complete until the new one is; :func:`remove_unfinished_saves` clears what a killed save left.
:func:`split_checkpoint` stores a checkpoint as a folder of parts (each under a hosting limit, e.g. a Git host's
file size) with a manifest of their SHA-256 sums; :func:`read_checkpoint` reads such a folder like a file.
"""

from __future__ import annotations

import codecs
import errno
import hashlib
import io
import json
import os
import re
import secrets
import shutil
import socket
import urllib.error
import urllib.request
import zipfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import suppress
from pathlib import Path
from typing import IO, Any
from urllib.parse import unquote, urlsplit

import torch
from lightning.pytorch.utilities import rank_zero_info, rank_zero_warn
from torch import Tensor

SAFE_GLOBALS: tuple[Any, ...] = ()
"""The project's allow-list: Python types a checkpoint may hold beyond what torch's ``weights_only`` loading accepts
(tensors, numbers, strings, lists, dicts...). Empty: dapm-lightning checkpoints hold plain values only (settings as
dicts, RNG states as tensors, :mod:`.rng`). A type added here must be data, never something that runs code."""

_CHUNK = 1 << 22  # bytes copied at a time when fetching a remote checkpoint
_PARTIAL = re.compile(r"\.partial-(?P<host>.*)-(?P<pid>\d+)-[0-9a-f]{8}$")
"""The name of a save in progress: ``NAME.partial-HOST-PID-TOKEN`` next to ``NAME`` (see :func:`save_atomically`)."""


COPY_AGAIN_FIX = ("Fix: copy the checkpoint again (a file cut short by a full disk or an interrupted transfer cannot "
                  "be read) or pick another one, e.g. the run's last.ckpt.")
NOT_A_CHECKPOINT_FIX = ("Fix: give a checkpoint written by `dapm-lightning fit` (a run's checkpoints/last.ckpt or "
                        "best-*.ckpt) or a shipped model such as models/dapm-synthetic-r18-256.")


class CheckpointReadError(RuntimeError):
    """A checkpoint file that cannot be read: cut short, damaged or not a checkpoint (the message names it).

    ``fix`` says what to do (shown after the message by ``dapm-lightning``, tools/errors.py).
    """

    def __init__(self, message: str, fix: str = COPY_AGAIN_FIX) -> None:
        super().__init__(message)
        self.fix = fix


class NotACheckpointFileError(CheckpointReadError):
    """A file that is something else than a checkpoint, said what (an ONNX model, a part of a split checkpoint)."""

    explained = True  # the message says what it is and the fix: printed as it is (tools/errors.py)


_SPLIT_PART = re.compile(r"^checkpoint\.part\d+$")
"""The name of one part of a split checkpoint (:func:`split_checkpoint`)."""
_ONNX_MODEL_TAGS = frozenset({0x12, 0x1A, 0x22, 0x28, 0x32, 0x3A, 0x42, 0x72})
"""The protobuf tags of ONNX ``ModelProto`` fields 2-8 and 14, one of which follows ``ir_version`` (field 1)."""


def looks_like_onnx(head: bytes) -> bool:
    """Whether a file's first bytes are an ONNX model's (protobuf ``ModelProto``: ``ir_version``, then another field).

    Protobuf writes fields in number order: tag ``0x08`` (field 1, a varint), the IR version (1 to 127), then the
    tag of a later field (producer, graph, opset imports...). A PyTorch checkpoint starts ``PK`` (zip) or ``0x80``.
    """
    return len(head) >= 3 and head[0] == 0x08 and 0 < head[1] < 0x80 and head[2] in _ONNX_MODEL_TAGS


def _not_a_checkpoint(path: str | Path, source: Path) -> str | None:
    """What a local file that torch cannot load is, when it is an ONNX model or a split checkpoint's part; else None."""
    listed = source.parent / SPLIT_MANIFEST
    part_of_split = _SPLIT_PART.match(source.name) is not None
    if listed.is_file() and not part_of_split:
        try:
            part_of_split = source.name in {str(p.get("name")) for p in json.loads(listed.read_text())["parts"]}
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            part_of_split = False
    if part_of_split:
        folder = source.parent
        if listed.is_file():
            return (f"{path}: one part of a split checkpoint, not a whole checkpoint: the folder {folder} holds it "
                    f"(its parts and {SPLIT_MANIFEST}), joined and checked when read.\nFix: pass the folder, "
                    f"{folder}, instead of one of its parts.")
        return (f"{path}: one part of a split checkpoint, not a whole checkpoint, and {folder} has no "
                f"{SPLIT_MANIFEST} to join it with the other parts.\nFix: pass the folder that holds all the parts "
                f"and {SPLIT_MANIFEST} (copy it again whole if parts.json is missing).")
    try:
        with open(source, "rb") as stream:
            head = stream.read(16)
    except OSError:
        return None
    if looks_like_onnx(head):
        run = (f"`dapm-lightning predict SOURCE --ckpt_path {path}`" if source.suffix.lower() == ".onnx" else
               f"`dapm-lightning predict SOURCE --ckpt_path {source.with_suffix('.onnx')}` (renamed to end in .onnx, "
               "which is how predict tells an ONNX model)")
        return (f"{path}: an exported ONNX model, not a checkpoint written by `dapm-lightning fit` (.ckpt).\nFix: "
                f"pass the .ckpt it was exported from; predict runs the ONNX model directly: {run}.")
    return None


class UnsafeCheckpointError(RuntimeError):
    """A checkpoint refused because it holds pickled Python objects (code could run); nothing in it was run."""

    explained = True  # the message says what it is and the fix: printed as it is (tools/errors.py)


class CheckpointSaveError(RuntimeError):
    """A checkpoint that could not be written (full disk, read-only folder...); the message names it and the fix."""

    explained = True


class CheckpointFetchError(RuntimeError):
    """A remote checkpoint (``http(s)://``, another fsspec path) that could not be fetched, with the fix."""

    explained = True


class UnsafeCheckpointIOError(ValueError):
    """A ``CheckpointIO`` plugin that reads checkpoints its own way, which cannot be made safe."""


def is_remote(path: str | Path) -> bool:
    """Whether ``path`` is an address (``http://``, ``s3://``, ``memory://``...) rather than a local file.

    ``file://`` paths are local. Lightning's special ``--ckpt_path`` values (``last``, ``best``, ``hpc``,
    ``registry:NAME``) are not addresses.
    """
    text = str(path)
    scheme = urlsplit(text).scheme
    return "://" in text and len(scheme) > 1 and scheme != "file"


def local_path(path: str | Path) -> Path:
    """``path`` as a local :class:`~pathlib.Path`: a ``file://`` URL's path (``file:/x`` too), else as it is."""
    text = str(path)
    if text.startswith("file:"):
        return Path(unquote(urlsplit(text).path))
    return Path(path)


def _host() -> str:
    return re.sub(r"[^\w.-]", "_", socket.gethostname()) or "host"


def _remote_chunks(url: str) -> Iterator[bytes]:
    """The bytes of the file at ``url``, a chunk at a time: urllib for ``http(s)``, fsspec for other protocols."""
    scheme = urlsplit(url).scheme
    try:
        if scheme in ("http", "https"):
            opened: Any = urllib.request.urlopen(url, timeout=60)  # noqa: S310 (http(s) only)
        else:
            import fsspec

            opened = fsspec.open(url, "rb")
        with opened as stream:
            while chunk := stream.read(_CHUNK):
                yield chunk
    except (OSError, ValueError, ImportError) as error:  # urllib's URLError is an OSError
        if isinstance(error, (ValueError, ImportError)) and scheme not in ("http", "https"):
            raise CheckpointFetchError(
                f"{url}: cannot read a checkpoint from a {scheme}:// path here ({error}).\n"
                "Fix: download the file and pass its local path, or install the fsspec filesystem for "
                f"{scheme}://.") from error
        reason = getattr(error, "reason", None) or error
        raise CheckpointFetchError(f"{url}: could not fetch the checkpoint ({reason}).\n"
                                   "Fix: check the address, or download the file and pass its local path.") from error


def _space_left(error: BaseException) -> bool:
    """Whether ``error`` (or an error it was raised from, as torch wraps them) is a full disk or quota."""
    seen: BaseException | None = error
    while seen is not None:
        if isinstance(seen, OSError) and seen.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        seen = seen.__cause__ or seen.__context__
    return False


def _os_error(error: BaseException) -> OSError | None:
    seen: BaseException | None = error
    while seen is not None:
        if isinstance(seen, OSError):
            return seen
        seen = seen.__cause__ or seen.__context__
    return None


def _megabytes(count: int) -> str:
    return f"{count / 1e6:.1f} MB"


def _tensor_bytes(value: Any, seen: set[int] | None = None) -> int:
    """The bytes of the tensors in ``value`` (nested dicts, lists, tuples), each storage counted once."""
    seen = set() if seen is None else seen
    if isinstance(value, Tensor):
        storage = value.untyped_storage()
        if storage.data_ptr() in seen:
            return 0
        seen.add(storage.data_ptr())
        return int(storage.nbytes())
    if isinstance(value, Mapping):
        return sum(_tensor_bytes(v, seen) for v in value.values())
    if isinstance(value, (list, tuple)):
        return sum(_tensor_bytes(v, seen) for v in value)
    return 0


def _write_error(path: Path, error: BaseException, written: int, what: str = "save the checkpoint") -> Exception:
    """The one-paragraph error of a failed write of ``path``: the file, the cause, the fix."""
    folder = path.parent
    if _space_left(error):
        free = shutil.disk_usage(folder).free if folder.is_dir() else 0
        previous = path.stat().st_size if path.is_file() else 0
        need = max(written, previous)
        needed = f", about {_megabytes(need)} needed" if need > free else ""
        kept = f" The previous {path.name} is unchanged." if previous else ""
        return CheckpointSaveError(
            f"{path}: could not {what}: no space left in {folder} ({_megabytes(free)} free{needed}).{kept}\n"
            f"Fix: free space in {folder}, or write the run to another disk with --trainer.default_root_dir DIR.")
    cause = _os_error(error)
    reason = f"{cause.strerror or cause}" if cause is not None else str(error).splitlines()[0]
    return CheckpointSaveError(f"{path}: could not {what} ({reason}).\nFix: make {folder} writable with space "
                               "for the checkpoint, or write the run elsewhere with --trainer.default_root_dir DIR.")


def _fsync_folder(folder: Path) -> None:
    """Make a rename in ``folder`` durable (some filesystems cannot sync a folder: ignored there)."""
    with suppress(OSError):
        descriptor = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(descriptor)
        finally:
            os.close(descriptor)


def _atomic_write(path: Path, write: Callable[[IO[bytes]], None], what: str, size: Callable[[], int] = lambda: 0
                  ) -> None:
    """``write`` into a temporary file beside ``path``, flushed and fsynced, then renamed over ``path``.

    ``size`` estimates the bytes needed, for the message of a full disk.
    """
    folder = path.parent
    temporary = path.with_name(f"{path.name}.partial-{_host()}-{os.getpid()}-{secrets.token_hex(4)}")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with open(temporary, "xb") as stream:
            write(stream)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException as error:  # KeyboardInterrupt too: never leave the temporary file behind
        written = temporary.stat().st_size if temporary.exists() else 0
        with suppress(OSError):
            temporary.unlink()
        if isinstance(error, Exception) and not getattr(error, "explained", False) and _os_error(error) is not None:
            raise _write_error(path, error, max(written, size()), what) from error
        raise
    _fsync_folder(folder)


def save_atomically(checkpoint: Any, path: str | Path) -> None:
    """``torch.save(checkpoint)`` to ``path`` so that ``path`` is always either the old file or the new one.

    The checkpoint is written to ``NAME.partial-HOST-PID-TOKEN`` in ``path``'s own folder (never ``$TMPDIR``),
    flushed and fsynced, then renamed over ``path`` with ``os.replace`` (atomic on one filesystem), and the
    folder is fsynced. A failed save removes its temporary file and raises :class:`CheckpointSaveError` naming
    the file and the fix (free space in the folder, or ``--trainer.default_root_dir``); a killed one leaves it,
    and :func:`remove_unfinished_saves` removes it on the next start.

    Args:
        checkpoint: what ``torch.save`` takes (a Lightning checkpoint dictionary).
        path: the checkpoint file (a local path or ``file://`` URL).
    """
    _atomic_write(local_path(path), lambda stream: torch.save(checkpoint, stream), "save the checkpoint",
                  lambda: _tensor_bytes(checkpoint))


def _writer_alive(match: re.Match[str]) -> bool:
    """Whether the process that started a save (``NAME.partial-HOST-PID-...``) may still be writing it."""
    pid = int(match["pid"])
    if match["host"] != _host() or pid == os.getpid():
        return False  # another machine's leftover (only one process saves), or this process before its first save
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    with suppress(OSError, IndexError):  # a killed process not yet reaped by its parent is a zombie: gone
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    return True


def remove_unfinished_saves(folders: Iterable[str | Path], recursive: bool = True) -> list[Path]:
    """Remove the temporary files of saves that were killed (``*.partial-HOST-PID-TOKEN``), named in one warning.

    A file whose writer is still running on this machine is kept.

    Args:
        folders: where to look (missing folders are skipped).
        recursive: also in their subfolders.

    Returns:
        The files removed.
    """
    removed: list[Path] = []
    for folder in dict.fromkeys(local_path(f) for f in folders):
        if not folder.is_dir():
            continue
        for path in sorted(folder.rglob("*.partial-*") if recursive else folder.glob("*.partial-*")):
            match = _PARTIAL.search(path.name)
            if match is None or not path.is_file() or _writer_alive(match):
                continue
            with suppress(FileNotFoundError):
                path.unlink()
                removed.append(path)
    if removed:
        rank_zero_warn(f"removed {len(removed)} unfinished checkpoint file(s) left by interrupted saves: "
                       + ", ".join(str(p) for p in removed))
    return removed


def _fetch_name(url: str) -> str:
    name = re.sub(r"[^\w.-]", "_", unquote(urlsplit(url).path.rsplit("/", 1)[-1])) or "checkpoint.ckpt"
    return f"{hashlib.sha256(url.encode()).hexdigest()[:12]}-{name}"


def fetch_checkpoint(url: str, folder: str | Path) -> Path:
    """Download the checkpoint at ``url`` into ``folder`` (atomically), every time: no cache.

    The file is named ``HASH-NAME``: NAME from the address, HASH from the whole address, so two addresses
    ending in the same name never share a file. It is read afterwards like any local file.

    Args:
        url: an ``http(s)://`` address or another fsspec path (``s3://``, ``memory://``...).
        folder: the run's folder for fetched files (created).

    Returns:
        The local file.

    Raises:
        CheckpointFetchError: the address cannot be read (the message names it and the fix).
        CheckpointSaveError: the file cannot be written into ``folder``.
    """
    path = Path(folder) / _fetch_name(url)
    digest = hashlib.sha256()

    def copy(target: IO[bytes]) -> None:
        for chunk in _remote_chunks(url):
            digest.update(chunk)
            target.write(chunk)

    _atomic_write(path, copy, f"fetch {url}")
    rank_zero_info(f"fetched {url} into {path} ({_megabytes(path.stat().st_size)}, sha256 {digest.hexdigest()[:16]})")
    return path


SPLIT_MANIFEST = "parts.json"
"""The manifest of a split checkpoint folder (:func:`split_checkpoint`)."""


def split_checkpoint(source: str | Path, folder: str | Path, part_bytes: int = 15 << 20,
                     card: Mapping[str, Any] | None = None) -> list[Path]:
    """Write the checkpoint file ``source`` as ``folder/checkpoint.partNN`` files of at most ``part_bytes`` each.

    ``folder/parts.json`` lists the parts with their sizes and SHA-256 sums, the whole file's size and sum, and
    ``card`` (plain values describing the model, e.g. its training command). :func:`read_checkpoint` joins and checks
    them. Returns the files written (the parts, then the manifest).
    """
    data = Path(source).read_bytes()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    parts: list[dict[str, Any]] = []
    written = []
    for index, start in enumerate(range(0, len(data), part_bytes)):
        chunk = data[start:start + part_bytes]
        path = folder / f"checkpoint.part{index:02d}"
        _atomic_write(path, _writer(chunk), "write a checkpoint part")
        parts.append({"name": path.name, "bytes": len(chunk), "sha256": hashlib.sha256(chunk).hexdigest()})
        written.append(path)
    manifest = {"bytes": len(data), "sha256": hashlib.sha256(data).hexdigest(), "parts": parts,
                "card": dict(card or {})}
    _atomic_write(folder / SPLIT_MANIFEST, _writer((json.dumps(manifest, indent=2) + "\n").encode()),
                  "write the manifest")
    return [*written, folder / SPLIT_MANIFEST]


def _writer(data: bytes) -> Callable[[IO[bytes]], None]:
    """A writer of ``data`` for :func:`_atomic_write`."""
    def write(stream: IO[bytes]) -> None:
        stream.write(data)
    return write


def is_split_checkpoint(path: str | Path) -> bool:
    """Whether ``path`` is a local folder written by :func:`split_checkpoint`."""
    return not is_remote(path) and (local_path(path) / SPLIT_MANIFEST).is_file()


def split_checkpoint_card(path: str | Path) -> dict[str, Any]:
    """The ``card`` of a split checkpoint folder's manifest (empty for any other path)."""
    if not is_split_checkpoint(path):
        return {}
    card = json.loads((local_path(path) / SPLIT_MANIFEST).read_text()).get("card", {})
    return dict(card) if isinstance(card, dict) else {}


def join_split_checkpoint(path: str | Path) -> bytes:
    """The checkpoint file a split folder holds, each part and the whole checked against the manifest.

    Raises FileNotFoundError (a part missing) or :class:`CheckpointReadError` (a part or the manifest damaged),
    each naming the file and the fix (a CheckpointReadError's in its ``fix``).
    """
    folder = local_path(path)
    fix = (f"Fix: restore the folder as it was published (e.g. `git checkout -- {folder}`, or copy it again "
           "whole); every part listed in parts.json is needed.")
    try:
        manifest = json.loads((folder / SPLIT_MANIFEST).read_text())
        parts = [(str(p["name"]), int(p["bytes"]), str(p["sha256"])) for p in manifest["parts"]]
        whole = str(manifest["sha256"])
    except (ValueError, KeyError, TypeError) as error:
        raise CheckpointReadError(f"{folder / SPLIT_MANIFEST}: not a split checkpoint manifest ({error})", fix
                                  ) from error
    chunks = []
    for name, size, digest in parts:
        part = folder / name
        if not part.is_file():
            raise FileNotFoundError(f"{part}: a part of the split checkpoint {folder} is missing.\n{fix}")
        chunk = part.read_bytes()
        if len(chunk) != size or hashlib.sha256(chunk).hexdigest() != digest:
            raise CheckpointReadError(f"{part}: damaged ({len(chunk)} bytes, {size} expected, or another SHA-256 "
                                      "than parts.json lists)", fix)
        chunks.append(chunk)
    data = b"".join(chunks)
    if hashlib.sha256(data).hexdigest() != whole:
        raise CheckpointReadError(f"{folder}: the joined parts do not match parts.json's SHA-256", fix)
    return data


def join_split_checkpoint_file(path: str | Path, folder: str | Path) -> Path:
    """:func:`join_split_checkpoint` written atomically to ``folder/NAME-SHA8.ckpt`` (kept if already there)."""
    data = join_split_checkpoint(path)
    target = Path(folder) / f"{local_path(path).resolve().name}-{hashlib.sha256(data).hexdigest()[:8]}.ckpt"
    if not (target.is_file() and target.stat().st_size == len(data)):
        _atomic_write(target, _writer(data), "write the joined checkpoint", lambda: len(data))
    return target


def _refused_globals(source: str | Path | bytes) -> list[str]:
    """The pickled globals of a checkpoint that ``weights_only`` loading refuses ([] if none or unreadable)."""
    allowed = {f"{getattr(g, '__module__', '')}.{getattr(g, '__qualname__', g)}" for g in SAFE_GLOBALS}
    try:
        found = torch.serialization.get_unsafe_globals_in_checkpoint(
            io.BytesIO(source) if isinstance(source, bytes) else source)
    except Exception:  # not a zip checkpoint at all: damaged, not refused
        return []
    return [name for name in found if name not in allowed]


LIGHTNING_CHECKPOINT_WORDS = ("best", "last", "hpc", "registry")
"""``--ckpt_path`` values Lightning resolves itself (``registry:NAME:VERSION`` too); any other is a path."""


def is_lightning_checkpoint_word(ckpt_path: str) -> bool:
    """Whether ``ckpt_path`` is one of Lightning's own values (:data:`LIGHTNING_CHECKPOINT_WORDS`), not a path.

    ``registry`` and ``registry:NAME`` count in any case, as Lightning matches them; ``registry_old.ckpt`` is a path.
    """
    return ckpt_path in LIGHTNING_CHECKPOINT_WORDS or re.match(r"registry(:.*|$)", ckpt_path.lower()) is not None


def _likeliest_checkpoint(path: Path) -> tuple[bool, bool, bool, int, float]:
    """How likely ``path`` is the checkpoint meant, to sort by.

    A complete checkpoint zip (as torch.save writes) first, then ``last.ckpt``, ``best-*``, the largest, the newest.
    """
    try:
        with zipfile.ZipFile(path) as opened:
            complete = any(name.endswith("data.pkl") for name in opened.namelist())
    except (zipfile.BadZipFile, OSError, ValueError):
        complete = False
    stat = path.stat()
    return complete, path.name == "last.ckpt", path.name.startswith("best"), stat.st_size, stat.st_mtime


def _folder_not_checkpoint(folder: Path) -> str:
    """What to say when a folder is given as a checkpoint: the checkpoints below it, the likeliest one first."""
    ranked = sorted(((_likeliest_checkpoint(p), p) for p in folder.rglob("*.ckpt") if p.is_file()), reverse=True)
    found = [p for _, p in ranked]
    if not found:
        return f"{folder}: a folder, not a checkpoint file, and no *.ckpt is below it.\nFix: give a checkpoint file."
    listed = ", ".join(str(p) for p in found[:3]) + (f" ({len(found)} in all)" if len(found) > 3 else "")
    if not ranked[0][0][0]:
        return (f"{folder}: a folder, not a checkpoint file; below it: {listed}, none of them a complete checkpoint."
                f"\nFix: give a checkpoint file written by `dapm-lightning fit`.")
    return f"{folder}: a folder, not a checkpoint file; below it: {listed}.\nFix: give one of them, e.g. {found[0]}"


def check_checkpoint_there(path: str | Path) -> None:
    """Refuse a local path holding neither a file nor a split checkpoint, as :func:`read_checkpoint` would.

    Raises:
        FileNotFoundError: nothing there.
        IsADirectoryError: a folder that is not a split checkpoint (naming the checkpoints below it).
    """
    if is_remote(path) or is_split_checkpoint(path):
        return
    source = local_path(path)
    if source.is_dir():
        raise IsADirectoryError(_folder_not_checkpoint(source))
    if not source.is_file():
        hint = ""
        if is_lightning_checkpoint_word(str(path)):
            hint = (f"; `{path}` is Lightning's word for a checkpoint, which only fit, validate, test and predict "
                    "given a --config resolve (docs/long_jobs.md).\nFix: give the checkpoint file, e.g. "
                    "outputs/RUN/tensorboard/version_0/checkpoints/last.ckpt")
        raise FileNotFoundError(f"{path}: no such checkpoint file{hint}")


def read_checkpoint(path: str | Path, map_location: Any = "cpu") -> dict[str, Any]:
    """Load a checkpoint safely: ``weights_only=True`` with :data:`SAFE_GLOBALS`, from any kind of path.

    Local files and ``file://`` paths are read in place; ``http(s)://`` and other fsspec paths are read into
    memory (never through torch hub's cache, which is keyed by the file's name). No pickled code runs.

    Args:
        path: the checkpoint: a file, a split checkpoint folder (:func:`split_checkpoint`) or a remote file.
        map_location: where tensors go, as in ``torch.load``.

    Returns:
        The checkpoint (a dictionary, or whatever plain values the file holds).

    Raises:
        FileNotFoundError: no such local file.
        IsADirectoryError: a folder that is not a split checkpoint (naming the checkpoints below it).
        UnsafeCheckpointError: the file holds pickled objects that could run code (refused, nothing run).
        CheckpointReadError: the file is damaged or not a PyTorch file (``not a readable checkpoint``).
        CheckpointFetchError: a remote file that cannot be fetched.
    """
    source: Path | bytes
    if is_remote(path):
        source = b"".join(_remote_chunks(str(path)))
    elif is_split_checkpoint(path):
        source = join_split_checkpoint(path)
    else:
        check_checkpoint_there(path)
        source = local_path(path)
    try:
        with torch.serialization.safe_globals(list(SAFE_GLOBALS)):
            if isinstance(source, bytes):
                return torch.load(io.BytesIO(source), map_location=map_location, weights_only=True)
            with open(source, "rb") as stream:
                return torch.load(stream, map_location=map_location, weights_only=True)
    except Exception as error:  # torch raises RuntimeError / UnpicklingError / EOFError for damaged files
        refused = _refused_globals(source)
        if refused:
            shown = ", ".join(refused[:4]) + (f" and {len(refused) - 4} more" if len(refused) > 4 else "")
            raise UnsafeCheckpointError(
                f"{path}: refused: the file holds pickled Python objects ({shown}), which could run code when "
                "loaded. It was not loaded, and nothing in it was run: dapm-lightning reads checkpoints with "
                "weights_only=True (tensors and plain values only).\nFix: use a checkpoint written by "
                "`dapm-lightning fit`; if you made this file yourself and trust it, load it once with "
                "torch.load(..., weights_only=False) and save it again with tensors and plain values only.") from error
        other = None if isinstance(source, bytes) else _not_a_checkpoint(path, source)
        if other:
            raise NotACheckpointFileError(other) from error
        what, fix = _unloadable(path, source, error)
        raise CheckpointReadError(f"{path}: not a readable checkpoint ({what})", fix) from error


IMAGE_HEADS = {b"\x89PNG": "a PNG image", b"\xff\xd8\xff": "a JPEG image", b"GIF8": "a GIF image",
               b"II*\x00": "a TIFF image", b"MM\x00*": "a TIFF image"}
"""The first bytes of image files, with what each is: named where an image is given for a checkpoint or a table."""
_SETTINGS = re.compile(r"^(?:trainer|model|data|ckpt_path|seed_everything)\s*:", re.MULTILINE)


def _unloadable(path: str | Path, source: Path | bytes, error: BaseException) -> tuple[str, str]:
    """``(what, fix)`` for a file torch cannot load: empty, a checkpoint cut short or damaged, or no checkpoint at all.

    ``torch.save`` writes a zip holding ``data.pkl`` (a bare pickle before torch 1.6): a file that starts so but does
    not load is a checkpoint cut short or damaged; anything else (an image, a text or YAML file) is no checkpoint.
    """
    with io.BytesIO(source) if isinstance(source, bytes) else open(source, "rb") as stream:
        head = stream.read(4096)
        size = stream.seek(0, io.SEEK_END)
        zipped = head.startswith(b"PK\x03\x04")
        try:
            saved_by_torch = zipped and any(n.endswith("data.pkl") for n in zipfile.ZipFile(stream).namelist())
        except (zipfile.BadZipFile, OSError, ValueError):  # a zip without its directory: cut short (or damaged)
            saved_by_torch = True
    if not size:
        return "0 bytes: the file is empty", COPY_AGAIN_FIX
    if head[:1] == b"\x80" or saved_by_torch:
        first = str(error).strip().splitlines()[0].split(". ")[0] if str(error).strip() else type(error).__name__
        return f"{size} bytes, a checkpoint cut short or damaged: {first}", COPY_AGAIN_FIX
    try:
        text = codecs.getincrementaldecoder("utf-8")().decode(head)  # a character cut at the end is no error
    except UnicodeDecodeError:
        text = "\x00"
    image = next((kind for start, kind in IMAGE_HEADS.items() if head.startswith(start)), None)
    fix = NOT_A_CHECKPOINT_FIX
    if zipped:
        kind = "a zip archive without the data.pkl of a PyTorch checkpoint"
    elif image:
        kind, fix = image, f"Fix: an image goes to predict as its SOURCE (`dapm-lightning predict IMAGE --ckpt_path " \
            f"CKPT`); {fix.removeprefix('Fix: ')}"
    elif "\x00" in text:
        kind = "neither the zip nor the pickle that torch.save writes"
    elif Path(str(path)).suffix.lower() in (".yaml", ".yml") or _SETTINGS.search(text):
        kind, fix = "a YAML file of settings", f"Fix: settings go to --config {path}; {fix.removeprefix('Fix: ')}"
    else:
        kind = "a text file"
    return f"{size} bytes, not a checkpoint at all: {kind}", fix


class NotADAPMCheckpointError(ValueError):
    """A readable file that is not a dapm-lightning checkpoint (another model's, a bare state dict...)."""


class NonFiniteWeightsError(ValueError):
    """A dapm-lightning checkpoint whose weights hold NaN or infinite values (a training that diverged)."""


def some_keys(keys: Iterable[Any], count: int = 3) -> str:
    """Up to ``count`` of ``keys``, quoted, and how many there are when more: ``'a', 'b', ... (5 in all)``."""
    names = [str(k) for k in keys]
    shown = ", ".join(repr(k) for k in names[:count])
    return shown + (f", ... ({len(names)} in all)" if len(names) > count else "")


def foreign_checkpoint(checkpoint: Any) -> str | None:
    """None for a dapm-lightning checkpoint; else what ``checkpoint`` (a loaded file) is, in a few words.

    A dapm-lightning checkpoint is a Lightning checkpoint whose ``hyper_parameters`` hold the network's
    settings (``net``) and whose ``state_dict`` holds the network's weights (``net.*``).
    """
    if not isinstance(checkpoint, Mapping):
        return f"it holds a {type(checkpoint).__name__}, not a dictionary of weights and settings"
    state_dict = checkpoint.get("state_dict")
    if not isinstance(state_dict, Mapping):
        if checkpoint and all(isinstance(v, Tensor) for v in checkpoint.values()):
            whose = ("the weights of a DAPM network" if any(str(k).startswith("net.") for k in checkpoint)
                     else "another model's weights")
            return (f"a plain PyTorch state dict, {whose} ({some_keys(checkpoint, 2)}), without the settings "
                    "that rebuild the network")
        return f"a dictionary with the keys {some_keys(checkpoint, 6)}, not a Lightning checkpoint"
    hyper_parameters = checkpoint.get("hyper_parameters")
    settings = hyper_parameters if isinstance(hyper_parameters, Mapping) else {}
    ours = isinstance(settings.get("net"), Mapping) and any(str(k).startswith("net.") for k in state_dict)
    if ours:
        return None
    if any(str(k).startswith("net.") for k in state_dict):
        return "DAPM weights without the network's settings (no hyper_parameters['net'])"
    kind = "a Lightning checkpoint" if "pytorch-lightning_version" in checkpoint else "a checkpoint"
    class_path = settings.get("_class_path")
    model = f" of {class_path}" if isinstance(class_path, str) else " of another model"
    shown = f"; settings {some_keys([k for k in settings if not str(k).startswith('_')], 4)}" if settings else ""
    return f"{kind}{model}: {len(state_dict)} weight tensor(s) such as {some_keys(state_dict, 2)}{shown}"


def check_dapm_checkpoint(checkpoint: Any, source: str | Path) -> None:
    """Raise :class:`NotADAPMCheckpointError` (a ValueError naming ``source`` and the fix) unless ours.

    Raises :class:`NonFiniteWeightsError` for one of ours whose weights hold NaN or infinite values: every output
    of that network would be NaN (before, ``predict`` wrote files of NaN and stopped on a drawing error).
    """
    what = foreign_checkpoint(checkpoint)
    if what is None:
        check_finite_weights(checkpoint["state_dict"], source)
        return
    fix = ("Fix: pass a checkpoint written by `dapm-lightning fit` (the run's checkpoints/last.ckpt or best-*.ckpt)")
    if "DAPM" in what:
        fix += ("; to use bare DAPM weights, build the model with the settings they were trained with and call "
                "`DAPMModule(net=...).load_state_dict(...)`")
    raise NotADAPMCheckpointError(f"{source}: not a dapm-lightning checkpoint ({what}).\n{fix}.")


def check_finite_weights(state_dict: Mapping[str, Any], source: str | Path) -> None:
    """Raise :class:`NonFiniteWeightsError`, naming ``source``, the tensors and the fix, if a weight is NaN or inf."""
    bad = [name for name, value in state_dict.items()
           if isinstance(value, Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all())]
    if bad:
        raise NonFiniteWeightsError(
            f"{source}: {len(bad)} of its {len(state_dict)} weight tensors hold NaN or infinite values "
            f"({some_keys(bad, 2)}): the training that wrote it diverged (or the file was altered), so every "
            "output of this network would be NaN.\nFix: use an earlier checkpoint of that run (its "
            "checkpoints/best-*.ckpt, or a last.ckpt saved before the loss turned NaN), or train again with a lower "
            "learning rate (--model.optimizer.lr).")


INFERENCE_KEYS = ("hyper_parameters", "epoch", "global_step", "pytorch-lightning_version", "dapm_train_image_size")
"""What :func:`inference_checkpoint` keeps of a training checkpoint besides the weights."""


def inference_checkpoint(checkpoint: Mapping[str, Any], dtype: torch.dtype = torch.float16) -> dict[str, Any]:
    """The part of a training checkpoint a shipped model needs; no optimizer, loop or callback state.

    That is the weights (floating point ones as ``dtype``), the hyper-parameters (without ``init_weights``: where
    its fit started is no setting of the shipped model) and the training size.

    Raises:
        ValueError: a finite weight beyond ``dtype``'s range (float16: 65504), which would be shipped as inf.
    """
    weights = {name: value.to(dtype) if value.is_floating_point() else value
               for name, value in checkpoint["state_dict"].items()}
    overflowed = [name for name, value in weights.items() if value.is_floating_point()
                  and bool((torch.isinf(value) & torch.isfinite(checkpoint["state_dict"][name])).any())]
    if overflowed:
        raise ValueError(f"{len(overflowed)} weight tensor(s) hold values beyond {dtype}'s range "
                         f"({some_keys(overflowed, 2)}), which would be shipped as inf; ship them as torch.float32")
    kept = {key: checkpoint[key] for key in INFERENCE_KEYS if key in checkpoint}
    if isinstance(kept.get("hyper_parameters"), Mapping):
        kept["hyper_parameters"] = {k: v for k, v in kept["hyper_parameters"].items() if k != "init_weights"}
    return {"state_dict": weights, **kept}
