"""int8 models: onnxruntime static quantisation of an exported float32 model, calibrated on synthetic renders.

What is quantised is chosen by the network module each ONNX node comes from (the exporter records it in the
node's ``namespace`` metadata): the convolutions of the encoder, the depth decoder, the depth head, the IGD
feature, the depth bins blocks and the convex-upsample mask (:data:`QUANTISED_SCOPES`) get int8 weights (one
scale per output channel) and uint8 activations. Everything else stays float32: DAPMNet's own arithmetic (the
log-depth decode to metres, the IGD, the pose decode, the resizes), the bins' softmax and soft-argmax, the
convex-upsample softmax and mixing, and the whole pose branch, whose pooled features and small linear layers
lose the pose medians when quantised and cost little in float.
"""

from __future__ import annotations

import re
import tempfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dapm_lightning.geometry.depth_codec import grey_to_depth
from dapm_lightning.geometry.image import unit_image
from dapm_lightning.inference.onnx import onnx_feed

QUANTISED_SCOPES = ("net.encoder", "net.depth_decoder", "net.to_head", "net.igd_feature", "net.depth_pqb.blocks",
                    "net.depth_pqb.head", "net.upsample.mask")
"""Network modules whose convolutions are quantised (prefixes of PyTorch module paths)."""
QUANTISED_OPS = ("Conv", "Relu", "Add", "MaxPool", "Resize", "Concat")
"""The op types quantised inside :data:`QUANTISED_SCOPES` (a Relu, Add or Concat between two int8
convolutions stays in int8 instead of going through float)."""
CALIBRATION_SEED = 0
"""The generator seed of the calibration renders (split ``calibration``)."""
HELD_OUT_SEED = 1
"""The generator seed of the held-out renders (split ``test``): images the calibration does not see."""
_SCOPE = re.compile(r"(?:^|/)(net(?:\.[\w]+)*): ")


@dataclass(frozen=True)
class Render:
    """One synthetic render.

    ``image [1, 3, H, W]`` float32 in [0, 1], ``depth_m [1, 1, H, W]`` (the depth limit where the render is sky,
    as the data sets store it), ``pose [4]`` (height m, pitch, roll, fov deg).
    """

    image: np.ndarray
    depth_m: np.ndarray
    pose: np.ndarray


def render_set(size: tuple[int, int], count: int, *, seed: int = HELD_OUT_SEED, split: str = "test",
               start: int = 0) -> list[Render]:
    """``count`` images of the project's generator at ``size`` ``(H, W)``: every scene family, camera effects on.

    The depth goes through the data sets' 8-bit grey encoding, as the model was trained and tested on it.
    """
    from dapm_lightning.data.synthetic.generate import render_sample
    from dapm_lightning.data.uapd import parse_uapd_filename, pose_from_parsed

    renders = []
    for index in range(start, start + count):
        name, rgb, grey, _ = render_sample(seed, split, index, size)
        image = unit_image(torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)[None]))).numpy()
        depth = grey_to_depth(grey).astype(np.float32)[None, None]
        renders.append(Render(image, depth, pose_from_parsed(parse_uapd_filename(name)).astype(np.float32)))
    return renders


def synthetic_calibration(size: tuple[int, int], count: int, seed: int = CALIBRATION_SEED) -> list[np.ndarray]:
    """``count`` ``[1, 3, H, W]`` float32 RGB renders in [0, 1] at ``size``, from the ``calibration`` split."""
    return [r.image for r in render_set(size, count, seed=seed, split="calibration")]


def calibration_images(train_size: tuple[int, int], export_size: tuple[int, int], *, at_train: int = 64,
                       at_export: int = 16) -> list[np.ndarray]:
    """The calibration set: renders at the training size, and some at the export size.

    ``at_train`` at the checkpoint's training size (the activation ranges it learnt), and ``at_export`` more at the
    export size when that differs (those of larger inputs).
    """
    images = synthetic_calibration(train_size, at_train)
    if tuple(export_size) != tuple(train_size):
        images += [r.image for r in render_set(export_size, at_export, seed=CALIBRATION_SEED, split="calibration",
                                               start=at_train)]
    return images


