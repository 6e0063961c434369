"""int8 models: onnxruntime static quantisation of an exported float32 model, calibrated on synthetic renders."""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from dapm_lightning.geometry.image import unit_image
from dapm_lightning.inference.onnx import onnx_feed


def synthetic_calibration(size: tuple[int, int], count: int, seed: int = 0) -> list[np.ndarray]:
    """Images the project's generator renders, as ``[1, 3, H, W]`` float32 RGB in [0, 1].

    Every scene family, camera effects on: int8 calibration data that needs no data set.
    """
    from dapm_lightning.data.synthetic.generate import render_sample

    images = []
    for index in range(count):
        _, rgb, _, _ = render_sample(seed, "calibration", index, size)
        images.append(unit_image(torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)[None]))).numpy())
    return images


def quantize_int8(float_path: str | Path, int8_path: str | Path, calibration: Sequence[np.ndarray], *,
                  per_channel: bool = True) -> Path:
    """Onnxruntime static int8 quantisation (QDQ: int8 weights, uint8 activations, MinMax calibration).

    Args:
        float_path: the float32 ONNX model (:func:`export_onnx`).
        int8_path: the quantised model; same input and outputs, so it runs wherever the float model does.
        calibration: ``[1, 3, H, W]`` float32 images in [0, 1] (:func:`synthetic_calibration`).
        per_channel: one weight scale per output channel (more accurate; default).
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

    input_names = [i.name for i in onnx.load(str(float_path), load_external_data=False).graph.input]
    int8_path = Path(int8_path)
    int8_path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as folder:
        inline, prepared = Path(folder) / "float.onnx", Path(folder) / "prepared.onnx"
        onnx.save(onnx.load(str(float_path)), str(inline))  # weights inside (the exporter may write NAME.onnx.data)
        quantization.quant_pre_process(str(inline), str(prepared), skip_symbolic_shape=True)  # shapes, graph fused
        quantization.quantize_static(str(prepared), str(int8_path), Images(), quant_format=quantization.QuantFormat.QDQ,
                                     activation_type=quantization.QuantType.QUInt8,
                                     weight_type=quantization.QuantType.QInt8, per_channel=per_channel,
                                     calibrate_method=quantization.CalibrationMethod.MinMax)
    return int8_path
