"""User errors as short messages: what went wrong with which file, the fix, and a non-zero exit status.

``dapm-lightning`` runs every subcommand through :func:`run_reporting_errors`: bad paths, bad data
(:class:`~dapm_lightning.data.errors.DatasetError`), unreadable checkpoints, files that are not dapm-lightning
checkpoints, refused checkpoints (pickled code), failed saves and bad settings end in two or three lines on stderr and
exit status 1; Ctrl-C ends in exit status 130, whether Lightning or this module caught it. The Python traceback is
shown only with ``--debug`` (anywhere on the command line) or ``DAPM_DEBUG=1``. A command line the parser
refuses (an unknown or abbreviated option, a value of the wrong type) ends in a few lines with the closest
valid options and exit status 2 (:class:`~dapm_lightning.training.lightning_cli.DAPMArgumentParser`).
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TextIO

DEBUG_FLAG = "--debug"
DEBUG_ENV = "DAPM_DEBUG"
EXIT_ERROR = 1
EXIT_INTERRUPTED = 130
EXPORT_MODULES = ("onnx", "onnxscript", "onnxruntime")
"""The packages of the ``export`` extra (pyproject.toml): ONNX export, int8 and onnxruntime prediction."""
_PATH_ERRORS = (FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError)
_WORKER_TAIL = re.compile(r"^(?:[\w.]+\.)?(\w*(?:Error|Exception)): ", re.MULTILINE)


def debug_requested(argv: Sequence[str]) -> tuple[bool, list[str]]:
    """``(debug?, argv without --debug)``: the flag or ``DAPM_DEBUG`` set to anything but ``0``/empty."""
    args = list(argv)
    flag = DEBUG_FLAG in args
    env = os.environ.get(DEBUG_ENV, "").strip().lower() not in ("", "0", "false", "no")
    return flag or env, [a for a in args if a != DEBUG_FLAG]


def _unwrap(error: BaseException) -> tuple[str, str]:
    """``(type name, message)``, with a DataLoader worker's wrapped exception reduced to the original's."""
    message = str(error).strip()
    if "Original Traceback" in message:  # re-raised from a DataLoader worker: keep the original's last lines
        matches = list(_WORKER_TAIL.finditer(message))
        if matches:
            return matches[-1].group(1), message[matches[-1].end():].strip()
    return type(error).__name__, message


def _is_dataset_error(error: BaseException, name: str) -> bool:
    """A :class:`~dapm_lightning.data.errors.DatasetError` (or one re-raised by a loader worker, by its name).

    Looked up where it was raised, so that this module (imported by every command) imports no data code: the
    top-level ``--help`` stays instant.
    """
    errors = sys.modules.get("dapm_lightning.data.errors")
    return name == "DatasetError" or (errors is not None and isinstance(error, errors.DatasetError))


def _is_download_error(error: BaseException, message: str) -> bool:
    """A failed download from the Hugging Face Hub (timm's pretrained weights), whatever its exception class."""
    chain = [error, error.__cause__, error.__context__]
    from_hub = any(type(e).__module__.startswith("huggingface_hub") for e in chain if e)
    return from_hub or "on the Hub" in message


def _end_progress_line(stream: Any) -> None:
    """End the line a progress bar (tqdm's: Lightning's, the project's) left open, so a message starts on its own."""
    tqdm = sys.modules.get("tqdm")
    bars = getattr(getattr(tqdm, "tqdm", None), "_instances", ()) if tqdm is not None else ()
    if any(not getattr(bar, "disable", True) for bar in list(bars)):
        print(file=stream)


def _union_cause(message: str) -> str | None:
    """The error of the class that was meant, from jsonargparse's report on a union that refused a value.

    ``data`` is a union (a data module or None): a data module refusing its settings is reported as neither type
    fitting, its own message in the middle. None for any other message.
    """
    if not message.startswith("Does not validate against any of the Union subtypes"):
        return None
    errors = message.partition("\nErrors:\n")[2].partition("\nGiven value")[0]
    causes = ["\n".join(line.strip() for line in c.strip().splitlines())
              for c in re.split(r"^  - ", errors, flags=re.MULTILINE) if c.strip()]
    meant = [c for c in causes if not c.startswith("Expected a <class 'NoneType'>")]
    return meant[0] if meant else None


def describe(error: BaseException) -> tuple[str, bool]:
    """``(message, expected)`` for an exception: ``expected`` is False for what looks like a bug."""
    name, message = _unwrap(error)
    message = _union_cause(message) or message
    if _is_dataset_error(error, name):
        fix = getattr(error, "fix", None) or (
            "Fix: correct or remove the files listed (`dapm-lightning doctor ROOT` reports on a whole data set), or "
            "leave them out with --data.init_args.on_bad_file skip.")
        return f"{message}\n{fix}", True
    if getattr(error, "explained", False):  # says what happened and the fix itself (refused or unsaved checkpoints)
        return message, True
    checkpoints = sys.modules.get("dapm_lightning.training.checkpoint_files")  # loaded where it was raised
    if checkpoints is not None and isinstance(error, checkpoints.CheckpointReadError):  # damaged or not a checkpoint
        return f"{message}\n{error.fix}", True
    if _is_download_error(error, message):
        return (f"{name}: {message}\nFix: the backbone's pretrained (ImageNet) weights could not be downloaded (no "
                "internet here?): pass --model.net.weights_path FILE with the weights saved on a machine that has it, "
                "or --model.net.pretrained false to train from random weights (docs/model.md)."), True
    if isinstance(error, OSError) and error.filename and not isinstance(error, FileNotFoundError):
        from dapm_lightning.data import files  # here, not at the top: --help imports no data code

        if error.errno in files.WRITE_ERRNOS:  # a full or read-only disk, a folder not ours, a file in the way
            return str(files.write_error(Path(error.filename), error)), True
    if isinstance(error, _PATH_ERRORS):
        fix = f"Fix: check the path (relative paths start from the current directory, {os.getcwd()})."
        return (message if "Fix" in message else f"{message}\n{fix}"), True
    if message.startswith("Expected more than 1 value per channel when training"):  # BatchNorm of a 1x1 map
        return (f"{message}: a training batch of one image whose deepest feature map is one pixel (the default "
                "encoder divides each side by 32), on which batch normalisation cannot be computed.\nFix: batches of "
                "at least 2 images (--data.init_args.batch_size, and at least that many training images per "
                "process) or images with a side above 32 pixels."), True
    if "EADDRINUSE" in message:  # DDP's rendezvous port (torch's DistNetworkError)
        port = os.environ.get("MASTER_PORT")
        held = f"MASTER_PORT={port} is" if port else "the port is"
        return (f"{name}: {message}\nFix: {held} taken by another program or run on this machine: unset "
                "MASTER_PORT (Lightning then picks a free port) or set it to a free one."), True
    if isinstance(error, ModuleNotFoundError) and (error.name or "").split(".")[0] in EXPORT_MODULES:
        return (f"{name}: {message}: ONNX export and running an .onnx model need the export extra.\n"
                f"Fix: pip install \"dapm-lightning[export]\" ({', '.join(EXPORT_MODULES)})"), True
    if isinstance(error, (ValueError, KeyError)) or name == "ValueError":
        return message, True
    if isinstance(error, (RuntimeError, ImportError, OSError)) or name == "MisconfigurationException":
        return f"{name}: {message}", True  # Lightning's MisconfigurationException: settings it refuses
    return f"{name}: {message}\n(an unexpected error, possibly a bug: rerun with --debug and report the traceback)", \
        False


def run_reporting_errors(function: Callable[[], Any], debug: bool, stream: TextIO | None = None) -> Any:
    """Call ``function``; on an exception print a short message and exit 1 (re-raise it when ``debug``).

    Ctrl-C exits 130: a KeyboardInterrupt, and Lightning's own ``sys.exit(1)`` after one (its graceful
    shutdown). A stop by SIGTERM or a first Ctrl-C during training (``CheckpointOnSigterm``) keeps its status.
    """
    stream = stream or sys.stderr
    try:
        return function()
    except SystemExit as stop:
        if stop.code == EXIT_ERROR and isinstance(stop.__context__, KeyboardInterrupt):  # Lightning's Ctrl-C
            print("\ninterrupted", file=stream)
            raise SystemExit(EXIT_INTERRUPTED) from None
        raise
    except KeyboardInterrupt:
        if debug:
            raise
        print("\ninterrupted", file=stream)
        raise SystemExit(EXIT_INTERRUPTED) from None
    except Exception as error:
        if debug:
            raise
        message, _ = describe(error)
        _end_progress_line(stream)
        print(f"error: {message}", file=stream)
        print(f"(traceback: rerun with {DEBUG_FLAG} or {DEBUG_ENV}=1)", file=stream)
        raise SystemExit(EXIT_ERROR) from None