def node_scope(node: Any) -> str:
    """The PyTorch module path an exported ONNX node comes from (``"net.encoder.body.layer1.0"``; ``""`` if none)."""
    namespace = next((p.value for p in node.metadata_props if p.key == "namespace"), "")
    scopes = _SCOPE.findall(namespace)
    return scopes[-1] if scopes else ""


def quantised_nodes(nodes: Iterable[Any], scopes: Sequence[str] = QUANTISED_SCOPES,
                    op_types: Sequence[str] = QUANTISED_OPS) -> list[str]:
    """Names of the nodes to quantise: ops of ``op_types`` from modules under ``scopes``."""
    def inside(scope: str) -> bool:
        return any(scope == s or scope.startswith(s + ".") for s in scopes)

    return [n.name for n in nodes if n.op_type in op_types and inside(node_scope(n))]


def quantize_int8(float_path: str | Path, int8_path: str | Path, calibration: Sequence[np.ndarray], *,
                  per_channel: bool = True, scopes: Sequence[str] = QUANTISED_SCOPES) -> Path:
    """Onnxruntime static int8 quantisation (QDQ: int8 weights, uint8 activations, MinMax calibration).

    Args:
        float_path: the float32 ONNX model (:func:`~dapm_lightning.inference.onnx.export_onnx`).
        int8_path: the quantised model; same inputs and outputs, so it runs wherever the float model does.
        calibration: ``[1, 3, H, W]`` float32 images in [0, 1] (:func:`calibration_images`).
        per_channel: one weight scale per output channel (more accurate; default).
        scopes: the network modules quantised (:data:`QUANTISED_SCOPES`); the rest stays float32.
    """
    import onnx
    import onnxruntime.quantization as quantization

    class Images(quantization.CalibrationDataReader):  # type: ignore[misc]  # onnxruntime is untyped
        def __init__(self) -> None:
            self.items = iter(calibration)

        def get_next(self) -> dict[str, np.ndarray] | None:
            image = next(self.items, None)
            if image is None:
                return None
            return onnx_feed(image, input_names)  # calibrated without telemetry: the network's own pose

    int8_path = Path(int8_path)
    int8_path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as folder:
        inline, prepared = Path(folder) / "float.onnx", Path(folder) / "prepared.onnx"
        float_model = onnx.load(str(float_path))
        onnx.save(float_model, str(inline))  # weights inside (the exporter may write NAME.onnx.data)
        # chosen on the export: its nodes name their module; the pre-processing keeps node names but may drop that
        in_scope = set(quantised_nodes(float_model.graph.node, scopes))
        quantization.quant_pre_process(str(inline), str(prepared), skip_symbolic_shape=True)  # shapes
        model = onnx.load(str(prepared), load_external_data=False)
        input_names = [i.name for i in model.graph.input]
        chosen = [n.name for n in model.graph.node if n.name in in_scope]
        if not chosen:
            raise ValueError(f"{float_path}: no node of {', '.join(scopes)} found (not a dapm-lightning export?)")
        # a LayerNormalization's scale is 1-D: its channels are on axis 0 (the default, 1, is out of range)
        axes = {"LayerNormalization": 0, "InstanceNormalization": 0, "BatchNormalization": 0}
        quantization.quantize_static(
            str(prepared), str(int8_path), Images(), quant_format=quantization.QuantFormat.QDQ,
            activation_type=quantization.QuantType.QUInt8, weight_type=quantization.QuantType.QInt8,
            per_channel=per_channel, nodes_to_quantize=chosen, op_types_to_quantize=list(QUANTISED_OPS),
            calibrate_method=quantization.CalibrationMethod.MinMax,
            extra_options={"QDQOpTypePerChannelSupportToAxis": axes})
    return int8_path
