"""Checkpoints for long jobs: safe loading, the architecture check, RNG states, ``last.ckpt``, SIGTERM saves.

``last.ckpt`` is kept at the latest state (:class:`LastCheckpoint`) and ``--ckpt_path last`` finds it in
any of the run's log versions (:func:`find_last_checkpoint`).
"""

from __future__ import annotations

import math
import random
import re
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities.exceptions import SIGTERMException
from torch import Tensor

from dapm_lightning.models.config import DAPMConfig


class SafeCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint I/O with safe loading.

    Writes are Lightning's (atomic: an fsspec transaction). Loading uses ``weights_only=True`` by
    default (no arbitrary pickled code) and names the file when it cannot read it.
    """

    def load_checkpoint(self, path: Any, map_location: Callable[..., Any] | None = lambda storage, loc: storage,
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


def check_architecture(saved: Mapping[str, Any] | DAPMConfig, current: DAPMConfig, source: str) -> None:
    """Raise a ValueError listing every architecture setting (:meth:`DAPMConfig.architecture_fields`) that differs.

    Args:
        saved: the network settings a checkpoint was trained with (``hyper_parameters["net"]``).
        current: this run's.
        source: what ``saved`` came from, for the message (a checkpoint path).
    """
    saved_config = saved if isinstance(saved, DAPMConfig) else DAPMConfig.from_dict(saved)
    differences = [f"model.net.{name}: checkpoint {getattr(saved_config, name)!r}, this run "
                   f"{getattr(current, name)!r}"
                   for name in DAPMConfig.architecture_fields()
                   if getattr(saved_config, name) != getattr(current, name)]
    if differences:
        raise ValueError(f"{source} was trained with another network; it cannot be loaded into this one:\n  "
                         + "\n  ".join(differences)
                         + "\nFix: pass the config it was trained with (the config.yaml next to its log), or set "
                           "the settings above to the checkpoint's values.")


def rng_states() -> dict[str, Any]:
    """Python, NumPy, CPU torch and (when CUDA is initialised) every GPU's RNG state, as tensors and plain values.

    Lightning's own ``_collect_rng_states`` keeps NumPy's state as an ``ndarray``, which a
    ``weights_only`` load refuses; these are the same states in types such a load accepts.
    """
    numpy_state = np.random.get_state()
    states: dict[str, Any] = {"python": random.getstate(),
                              "numpy_keys": torch.from_numpy(numpy_state[1].astype(np.int64)),
                              "numpy_pos": int(numpy_state[2]), "torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def pack_rng_states(states: Mapping[str, Any]) -> dict[str, Tensor]:
    """:func:`rng_states` as fixed-shape tensors, so that every process's can be gathered into one checkpoint."""
    version, internal, gauss = states["python"]
    packed = {"python": torch.tensor([version, *internal], dtype=torch.int64),
              "python_gauss": torch.tensor([math.nan if gauss is None else gauss], dtype=torch.float64),
              "numpy_keys": states["numpy_keys"], "numpy_pos": torch.tensor([states["numpy_pos"]]),
              "torch": states["torch"]}
    if "cuda" in states:
        packed["cuda"] = states["cuda"][torch.cuda.current_device()]
    return packed


def unpack_rng_states(packed: Mapping[str, Tensor]) -> dict[str, Any]:
    """Inverse of :func:`pack_rng_states` (the GPU state becomes that of the current device)."""
    python = packed["python"].tolist()
    gauss = float(packed["python_gauss"][0])
    states: dict[str, Any] = {"python": (python[0], tuple(python[1:]), None if math.isnan(gauss) else gauss),
                              "numpy_keys": packed["numpy_keys"], "numpy_pos": int(packed["numpy_pos"][0]),
                              "torch": packed["torch"]}
    if "cuda" in packed and torch.cuda.is_available():
        states["cuda"] = [torch.cuda.get_rng_state(d) for d in range(torch.cuda.device_count())]
        states["cuda"][torch.cuda.current_device()] = packed["cuda"]
    return states


def set_rng_states(states: Mapping[str, Any]) -> None:
    """Restore what :func:`rng_states` saved (GPU states when saved and this process has as many GPUs)."""
    version, internal, gauss = states["python"]
    random.setstate((version, tuple(internal), gauss))
    np.random.set_state(("MT19937", states["numpy_keys"].numpy().astype(np.uint32), states["numpy_pos"], 0, 0.0))
    torch.set_rng_state(states["torch"])
    cuda = states.get("cuda")
    if cuda is not None and torch.cuda.is_available() and len(cuda) == torch.cuda.device_count():
        torch.cuda.set_rng_state_all(cuda)


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
        if trainer.sanity_checking or trainer.fast_dev_run or trainer.global_step == 0:
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
    """On SIGTERM (what SLURM sends before pre-emption), save ``last.ckpt`` before the process exits.

    Lightning stops at the end of the current batch with a ``SIGTERMException``; this writes the
    checkpoint the run resumes from with ``--ckpt_path last``.
    """

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        if not isinstance(exception, SIGTERMException):
            return
        last = [cb for cb in trainer.checkpoint_callbacks if isinstance(cb, LastCheckpoint)]
        checkpoint = last[0] if last else trainer.checkpoint_callback
        folder = getattr(checkpoint, "dirpath", None) or Path(trainer.default_root_dir) / "checkpoints"
        path = Path(folder) / "last.ckpt"
        trainer.save_checkpoint(path)
        if checkpoint is not None and hasattr(checkpoint, "last_model_path"):
            checkpoint.last_model_path = str(path)
