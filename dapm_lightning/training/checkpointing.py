"""Checkpoints for long jobs: safe loading in Lightning, ``last.ckpt``, SIGTERM/SIGINT saves (RNG: :mod:`.rng`).

The files themselves (safe reading, atomic writing) are :mod:`.checkpoint_files`'s. :class:`SafeCheckpointIO` is
Lightning's side of both, and :func:`enforce_safe_checkpoint_io` puts it on a trainer whatever its plugins say.
``last.ckpt`` is kept at the latest state (:class:`LastCheckpoint`) and ``--ckpt_path last`` finds the newest
complete one in any of the run's log versions (:func:`resolve_last_checkpoint`). :func:`load_dapm_module` is the
one way to build a model from a checkpoint.
"""

from __future__ import annotations

import inspect
import os
import re
import signal
import sys
import threading
from collections.abc import Iterable, Mapping
from pathlib import Path
from types import FrameType
from typing import Any

import lightning as L
from lightning.fabric.plugins.environments.lightning import LightningEnvironment
from lightning.fabric.plugins.io.checkpoint_io import CheckpointIO
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.fabric.utilities.cloud_io import get_filesystem
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.plugins.io.wrapper import _WrappingCheckpointIO
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities import rank_zero_warn
from lightning.pytorch.utilities.exceptions import SIGTERMException
from torch import Tensor

from dapm_lightning.models.config import DAPMConfig
from dapm_lightning.training.checkpoint_files import (  # the check of foreign files lives there: re-exported
    CheckpointReadError,
    NotADAPMCheckpointError,
    UnsafeCheckpointIOError,
    check_dapm_checkpoint,
    is_remote,
    local_path,
    read_checkpoint,
    remove_unfinished_saves,
    save_atomically,
    some_keys,
)
from dapm_lightning.training.module import DAPMModule
from dapm_lightning.training.signals import request_stop, validation_follows

EXIT_SIGTERM = 128 + signal.SIGTERM
"""Exit status of a run stopped by SIGTERM after saving ``last.ckpt`` (143: a job script can tell it from 0)."""

EXIT_SIGINT = 128 + signal.SIGINT
"""Exit status of a run stopped by SIGINT (Ctrl-C) after saving ``last.ckpt`` (130, as a shell reports it)."""

class SafeCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint I/O, reading safely and writing atomically on any filesystem.

    Loading is :func:`read_checkpoint` whatever ``weights_only`` Lightning passes (tensors and plain values
    only; remote paths read into memory). Saving to a local path is :func:`save_atomically` (a temporary file
    in the checkpoint's folder, renamed when complete; before the first save into a folder, the temporary
    files of killed saves there are removed); saving to a remote path is Lightning's.
    """

    def __init__(self) -> None:
        super().__init__()
        self._cleaned: set[Path] = set()

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        """Write ``checkpoint`` to ``path`` atomically (local paths; remote ones as Lightning does)."""
        if storage_options is not None or is_remote(path):
            super().save_checkpoint(checkpoint, path, storage_options=storage_options)
            return
        folder = local_path(path).parent
        if folder not in self._cleaned:
            self._cleaned.add(folder)
            remove_unfinished_saves([folder], recursive=False)
        save_atomically(checkpoint, path)

    def load_checkpoint(self, path: Any, map_location: Any = lambda storage, loc: storage,
                        weights_only: bool | None = None) -> dict[str, Any]:
        """:func:`read_checkpoint` (``weights_only`` is always True, whatever is passed)."""
        return read_checkpoint(path, map_location=map_location)


class SafeLoadingCheckpointIO(CheckpointIO):
    """A user's ``CheckpointIO`` whose saves are kept and whose loads are :func:`read_checkpoint`."""

    def __init__(self, inner: CheckpointIO) -> None:
        super().__init__()
        self.inner = inner

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        """The wrapped plugin's save."""
        self.inner.save_checkpoint(checkpoint, path, storage_options=storage_options)

    def load_checkpoint(self, path: Any, map_location: Any | None = None,
                        weights_only: bool | None = None) -> dict[str, Any]:
        """:func:`read_checkpoint`."""
        return read_checkpoint(path, map_location=map_location)

    def remove_checkpoint(self, path: Any) -> None:
        """The wrapped plugin's removal."""
        self.inner.remove_checkpoint(path)

    def teardown(self) -> None:
        """The wrapped plugin's teardown."""
        self.inner.teardown()


