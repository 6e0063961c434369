"""dapm-lightning export: an ONNX model (image in; depth, sky probability and/or pose out), checked on the spot.

Any DAPM checkpoint exports: the full model (depth_m, sky_prob, pose), DAPM(D) (depth_m, sky_prob) and
DAPM(P) (pose). Batch, height and width are dynamic by default (height and width multiples of 32, as
the predict path feeds them); --fp16 true stores the weights and runs the network in half precision with
float32 input and outputs. After writing, onnxruntime and PyTorch run the same random inputs at two
sizes and the largest difference of each output is printed. Settings can come from a YAML file
(--config FILE; --print_config shows one).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

OUTPUT_NAMES = ("depth_m", "sky_prob", "pose")
_ATTRIBUTES = {"depth_m": "depth_m", "sky_prob": "sky_prob", "pose": "pose_physical"}
"""ONNX output name -> ``DAPMOutput`` attribute."""
SIZE_MULTIPLE = 32
"""Exported models take heights and widths that are multiples of this (the network's total stride)."""


class ExportWrapper(nn.Module):
    """``image [B, 3, H, W]`` float RGB in [0, 1] -> the model's outputs among ``depth_m``, ``sky_prob``, ``pose``.

    ``depth_m [B, 1, H, W]`` metres (sky set to the depth limit), ``sky_prob [B, 1, H, W]``, ``pose [B, 4]``
    (height m, pitch, roll, fov deg); :attr:`names` lists those this model has. ``half``: the network runs in
    float16 (call after ``net.half()``); input and outputs stay float32.
    """

    def __init__(self, net: nn.Module, half: bool = False) -> None:
        super().__init__()
        self.net, self.half_precision = net, half
        dtype = next(net.parameters()).dtype
        with torch.no_grad():
            out = net(torch.rand(1, 3, SIZE_MULTIPLE * 2, SIZE_MULTIPLE * 2, dtype=dtype))
        self.names = tuple(name for name in OUTPUT_NAMES if getattr(out, _ATTRIBUTES[name]) is not None)
        self.eval()

    def forward(self, image: Tensor) -> tuple[Tensor, ...]:
        out = self.net(image.half() if self.half_precision else image)
        return tuple(getattr(out, _ATTRIBUTES[name]).float() for name in self.names)


def _adaptive_avg_pool2d(x: Tensor, output_size: Any) -> Tensor:
    """``F.adaptive_avg_pool2d`` in ops that keep the input size symbolic (prefix sums and gathered bounds).

    Same windows as PyTorch (``floor(i H / n)`` to ``ceil((i + 1) H / n)``); PyTorch's own decomposition bakes
    the example's indices into the ONNX graph, which then fails at any other size.
    """
    n_h, n_w = (output_size, output_size) if isinstance(output_size, int) else output_size

    def pool(values: Tensor, dim: int, n: int) -> Tensor:
        size = values.shape[dim]
        index = torch.arange(n, device=values.device)
        start, end = (index * size) // n, ((index + 1) * size + n - 1) // n
        sums = torch.cat([torch.zeros_like(values.narrow(dim, 0, 1)), values.cumsum(dim)], dim)
        shape = [1] * values.ndim
        shape[dim] = n
        counts = (end - start).to(values.dtype).view(shape)
        return (sums.index_select(dim, end) - sums.index_select(dim, start)) / counts

    return pool(pool(x, x.ndim - 1, n_w), x.ndim - 2, n_h)


class _ExportFunctional:
    """``torch.nn.functional`` with :func:`_adaptive_avg_pool2d` in place of PyTorch's."""

    adaptive_avg_pool2d = staticmethod(_adaptive_avg_pool2d)

    def __getattr__(self, name: str) -> Any:
        return getattr(F, name)


@contextlib.contextmanager
def dynamic_size_ops() -> Iterator[None]:
    """While exporting, the pose decoder's depth pooling uses size-symbolic ops (numerically the same)."""
    from dapm_lightning.models import decoders

    original = decoders.F
    decoders.F = _ExportFunctional()  # type: ignore[assignment]
    try:
        yield
    finally:
        decoders.F = original


def check_sizes(size: tuple[int, int], dynamic: bool) -> list[tuple[int, int, int]]:
    """``(batch, H, W)`` of the inputs compared with PyTorch: the export size, and another one if dynamic."""
    sizes = [(1, *size)]
    if dynamic:
        sizes.append((2, max(SIZE_MULTIPLE, size[0] - SIZE_MULTIPLE), size[1] + SIZE_MULTIPLE))
    return sizes


def export_onnx(net: nn.Module, path: str | Path, size: tuple[int, int], *, checks: int = 3, seed: int = 0,
                dynamic: bool = True, fp16: bool = False) -> list[dict[str, Any]]:
    """Export ``net`` (a :class:`DAPMNet`) and compare onnxruntime with PyTorch (float32) on random images.

    Args:
        net: the network (left unchanged). path: the ``.onnx`` file. size: ``(H, W)`` of the example input.
        checks: random inputs per checked size. dynamic: dynamic batch, height and width (multiples of 32).
        fp16: half-precision weights and arithmetic.

    Returns:
        one row per random input: ``shape`` and the max absolute difference of each output (``depth_m`` in
        metres, ``pose`` in metres/degrees).
    """
    import copy

    import onnxruntime

    if dynamic and (size[0] % SIZE_MULTIPLE or size[1] % SIZE_MULTIPLE):
        raise ValueError(f"height and width must be multiples of {SIZE_MULTIPLE} for a dynamic export, got {size}")
    reference = ExportWrapper(net.eval())
    model = ExportWrapper(copy.deepcopy(net).eval().half(), half=True) if fp16 else reference
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    example = torch.rand(2 if dynamic else 1, 3, *size)
    dynamic_shapes = None
    if dynamic:
        batch = torch.export.Dim("batch", min=1, max=4096)
        height = torch.export.Dim("height_32", min=1, max=1024)
        width = torch.export.Dim("width_32", min=1, max=1024)
        dynamic_shapes = {"image": {0: batch, 2: SIZE_MULTIPLE * height, 3: SIZE_MULTIPLE * width}}
    with dynamic_size_ops(), torch.no_grad():
        torch.onnx.export(model, (example,), str(path), input_names=["image"], output_names=list(model.names),
                          dynamo=True, dynamic_shapes=dynamic_shapes, verbose=False)
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    generator = torch.Generator().manual_seed(seed)
    rows = []
    for shape in check_sizes(size, dynamic):
        for _ in range(checks):
            image = torch.rand(shape[0], 3, *shape[1:], generator=generator)
            with torch.no_grad():
                expected = reference(image)
            got = session.run(None, {"image": image.numpy()})
            rows.append({"shape": shape, **{name: float(np.abs(g - e.numpy()).max())
                                            for name, g, e in zip(model.names, got, expected)}})
    return rows


def export(ckpt_path: Path, out: Path | None = None, height: int = 512, width: int = 512, dynamic: bool = True,
           fp16: bool = False, checks: int = 2) -> Path:
    """Export a DAPM checkpoint to ONNX and check it with onnxruntime against PyTorch.

    Args:
        ckpt_path: the checkpoint (any DAPM: full, DAPM(D), DAPM(P)); loaded with weights_only=True.
        out: the ONNX file (default: the checkpoint's path with .onnx, or _fp16.onnx).
        height: example input height (and the checked size); a multiple of 32 when dynamic.
        width: example input width; a multiple of 32 when dynamic.
        dynamic: dynamic batch, height and width; false: fixed [1, 3, height, width].
        fp16: half-precision weights and arithmetic (float32 input and outputs); for GPUs and Jetsons.
        checks: random inputs compared with PyTorch at each checked size.
    """
    from dapm_lightning.training.module import DAPMModule

    ckpt_path = Path(ckpt_path)
    if not ckpt_path.is_file():
        raise FileNotFoundError(f"{ckpt_path}: no such checkpoint file")
    module = DAPMModule.load_from_checkpoint(str(ckpt_path), map_location="cpu", weights_only=True)
    out = Path(out) if out else ckpt_path.with_name(ckpt_path.stem + ("_fp16" if fp16 else "") + ".onnx")
    start = time.perf_counter()
    rows = export_onnx(module.net.eval(), out, (height, width), checks=checks, dynamic=dynamic, fp16=fp16)
    names = [k for k in rows[0] if k != "shape"]
    shape = "[batch, 3, height, width] (multiples of 32)" if dynamic else f"[1, 3, {height}, {width}]"
    print(f"wrote {out} in {time.perf_counter() - start:.0f} s: input 'image' {shape} float RGB in [0, 1]; "
          f"outputs {', '.join(names)}{'; float16 inside' if fp16 else ''}")
    for row in rows:
        print(f"check {tuple(row['shape'])}: max |onnxruntime - PyTorch fp32|: "
              + ", ".join(f"{n} {row[n]:.3g}" for n in names))
    return out


def export_main(argv: Sequence[str]) -> None:
    """``dapm-lightning export --ckpt_path CKPT [--out FILE] [--height H --width W] [--fp16 true]``."""
    from jsonargparse import auto_cli

    auto_cli(export, args=list(argv), as_positional=False, prog="dapm-lightning export", description=__doc__)
