"""Random states in checkpoints: saved in types a ``weights_only`` load accepts, per process under DDP.

A resumed run draws what the uninterrupted one would (dropout, augmentation): :class:`DAPMModule` saves these
states in every checkpoint and restores them on load.
"""

from __future__ import annotations

import math
import random
from collections.abc import Mapping
from typing import Any, cast

import numpy as np
import torch
from torch import Tensor


def rng_states() -> dict[str, Any]:
    """Python, NumPy, CPU torch and (when CUDA is initialised) every GPU's RNG state, as tensors and plain values.

    Lightning's own ``_collect_rng_states`` keeps NumPy's state as an ``ndarray``, which a
    ``weights_only`` load refuses; these are the same states in types such a load accepts.
    """
    numpy_state = cast(tuple[Any, ...], np.random.get_state())
    states: dict[str, Any] = {"python": random.getstate(),
                              "numpy_keys": torch.from_numpy(numpy_state[1].astype(np.int64)),
                              "numpy_pos": int(numpy_state[2]), "torch": torch.get_rng_state()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():  # type: ignore[no-untyped-call]
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