def safe_checkpoint_io(plugin: CheckpointIO | None) -> CheckpointIO:
    """``plugin`` made safe to load with: the same object, a replacement or a wrapper; else an error.

    - none or Lightning's ``TorchCheckpointIO``: a :class:`SafeCheckpointIO`;
    - a :class:`SafeCheckpointIO` (or subclass): itself;
    - a wrapping plugin (``AsyncCheckpointIO``): itself, its inner plugin made safe the same way;
    - a ``TorchCheckpointIO`` subclass that changes only how checkpoints are saved: wrapped in
      :class:`SafeLoadingCheckpointIO` (its saves, safe loads);
    - any other (it reads checkpoints its own way): :class:`UnsafeCheckpointIOError`.
    """
    if plugin is None or type(plugin) is TorchCheckpointIO:
        return SafeCheckpointIO()
    if isinstance(plugin, (SafeCheckpointIO, SafeLoadingCheckpointIO)):
        return plugin
    if isinstance(plugin, _WrappingCheckpointIO):
        inner = plugin.checkpoint_io
        safe = safe_checkpoint_io(inner)
        if safe is not inner:
            plugin._checkpoint_io = safe  # the public setter keeps an inner plugin once one is set
        return plugin
    if isinstance(plugin, TorchCheckpointIO) and type(plugin).load_checkpoint is TorchCheckpointIO.load_checkpoint:
        return SafeLoadingCheckpointIO(plugin)
    name = f"{type(plugin).__module__}.{type(plugin).__qualname__}"
    raise UnsafeCheckpointIOError(
        f"trainer.plugins: {name} reads checkpoints its own way, which dapm-lightning cannot check is safe (a "
        "checkpoint's pickled code could run).\nFix: derive it from "
        "dapm_lightning.training.checkpointing.SafeCheckpointIO (its load_checkpoint reads with weights_only), "
        "or leave it out of trainer.plugins.")


def enforce_safe_checkpoint_io(trainer: L.Trainer) -> None:
    """Put a safe checkpoint I/O on ``trainer``'s strategy, whatever its plugins (see :func:`safe_checkpoint_io`).

    Called by :class:`~dapm_lightning.training.lightning_cli.DAPMCLI` for every trainer it builds, and by
    :class:`LastCheckpoint` and :class:`CheckpointOnSigterm` when they are set up (before Lightning restores a
    ``ckpt_path``), so that no ``--trainer.plugins`` value can bring back unsafe loading.
    """
    strategy = trainer.strategy
    current = strategy.checkpoint_io  # Lightning's default when no plugin set one
    safe = safe_checkpoint_io(current)
    if safe is not current:
        strategy.checkpoint_io = safe


