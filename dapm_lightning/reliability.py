"""Long-job safety: checkpoint I/O with clear errors, a save on SIGTERM, RNG states in checkpoints.

Also the training sampler whose order is a function of (seed, epoch), so a resumed run continues exactly.
"""

from __future__ import annotations

import random
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.utilities.exceptions import SIGTERMException

ARCHITECTURE_KEYS = ("backbone", "use_depth", "use_pose", "depth_bins", "pose_bins", "use_igd_feature",
                     "decoder_channels", "head_channels", "igd_channels", "head_stride", "pose_hidden")
"""Hyper-parameters that change the weights' shapes: a checkpoint must agree on them to be loaded."""


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


def check_architecture(saved: Mapping[str, Any], current: Mapping[str, Any], source: str) -> None:
    """Raise a ValueError listing every architecture hyper-parameter that differs."""
    def norm(value: Any) -> Any:
        return list(value) if isinstance(value, (list, tuple)) else value

    differences = [f"{key}: checkpoint {norm(saved[key])!r}, this run {norm(current[key])!r}"
                   for key in ARCHITECTURE_KEYS
                   if key in saved and key in current and norm(saved[key]) != norm(current[key])]
    if differences:
        raise ValueError(f"{source} was trained with another model configuration; it cannot be loaded into "
                         f"this one:\n  " + "\n  ".join(differences))


def rng_states() -> dict[str, Any]:
    """Python, numpy and torch RNG states as tensors and plain values (safe for ``weights_only`` loading)."""
    numpy_state = np.random.get_state()
    return {"python": random.getstate(), "numpy_keys": torch.from_numpy(numpy_state[1].astype(np.int64)),
            "numpy_pos": int(numpy_state[2]), "torch": torch.get_rng_state()}


def set_rng_states(states: Mapping[str, Any]) -> None:
    """Restore what :func:`rng_states` saved."""
    version, internal, gauss = states["python"]
    random.setstate((version, tuple(internal), gauss))
    np.random.set_state(("MT19937", states["numpy_keys"].numpy().astype(np.uint32), states["numpy_pos"], 0, 0.0))
    torch.set_rng_state(states["torch"])


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


class EpochShuffleSampler(torch.utils.data.Sampler[int]):
    """A shuffle that is a function of (seed, epoch), which can skip the batches a resumed run already saw.

    Lightning calls :meth:`set_epoch` before each epoch. ``on_epoch`` is called with the epoch too
    (the data set uses it to seed its augmentation per (seed, epoch, index)).
    """

    def __init__(self, length: int, seed: int = 0, on_epoch: Callable[[int], None] | None = None) -> None:
        self.length, self.seed, self.epoch, self.on_epoch = length, seed, 0, on_epoch
        self.skip_epoch, self.skip_samples = -1, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch
        if self.on_epoch is not None:
            self.on_epoch(epoch)

    def resume(self, epoch: int, samples_seen: int) -> None:
        """Skip the first ``samples_seen`` samples of ``epoch`` (a run restarted mid-epoch)."""
        self.skip_epoch, self.skip_samples = epoch, samples_seen

    def __iter__(self) -> Iterator[int]:
        order = torch.randperm(self.length, generator=torch.Generator().manual_seed(self.seed * 100003 + self.epoch))
        start = self.skip_samples if self.epoch == self.skip_epoch else 0
        return iter(order[start:].tolist())

    def __len__(self) -> int:
        return self.length
