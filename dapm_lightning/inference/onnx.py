"""ONNX: the network as an ONNX model (image in; depth, sky probability and/or pose out), checked on the spot.

Outputs are named as :data:`~dapm_lightning.models.dapm.INFERENCE_OUTPUTS` (those the model has). Batch, height
and width are dynamic by default (height and width multiples of 32). The ops that differ while exporting are
defined where the network uses them (:func:`dapm_lightning.models.blocks.adaptive_avg_pool2d`). PyTorch's
exporter writes the weights of a large model beside the graph, in ``NAME.onnx.data``: keep the two files together.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from dapm_lightning.inference.inputs import SIZE_MULTIPLE


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
        self.names = tuple(out.inference_outputs().named())
        self.eval()

    def forward(self, image: Tensor) -> tuple[Tensor, ...]:
        outputs = self.net(image.half() if self.half_precision else image).inference_outputs().named()
        return tuple(outputs[name].float() for name in self.names)


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
    # a dynamic dimension traced at 1 x 32 would be specialised to 1 by torch.export: trace at 64 or more
    traced = tuple(max(side, 2 * SIZE_MULTIPLE) for side in size) if dynamic else size
    example = torch.rand(2 if dynamic else 1, 3, *traced)
    dynamic_shapes = None
    if dynamic:
        batch = torch.export.Dim("batch", min=1, max=4096)
        height = torch.export.Dim("height_32", min=1, max=1024)
        width = torch.export.Dim("width_32", min=1, max=1024)
        dynamic_shapes = {"image": {0: batch, 2: SIZE_MULTIPLE * height, 3: SIZE_MULTIPLE * width}}
    with torch.no_grad():  # the network's export-time ops: models.blocks.adaptive_avg_pool2d
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


def onnx_session(module: nn.Module, path: Path) -> Any:
    """An onnxruntime session of ``path``, exported from ``module`` (dynamic sizes, checked) when missing."""
    import onnxruntime

    if not path.is_file():
        export_onnx(getattr(module, "net", module).eval(), path, (64, 64), checks=1, dynamic=True)
    return onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
