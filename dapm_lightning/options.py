"""The values the command-line options offer, in a module that imports nothing heavy.

``dapm-lightning predict --help`` builds its parser from these without importing PyTorch (seconds on a small
machine); the modules that use them (``inference.writers``, ``inference.runtime``, ``inference.inputs``,
``models.prior``) import them from here, so each is defined once.
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable
from typing import Final, Literal, get_args

DEFAULT_BATCH_SIZE: Final[int] = 4
"""Images per forward pass in prediction, unless told otherwise (every entry point)."""

Precision = Literal["32", "bf16", "16"]
"""Arithmetic of the PyTorch runtime: float32, or autocast to bfloat16 / float16 (half precision: GPUs)."""
PRECISIONS: Final[tuple[str, ...]] = get_args(Precision)

Output = Literal["depth_npy", "depth_tiff", "depth16", "depth_color", "sky", "camera", "points", "npz"]
"""A per-image file kind."""
OUTPUT_KINDS: Final[tuple[str, ...]] = get_args(Output)
DEFAULT_OUTPUTS: Final[tuple[str, ...]] = ("depth_color", "sky", "camera")
"""What is written per image when nothing is chosen: light files to look at and the camera; raw depth and the
point cloud on request (``all``: every kind)."""

PriorMode = Literal["condition", "scale", "both"]
"""How pose priors are used in prediction: ``condition`` (into the network, fused before its IGD feature),
``scale`` (the network's depth fitted to the known pose's ground afterwards; any checkpoint) or ``both``."""
PRIOR_MODES: Final[tuple[str, ...]] = get_args(PriorMode)
EXACT_SIGMA: Final[tuple[float, float, float, float]] = (0.0, 0.0, 0.0, 0.0)
"""The default telemetry σ (height m, pitch, roll, fov deg): the telemetry replaces the network's values."""
IGD_BOUND_MARGIN: Final[float] = 0.1
"""The IGD bound's margin: depth may exceed the flat ground of the known pose by 10 % (terrain up to 10 % of the
slant range below the take-off level, the telemetry height's own error); docs/predict.md."""


def check_outputs(outputs: Iterable[str] | str | None) -> list[str]:
    """The chosen output kinds, in their order (default :data:`DEFAULT_OUTPUTS`).

    Names may come one by one or comma-separated (``depth_npy,camera``); ``all`` is every kind. An unknown one
    is refused in one line with the closest kind and the valid list.
    """
    given = DEFAULT_OUTPUTS if outputs is None else [outputs] if isinstance(outputs, str) else outputs
    chosen: list[str] = []
    for item in given:
        for kind in (k.strip() for k in str(item).split(",")):
            if kind == "all":
                chosen += OUTPUT_KINDS
            elif kind not in OUTPUT_KINDS:
                close = difflib.get_close_matches(kind, OUTPUT_KINDS, n=1)
                raise ValueError(f"unknown output {kind!r}{f' (did you mean {close[0]}?)' if close else ''}; "
                                 f"choose from {', '.join(OUTPUT_KINDS)} or all")
            elif kind:
                chosen.append(kind)
    return list(dict.fromkeys(chosen))
