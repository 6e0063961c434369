"""Checkpoints for long jobs: safe loading with clear errors, the architecture check, RNG states, a save on SIGTERM."""

from __future__ import annotations

import math
import random
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
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


class CheckpointOnSigterm(L.Callback):
    """On SIGTERM (what SLURM sends before pre-emption), save ``last.ckpt`` before the process exits.

    Lightning stops at the end of the current batch with a ``SIGTERMException``; this writes the
    checkpoint the run resumes from with ``--ckpt_path last``.
    """

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        if not isinstance(exception, SIGTERMException):
            return
        checkpoint = trainer.checkpoint_callback
        folder = getattr(checkpoint, "dirpath", None) or Path(trainer.default_root_dir) / "checkpoints"
        path = Path(folder) / "last.ckpt"
        trainer.save_checkpoint(path)
        if checkpoint is not None and hasattr(checkpoint, "last_model_path"):
            checkpoint.last_model_path = str(path)
