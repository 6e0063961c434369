"""Checkpoints for long jobs: safe loading, ``last.ckpt``, SIGTERM saves (RNG states: :mod:`.rng`).

``last.ckpt`` is kept at the latest state (:class:`LastCheckpoint`) and ``--ckpt_path last`` finds it in
any of the run's log versions (:func:`find_last_checkpoint`). :func:`load_dapm_module` is the one way to
build a model from a checkpoint file: safe loading, and a clear error for damaged files and for files
that are not dapm-lightning checkpoints.
"""

from __future__ import annotations

import inspect
import re
import signal
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import lightning as L
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities.exceptions import SIGTERMException
from torch import Tensor

from dapm_lightning.training.module import DAPMModule

EXIT_SIGTERM = 128 + signal.SIGTERM
"""Exit status of a run stopped by SIGTERM after saving ``last.ckpt`` (143: a job script can tell it from 0)."""


class SafeCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint I/O with safe loading.

    Writes are Lightning's (atomic: an fsspec transaction). Loading uses ``weights_only=True`` by
    default (no arbitrary pickled code) and names the file when it cannot read it.
    """

    def load_checkpoint(self, path: Any, map_location: Any = lambda storage, loc: storage,
                        weights_only: bool | None = None) -> dict[str, Any]:
        try:
            return super().load_checkpoint(path, map_location=map_location,
                                           weights_only=True if weights_only is None else weights_only)
        except FileNotFoundError:
            raise
        except Exception as error:  # torch raises RuntimeError / UnpicklingError / EOFError for damaged files
            size = Path(path).stat().st_size if Path(path).is_file() else 0
            raise RuntimeError(f"{path}: not a readable checkpoint ({size} bytes; truncated, corrupt, or "
                               f"holding objects that weights_only loading refuses): {error}") from error


class NotADAPMCheckpointError(ValueError):
    """A readable file that is not a dapm-lightning checkpoint (another model's, a bare state dict...)."""


def _some_keys(keys: Iterable[Any], count: int = 3) -> str:
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
            return (f"a plain PyTorch state dict, {whose} ({_some_keys(checkpoint, 2)}), without the settings "
                    "that rebuild the network")
        return f"a dictionary with the keys {_some_keys(checkpoint, 6)}, not a Lightning checkpoint"
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
    shown = f"; settings {_some_keys([k for k in settings if not str(k).startswith('_')], 4)}" if settings else ""
    return f"{kind}{model}: {len(state_dict)} weight tensor(s) such as {_some_keys(state_dict, 2)}{shown}"


def check_dapm_checkpoint(checkpoint: Any, source: str | Path) -> None:
    """Raise :class:`NotADAPMCheckpointError` (a ValueError naming ``source`` and the fix) unless ours."""
    what = foreign_checkpoint(checkpoint)
    if what is None:
        return
    fix = ("Fix: pass a checkpoint written by `dapm-lightning fit` (the run's checkpoints/last.ckpt or best-*.ckpt)")
    if "DAPM" in what:
        fix += ("; to use bare DAPM weights, build the model with the settings they were trained with and call "
                "`DAPMModule(net=...).load_state_dict(...)`")
    raise NotADAPMCheckpointError(f"{source}: not a dapm-lightning checkpoint ({what}).\n{fix}.")


def load_dapm_module(path: str | Path, map_location: Any = "cpu") -> DAPMModule:
    """A :class:`~dapm_lightning.training.module.DAPMModule` from a checkpoint file, with the checkpoint's settings.

    Loads with ``weights_only=True`` (:class:`SafeCheckpointIO`: tensors and plain values only). Errors, each
    naming the file: FileNotFoundError; RuntimeError ``not a readable checkpoint`` for a damaged file;
    :class:`NotADAPMCheckpointError` (a ValueError) for another model's checkpoint or a bare state dict.

    Args:
        path: a checkpoint written by ``dapm-lightning fit`` (``last.ckpt``, ``best-*.ckpt``) or
            ``trainer.save_checkpoint``.
        map_location: where the tensors go (``"cpu"``, ``"cuda:0"``, a ``torch.device``, a function or
            mapping as in ``torch.load``); the module is moved there.

    Returns:
        The module, in training mode as Lightning's ``load_from_checkpoint`` returns it (call ``.eval()``).
        Its backbone is built without ImageNet weights (``pretrained`` and ``weights_path`` are not used:
        every weight comes from the checkpoint), so loading needs no internet.
    """
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: no such checkpoint file")
    checkpoint = SafeCheckpointIO().load_checkpoint(path, map_location=map_location)
    check_dapm_checkpoint(checkpoint, path)
    accepted = inspect.signature(DAPMModule.__init__).parameters
    settings = {k: v for k, v in checkpoint["hyper_parameters"].items() if k in accepted and k != "self"}
    # the weights come from the checkpoint: no ImageNet download (or local weights file) for the backbone
    settings["net"] = {**settings["net"], "pretrained": False, "weights_path": None}
    module = DAPMModule(**settings)
    module.on_load_checkpoint(checkpoint)
    try:
        module.load_state_dict(checkpoint["state_dict"], strict=True)
    except RuntimeError as error:
        raise NotADAPMCheckpointError(
            f"{path}: its weights do not fit the network its settings describe ({str(error).splitlines()[0]}).\n"
            "Fix: pass a checkpoint written by `dapm-lightning fit`, unmodified.") from error
    first = next((t for t in checkpoint["state_dict"].values() if isinstance(t, Tensor)), None)
    return module.to(first.device) if first is not None else module


class LastCheckpoint(ModelCheckpoint):
    """Keeps ``last.ckpt`` at the latest training state, whatever the validation metrics do.

    Lightning's ``ModelCheckpoint(monitor=..., save_last=True)`` rewrites ``last.ckpt`` only when it
    saves a new best checkpoint (Lightning >= 2.6): a job whose validation metric stopped improving
    would resume from that old step after a crash. This callback has no monitor; it overwrites
    ``last.ckpt`` every ``every_n_train_steps`` steps (or every ``every_n_epochs`` epochs, the default:
    each epoch) and once more when training ends, if the final step was not saved yet. Keep a
    ``ModelCheckpoint`` with a monitor (without ``save_last``) for the best model.
    """

    def __init__(self, dirpath: str | Path | None = None, every_n_train_steps: int | None = None,
                 every_n_epochs: int | None = None) -> None:
        super().__init__(dirpath=dirpath, filename=self.CHECKPOINT_NAME_LAST, monitor=None, save_top_k=1,
                         every_n_train_steps=every_n_train_steps, every_n_epochs=every_n_epochs,
                         enable_version_counter=False)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        super().on_train_end(trainer, pl_module)
        if trainer.sanity_checking or getattr(trainer, "fast_dev_run", False) or trainer.global_step == 0:
            return
        if self._last_global_step_saved != trainer.global_step:  # the final step fell between two saves
            self.best_model_path = self.format_checkpoint_name({})
            trainer.save_checkpoint(self.best_model_path)
            self._last_global_step_saved = trainer.global_step


def best_or_last_checkpoint(trainer: L.Trainer) -> str:
    """The path of the best checkpoint of a finished fit, else its ``last.ckpt`` ("" when neither exists)."""
    callbacks = [cb for cb in trainer.checkpoint_callbacks if isinstance(cb, ModelCheckpoint)]
    best = [cb.best_model_path for cb in callbacks if cb.monitor is not None]
    last = [cb.best_model_path for cb in callbacks if isinstance(cb, LastCheckpoint)]  # its one file
    last += [cb.last_model_path for cb in callbacks]  # a user's ModelCheckpoint(save_last=True)
    return next((path for path in best + last if path and Path(path).is_file()), "")


def find_last_checkpoint(roots: Iterable[str | Path]) -> Path | None:
    """The newest ``last.ckpt`` (or ``last-N.ckpt``) anywhere under ``roots``, or None.

    What ``--ckpt_path last`` resumes from: a resumed run logs into a new version folder
    (``tensorboard/version_1``), where Lightning's own lookup would find nothing and start from scratch.
    """
    found = [path for root in roots if Path(root).is_dir() for path in Path(root).rglob("last*.ckpt")
             if re.fullmatch(r"last(-v?\d+)?\.ckpt", path.name)]
    return max(found, key=lambda path: path.stat().st_mtime_ns) if found else None


class CheckpointOnSigterm(L.Callback):
    """On SIGTERM (what SLURM sends before pre-emption), save ``last.ckpt``, then exit with status 143.

    Lightning stops at the end of the current batch with a ``SIGTERMException``; during training this
    writes the checkpoint the run resumes from with ``--ckpt_path last`` (validate, test and predict save
    nothing: they have no training state). Lightning's exception exits with status 0, as a finished run
    would; this sets it to :data:`EXIT_SIGTERM` (128 + 15 = 143, the shell's status for a process ended by
    SIGTERM), so that a job script can tell pre-emption from completion and requeue.
    """

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        if not isinstance(exception, SIGTERMException):
            return
        if trainer.state.fn == TrainerFn.FITTING:
            self._save_last(trainer)
        exception.code = EXIT_SIGTERM  # the process exits with it once every callback's on_exception ran

    @staticmethod
    def _save_last(trainer: L.Trainer) -> None:
        last = [cb for cb in trainer.checkpoint_callbacks if isinstance(cb, LastCheckpoint)]
        checkpoint = last[0] if last else trainer.checkpoint_callback
        folder = getattr(checkpoint, "dirpath", None) or Path(trainer.default_root_dir) / "checkpoints"
        path = Path(folder) / "last.ckpt"
        trainer.save_checkpoint(path)
        if checkpoint is not None and hasattr(checkpoint, "last_model_path"):
            checkpoint.last_model_path = str(path)