def load_dapm_module(path: str | Path, map_location: Any = "cpu",
                     net_overrides: Mapping[str, Any] | None = None) -> DAPMModule:
    """A :class:`~dapm_lightning.training.module.DAPMModule` from a checkpoint file, with the checkpoint's settings.

    Loads with :func:`read_checkpoint` (``weights_only=True``: tensors and plain values only). Errors, each
    naming the file: FileNotFoundError; :class:`CheckpointReadError` (a RuntimeError, ``not a readable
    checkpoint``) for a damaged file; :class:`UnsafeCheckpointError` for a file holding pickled code (refused,
    not run); :class:`NotADAPMCheckpointError` (a ValueError) for another model's checkpoint or a bare state dict.

    Args:
        path: a checkpoint written by ``dapm-lightning fit`` (``last.ckpt``, ``best-*.ckpt``) or
            ``trainer.save_checkpoint``: a local file, a ``file://`` path or an ``http(s)://`` (fsspec) address,
            read into memory.
        map_location: where the tensors go (``"cpu"``, ``"cuda:0"``, a ``torch.device``, a function or
            mapping as in ``torch.load``); the module is moved there.
        net_overrides: network settings to change that change no weight (e.g. ``{"depth_readout": "bins_mode"}``);
            an architecture setting (:meth:`~dapm_lightning.models.config.DAPMConfig.architecture_fields`) is refused.

    Returns:
        The module, in training mode as Lightning's ``load_from_checkpoint`` returns it (call ``.eval()``).
        Its backbone is built without ImageNet weights (``pretrained`` and ``weights_path`` are not used:
        every weight comes from the checkpoint), so loading needs no internet.
    """
    checkpoint = read_checkpoint(path, map_location=map_location)
    check_dapm_checkpoint(checkpoint, path)
    accepted = inspect.signature(DAPMModule.__init__).parameters
    settings = {k: v for k, v in checkpoint["hyper_parameters"].items() if k in accepted and k != "self"}
    # the weights come from the checkpoint: no ImageNet download (or local weights file) for the backbone
    settings["net"] = {**settings["net"], "pretrained": False, "weights_path": None}
    settings.pop("init_weights", None)  # where its fit started: not read again
    if net_overrides:
        architecture = sorted(set(net_overrides) & set(DAPMConfig.architecture_fields()))
        if architecture:
            raise ValueError(f"net_overrides cannot change {architecture}: the weights of {path} are built for "
                             "the checkpoint's values")
        settings["net"] = {**settings["net"], **net_overrides}
    module = DAPMModule(**settings)
    module.on_load_checkpoint(checkpoint)
    try:
        module.load_state_dict(checkpoint["state_dict"], strict=True)
    except RuntimeError as error:
        raise NotADAPMCheckpointError(
            f"{path}: its weights do not fit the network its settings describe "
            f"({weights_mismatch(module.state_dict(), checkpoint['state_dict']) or str(error).splitlines()[0]}).\n"
            "Fix: pass a checkpoint written by `dapm-lightning fit`, unmodified.") from error
    first = next((t for t in checkpoint["state_dict"].values() if isinstance(t, Tensor)), None)
    return module.to(first.device) if first is not None else module


def weights_mismatch(expected: Mapping[str, Any], found: Mapping[str, Any]) -> str:
    """How the weights ``found`` in a file differ from those a network ``expected``: missing, unexpected, reshaped.

    E.g. ``2 missing: 'net.a.weight', 'net.a.bias'; 1 of another shape: 'net.b.weight' [8, 3] in the file, [16, 3]
    here``; empty when they agree.
    """
    missing = [key for key in expected if key not in found]
    unexpected = [key for key in found if key not in expected]
    reshaped = [key for key in expected if key in found and isinstance(found[key], Tensor)
                and isinstance(expected[key], Tensor) and found[key].shape != expected[key].shape]
    parts = []
    if missing:
        parts.append(f"{len(missing)} missing: {some_keys(missing, 2)}")
    if unexpected:
        parts.append(f"{len(unexpected)} not in the network: {some_keys(unexpected, 2)}")
    if reshaped:
        key = reshaped[0]
        parts.append(f"{len(reshaped)} of another shape: {key!r} {list(found[key].shape)} in the file, "
                     f"{list(expected[key].shape)} here")
    return "; ".join(parts)


