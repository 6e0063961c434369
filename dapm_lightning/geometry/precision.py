"""Float32 islands inside mixed precision: the geometry and the losses never compute in bf16 / fp16.

Under ``torch.autocast`` (Lightning's ``bf16-mixed``, predict's ``precision: bf16``) the network's layers
return bf16 tensors. A height of 57.3 m is 57.25 in bf16, and ``log2`` / ``exp2`` of the depth codec lose
two decimal digits; so every function marked :func:`float32` (IGD, depth codec, pose normalisation, bin
targets, ``DAPMLoss``) casts its half-precision tensor arguments to float32 and runs with autocast switched
off. Gradients flow back through the casts. The metrics compute in float64 whatever they are handed.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, ParamSpec, TypeVar

import torch

P = ParamSpec("P")
R = TypeVar("R")

_HALF = (torch.bfloat16, torch.float16)


def _map_tensors(value: Any, fn: Callable[[torch.Tensor], torch.Tensor]) -> Any:
    """``value`` with ``fn`` applied to every tensor in it (tensors, tuples, named tuples, lists, dicts)."""
    if isinstance(value, torch.Tensor):
        return fn(value)
    if isinstance(value, tuple):
        items = [_map_tensors(item, fn) for item in value]
        return type(value)(*items) if hasattr(value, "_fields") else tuple(items)
    if isinstance(value, list):
        return [_map_tensors(item, fn) for item in value]
    if isinstance(value, dict):
        return type(value)((key, _map_tensors(item, fn)) for key, item in value.items())
    return value


def to_float32(value: Any) -> Any:
    """``value`` with every bf16 / fp16 tensor in it cast to float32 (tensors, tuples, named tuples, lists, dicts)."""
    return _map_tensors(value, lambda t: t.float() if t.dtype in _HALF else t)


def _half_dtype(value: Any) -> torch.dtype | None:
    found: list[torch.dtype] = []

    def note(tensor: torch.Tensor) -> torch.Tensor:
        if tensor.dtype in _HALF:
            found.append(tensor.dtype)
        return tensor

    _map_tensors(value, note)
    return found[0] if found else None


def _autocasting() -> bool:
    return torch.is_autocast_enabled("cpu") or torch.is_autocast_enabled("cuda")


def held_in(value: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``value`` in the dtype of a network held in half precision (``like``'s), outside autocast; else as it is.

    A float32 result fed to such a network's layers (the IGD of a pose fused with a float32 prior) must be cast.
    """
    if like.dtype in (torch.float16, torch.bfloat16) and not _autocasting() and value.dtype == torch.float32:
        return value.to(like.dtype)
    return value


def float32(fn: Callable[P, R]) -> Callable[P, R]:
    """Decorator: run ``fn`` in float32 with autocast off; its bf16 / fp16 tensor arguments are cast first.

    Inside autocast the float32 results stay float32 (autocast casts them for the next layer). Outside
    autocast, half-precision arguments mean a network held in half precision (``export --fp16``): its
    float32 results are cast back to that dtype, computed in float32 all the same.
    """

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R:
        half = _half_dtype((args, kwargs))
        autocasting = _autocasting()
        # plain autocast contexts (CPU and CUDA, what the project runs on): torch.compile traces them unbroken
        with torch.autocast("cpu", enabled=False), torch.autocast("cuda", enabled=False):
            result = fn(*to_float32(args), **to_float32(kwargs))
        if half is None or autocasting:
            return result
        returned: R = _map_tensors(result, lambda t: t.to(half) if t.dtype == torch.float32 else t)
        return returned

    return wrapper