class LastCheckpoint(ModelCheckpoint):
    """Keeps ``last.ckpt`` at the latest training state, whatever the validation metrics do.

    Lightning's ``ModelCheckpoint(monitor=..., save_last=True)`` rewrites ``last.ckpt`` only when it
    saves a new best checkpoint (Lightning >= 2.6): a job whose validation metric stopped improving
    would resume from that old step after a crash. This callback has no monitor; it overwrites
    ``last.ckpt`` every ``every_n_train_steps`` steps (or every ``every_n_epochs`` epochs, the default:
    each epoch) and once more when training ends, if the final step was not saved yet. Keep a
    ``ModelCheckpoint`` with a monitor (without ``save_last``) for the best model.

    A step save that a validation follows is taken after that validation (and after the other callbacks
    have seen it), so the checkpoint holds the validation's results and the best-model state: a run resumed
    from it neither repeats nor skips that validation (from a save before it, Lightning would skip it).
    """

    def __init__(self, dirpath: str | Path | None = None, every_n_train_steps: int | None = None,
                 every_n_epochs: int | None = None) -> None:
        super().__init__(dirpath=dirpath, filename=self.CHECKPOINT_NAME_LAST, monitor=None, save_top_k=1,
                         every_n_train_steps=every_n_train_steps, every_n_epochs=every_n_epochs,
                         enable_version_counter=False)

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        """Lightning's setup, and a safe, atomic checkpoint I/O on the trainer (:func:`enforce_safe_checkpoint_io`).

        Moves itself behind every other callback: its saves come after theirs (a best-model checkpoint's state).
        """
        enforce_safe_checkpoint_io(trainer)
        super().setup(trainer, pl_module, stage)
        self._save_after_validation: int | None = None
        callbacks: list[L.Callback] = trainer.callbacks  # type: ignore[attr-defined]
        if self in callbacks:
            callbacks.remove(self)
            callbacks.append(self)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs: Any, batch: Any,
                           batch_idx: int) -> None:
        step_save = self._every_n_train_steps >= 1 and trainer.global_step % self._every_n_train_steps == 0
        if step_save and validation_follows(trainer):
            self._save_after_validation = trainer.global_step
            return
        super().on_train_batch_end(trainer, pl_module, outputs, batch, batch_idx)

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_validation_end(trainer, pl_module)
        if self._save_after_validation == trainer.global_step and not self._should_skip_saving_checkpoint(trainer):
            self._save_topk_checkpoint(trainer, self._monitor_candidates(trainer))
        self._save_after_validation = None

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_train_end(trainer, pl_module)
        if trainer.sanity_checking or getattr(trainer, "fast_dev_run", False) or trainer.global_step == 0:
            return
        if self._last_global_step_saved != trainer.global_step:  # the final step fell between two saves
            self.best_model_path = self.format_checkpoint_name({})
            trainer.save_checkpoint(self.best_model_path, weights_only=False)  # the full state, said (no log line)
            self._last_global_step_saved = trainer.global_step


def best_or_last_checkpoint(trainer: L.Trainer) -> str:
    """The path of the best checkpoint of a finished fit, else its ``last.ckpt`` ("" when neither exists)."""
    saved = fit_checkpoints_summary(trainer)
    return saved[0][1] if saved else ""


def fit_checkpoints_summary(trainer: L.Trainer) -> list[tuple[str, str]]:
    """What a finished fit saved: (what it is, path) for every best checkpoint, with its score, then ``last.ckpt``.

    Every best checkpoint comes before any last one, whatever the order of the callbacks. Only files that are there
    are named (saves are atomic: a file there is whole); [] when there are none.
    """
    best: list[tuple[str, str]] = []
    last: list[tuple[str, str]] = []

    def there(path: str) -> bool:
        return bool(path) and path not in {each for _, each in best + last} and get_filesystem(path).isfile(path)

    callbacks = [callback for callback in trainer.checkpoint_callbacks if isinstance(callback, ModelCheckpoint)]
    for callback in callbacks:
        path = callback.best_model_path
        if callback.monitor is not None and there(path):
            score = callback.best_model_score
            shown = f"{callback.monitor} {float(score):.4g}" if score is not None else callback.monitor
            best.append((f"best checkpoint ({shown})", path))
    for callback in callbacks:
        path = callback.best_model_path if isinstance(callback, LastCheckpoint) else callback.last_model_path
        if there(path):  # LastCheckpoint's one file, or a user's ModelCheckpoint(save_last=True)
            # the step of the callback's own last save: a ModelCheckpoint(save_last=True) saves last.ckpt with its
            # top-k files, which need not be at the fit's final step
            step = getattr(callback, "_last_global_step_saved", trainer.global_step)
            last.append((f"last checkpoint (step {step})", path))
    return best + last


def _last_files(roots: Iterable[str | Path]) -> list[Path]:
    found = {path for root in roots if local_path(root).is_dir() for path in local_path(root).rglob("last*.ckpt")
             if re.fullmatch(r"last(-v?\d+)?\.ckpt", path.name) and path.is_file()}
    return sorted(found, key=lambda path: path.stat().st_mtime_ns, reverse=True)


def find_last_checkpoint(roots: Iterable[str | Path]) -> Path | None:
    """The newest ``last.ckpt`` (or ``last-N.ckpt``) anywhere under ``roots``, or None.

    Not loaded (:func:`resolve_last_checkpoint` skips damaged files). What ``--ckpt_path last`` resumes from: a
    resumed run logs into a new version folder (``tensorboard/version_1``), where Lightning's own lookup would find
    nothing and start from scratch.
    """
    found = _last_files(roots)
    return found[0] if found else None


def resolve_last_checkpoint(roots: Iterable[str | Path], folders: Iterable[str | Path] = (),
                            start_from_scratch: bool = True) -> tuple[Path, dict[str, Any]] | None:
    """The checkpoint to resume from, loaded: what ``--ckpt_path last`` takes.

    The newest ``last.ckpt`` under ``roots`` (any log version). If it cannot be loaded (truncated, corrupt) it is
    skipped with a warning naming it, and the newest complete checkpoint is taken instead: another ``last.ckpt``,
    or another checkpoint (``best-*.ckpt``...) in a folder holding one or in ``folders``, whichever was written
    last. A file holding pickled code stops the search (:class:`UnsafeCheckpointError`).

    Args:
        roots: the run's folders (``default_root_dir``, the loggers' ``save_dir``...), searched recursively.
        folders: checkpoint folders (the callbacks' ``dirpath``), searched for other checkpoints.
        start_from_scratch: warn that the run starts from scratch when no checkpoint can be loaded (``fit``);
            False for a caller that refuses to run then (``validate``, ``test``, ``predict``).

    Returns:
        ``(path, checkpoint)``, or None when there is no ``last.ckpt`` or no complete checkpoint.
    """
    lasts = _last_files(roots)
    if not lasts:
        return None  # no last.ckpt at all: a first run starts from scratch
    places = dict.fromkeys([*(path.parent for path in lasts), *(local_path(f) for f in folders)])
    others = {path for folder in places if folder.is_dir() for path in folder.glob("*.ckpt") if path.is_file()}
    rest = sorted(others.union(lasts[1:]) - set(lasts[:1]), key=lambda path: path.stat().st_mtime_ns, reverse=True)
    candidates = lasts[:1] + rest
    for path in candidates:
        try:
            return path, read_checkpoint(path)
        except CheckpointReadError as error:
            reason = str(error).split(": not a readable checkpoint ", 1)[-1]
            rank_zero_warn(f"--ckpt_path last: skipping {path}: it cannot be loaded {reason}; taking the newest "
                           "complete checkpoint instead")
    if candidates and start_from_scratch:
        rank_zero_warn(f"--ckpt_path last: none of the {len(candidates)} checkpoint(s) found can be loaded; starting "
                       "from scratch")
    return None


def started_by_lightning(trainer: L.Trainer) -> bool:
    """Whether this process is one Lightning's launcher started beside the main one (``devices: N`` on a machine).

    Lightning's watcher in the main process kills every process, the main one included, as soon as one of
    those it started exits with a status other than 0. After a stop by SIGTERM or Ctrl-C they all exit, each
    when it is done; one that exits with 143 before the main one would get the main process killed (status
    -9 instead of 143, so a job script would not requeue). Those processes therefore exit 0 after such a stop;
    the main process, whose status the shell and the job script see, exits 143 or 130. Processes a cluster
    starts (SLURM, torchrun) keep 143 and 130: the cluster reads each one's status.
    """
    environment = getattr(trainer.strategy, "cluster_environment", None)
    return trainer.local_rank != 0 and type(environment) is LightningEnvironment


class CheckpointOnSigterm(L.Callback):
    """On SIGTERM (SLURM pre-emption) or SIGINT (Ctrl-C), save ``last.ckpt`` and exit with status 143 or 130.

    Lightning stops at the end of the current batch with a ``SIGTERMException`` (with a ``DAPMModule``, at the end of
    the accumulation window, or of the validation that follows it: :mod:`.signals`); during training this writes the
    checkpoint the run resumes from with ``--ckpt_path last`` (validate, test and predict save nothing: they have no
    training state). Lightning's exception exits with status 0, as a finished run would; this sets it to
    :data:`EXIT_SIGTERM` (128 + 15 = 143, the shell's status for a process ended by SIGTERM), so that a job script
    can tell pre-emption from completion and requeue.

    SIGINT during training is handled the same way (Lightning alone would stop in the middle of a step and exit
    1 without saving): the run stops where it would for SIGTERM, saves ``last.ckpt`` and exits with
    :data:`EXIT_SIGINT` (130). A second SIGINT stops at once without saving (the previous ``last.ckpt`` stays
    complete); SIGINT before training starts (set-up, sanity check) also stops at once. Under DDP the first
    SIGINT to the main process is passed on to the others, as Lightning does with SIGTERM. DataLoader workers
    forked from a training process ignore SIGINT: a Ctrl-C in a terminal reaches the whole process group, and
    a worker that stopped would fail the batches still to come.
    """

    def __init__(self) -> None:
        super().__init__()
        self._stopped_by: int | None = None
        self._previous_handler: Any = None
        self._pid: int | None = None
        self._trainer: L.Trainer | None = None
        self._training = False

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        """A safe checkpoint I/O on the trainer."""
        enforce_safe_checkpoint_io(trainer)
        self._stopped_by, self._training = None, False

    def on_sanity_check_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """The SIGINT handler, before the validation loaders' workers start (they inherit it, and ignore SIGINT)."""
        self._handle_sigint(trainer)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """From here a SIGINT stops at the end of a batch, with ``last.ckpt`` saved."""
        self._handle_sigint(trainer)
        self._training = True

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        """After the training loop, a SIGINT stops at once."""
        self._training = False

    def _handle_sigint(self, trainer: L.Trainer) -> None:
        # installed after Lightning recorded the process's signal handlers, which it puts back when fit ends
        if self._pid != os.getpid() and threading.current_thread() is threading.main_thread():
            self._pid, self._trainer = os.getpid(), trainer
            self._previous_handler = signal.signal(signal.SIGINT, self._on_sigint)

    def _on_sigint(self, signum: int, frame: FrameType | None) -> None:
        if os.getpid() != self._pid:
            return  # a DataLoader worker forked from the training process: the training process decides
        trainer = self._trainer
        if trainer is None or not self._training or (self._stopped_by == signal.SIGINT and trainer.is_global_zero):
            self._restore_sigint()
            raise KeyboardInterrupt  # before training, or a second Ctrl-C: stop at once (exit status 130)
        if self._stopped_by is None:
            self._stopped_by = signal.SIGINT
            if trainer.is_global_zero:  # os.write: safe inside a signal handler (print may not be)
                os.write(2, b"\nReceived SIGINT (Ctrl-C): saving last.ckpt at the end of this training step (and of "
                            b"its validation), then exiting (Ctrl-C again stops at once, without saving)\n")
            launcher = trainer.strategy.launcher
            if launcher is not None:
                launcher.kill(signal.SIGINT)  # DDP processes started by this one, as Lightning does for SIGTERM
        request_stop(trainer, signum)  # as SIGTERM: after the optimizer step (end of the batch without accumulation)

    def _restore_sigint(self) -> None:
        if self._pid == os.getpid() and signal.getsignal(signal.SIGINT) == self._on_sigint:
            signal.signal(signal.SIGINT, self._previous_handler)
        self._pid = None

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        """Save ``last.ckpt`` (training only) and set the exit status, for a stop by SIGTERM or SIGINT."""
        self._restore_sigint()
        if not isinstance(exception, SIGTERMException):
            return
        if trainer.state.fn == TrainerFn.FITTING:
            self._save_last(trainer)
        # the process exits with it once every callback's on_exception ran
        exception.code = EXIT_SIGINT if self._stopped_by == signal.SIGINT else EXIT_SIGTERM
        if started_by_lightning(trainer):
            exception.code = 0  # see started_by_lightning: the main process reports the status

    def teardown(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        """Give SIGINT back to the handler it had before ``fit``."""
        self._restore_sigint()
        self._trainer = None

    @staticmethod
    def _save_last(trainer: L.Trainer) -> None:
        last = [cb for cb in trainer.checkpoint_callbacks if isinstance(cb, LastCheckpoint)]
        checkpoint = last[0] if last else trainer.checkpoint_callback
        folder = getattr(checkpoint, "dirpath", None) or Path(trainer.default_root_dir) / "checkpoints"
        path = Path(folder) / "last.ckpt"
        trainer.save_checkpoint(path, weights_only=False)  # the full state
        if checkpoint is not None and hasattr(checkpoint, "last_model_path"):
            checkpoint.last_model_path = str(path)
        if trainer.is_global_zero:
            print(f"saved {path} (step {trainer.global_step}); resume with the same command and --ckpt_path last",
                  file=sys.stderr, flush=True)
