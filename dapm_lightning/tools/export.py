"""dapm-lightning export: an ONNX model (image in; depth, sky probability and/or pose out), checked on the spot.

Any DAPM checkpoint exports: the full model (depth_m, sky_prob, pose, with the telemetry inputs prior and
prior_sigma), DAPM(D) (depth_m, sky_prob) and DAPM(P) (pose). Batch, height and width are dynamic by default
(any size: the predict path feeds the same network size as PyTorch). The file carries the network's settings
and training size as metadata, so `dapm-lightning predict SOURCE --ckpt_path MODEL.onnx` needs nothing else.
--fp16 true stores the weights and runs the network in half precision with
float32 input and outputs; --int8 true quantises it for CPUs and edge boards (onnxruntime static QDQ
quantisation, calibrated on images the synthetic generator renders; same input and outputs). After writing,
onnxruntime and PyTorch run the same random inputs at two sizes and the largest difference of each output is
printed. A large model's weights go beside the graph in NAME.onnx.data (keep both files together). Settings
can come from a YAML file (--config FILE; --print_config shows one).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

from dapm_lightning.inference.inputs import checkpoint_network_size, network_size
from dapm_lightning.inference.onnx import export_metadata, export_onnx, write_metadata


def export(ckpt_path: Path, out: Path | None = None, height: int | None = None, width: int | None = None,
           dynamic: bool = True, fp16: bool = False, checks: int = 2, int8: bool = False,
           calibration_images: int = 32) -> Path:
    """Export a DAPM checkpoint to ONNX and check it with onnxruntime against PyTorch.

    Args:
        ckpt_path: the checkpoint (any DAPM: full, DAPM(D), DAPM(P)); loaded with weights_only=True.
        out: the ONNX file (default: the checkpoint's path with .onnx, or _fp16.onnx).
        height: example input height (and the checked size). Default: the checkpoint's training size.
        width: example input width. Default: the checkpoint's training size.
        dynamic: dynamic batch, height and width (any size); false: fixed [1, 3, height, width].
        fp16: half-precision weights and arithmetic (float32 input and outputs); for GPUs and Jetsons.
        checks: random inputs compared with PyTorch at each checked size.
        int8: static int8 quantisation (QDQ, per-channel weights) of the float32 model; written as
            NAME_int8.onnx; the float32 model is written too (NAME.onnx).
        calibration_images: synthetic images rendered at the example size to calibrate the int8 ranges.
    """
    from dapm_lightning.training.checkpointing import load_dapm_module

    ckpt_path = Path(ckpt_path)
    module = load_dapm_module(ckpt_path, map_location="cpu")
    trained = checkpoint_network_size(module)
    if height is None or width is None:
        height, width = network_size(height or trained[0], width or trained[1], None)
    if int8 and fp16:
        raise ValueError("--int8 quantises the float32 model: leave --fp16 out")
    suffix = "_fp16" if fp16 else "_int8" if int8 else ""
    out = Path(out) if out else ckpt_path.with_name(ckpt_path.stem + suffix + ".onnx")
    float_out = out.with_name(out.stem.removesuffix("_int8") + ".onnx") if int8 else out
    if float_out == out:
        float_out = out.with_name(out.stem + "_float32.onnx") if int8 else out
    start = time.perf_counter()
    metadata = {**export_metadata(module.net, module.train_image_size, ckpt_path),
                "dapm.precision": "float16" if fp16 else "float32"}
    rows = export_onnx(module.net.eval(), float_out, (height, width), checks=checks, dynamic=dynamic, fp16=fp16,
                       metadata=metadata)
    if int8:
        _quantize(float_out, out, (height, width), calibration_images)
        write_metadata(out, {**metadata, "dapm.precision": "int8"})  # the int8 file runs on its own too
    names = [k for k in rows[0] if k != "shape"]
    shape = "[batch, 3, height, width]" if dynamic else f"[1, 3, {height}, {width}]"
    data = out.with_name(out.name + ".data")
    weights = f" (weights in {data.name}: keep it beside the .onnx file)" if data.is_file() else ""
    print(f"wrote {out}{weights} in {time.perf_counter() - start:.0f} s: input 'image' {shape} float RGB in [0, 1]; "
          f"outputs {', '.join(names)}{'; float16 inside' if fp16 else ''}")
    for row in rows:
        print(f"check {tuple(row['shape'])}: max |onnxruntime - PyTorch fp32|: "
              + ", ".join(f"{n} {row[n]:.3g}" for n in names))
    return out


def _quantize(float_out: Path, out: Path, size: tuple[int, int], images: int) -> None:
    import numpy as np
    import onnxruntime

    from dapm_lightning.inference.onnx import onnx_feed
    from dapm_lightning.inference.quantize import quantize_int8, synthetic_calibration

    start = time.perf_counter()
    quantize_int8(float_out, out, synthetic_calibration(size, images))
    sessions = [onnxruntime.InferenceSession(str(p), providers=["CPUExecutionProvider"]) for p in (float_out, out)]
    names = [o.name for o in sessions[0].get_outputs()]
    gaps = dict.fromkeys(names, 0.0)
    for image in synthetic_calibration(size, 4, seed=1):  # images the calibration did not see
        reference, got = (s.run(None, onnx_feed(image, [i.name for i in s.get_inputs()])) for s in sessions)
        gaps = {n: max(gaps[n], float(np.abs(g - r).max())) for n, g, r in zip(names, got, reference)}
    print(f"wrote {out} in {time.perf_counter() - start:.0f} s: int8 (QDQ), calibrated on {images} synthetic images; "
          f"float32 model {float_out}; max |int8 - float32| on 4 other synthetic images: "
          + ", ".join(f"{n} {v:.3g}" for n, v in gaps.items()))


def export_main(argv: Sequence[str]) -> None:
    """``dapm-lightning export --ckpt_path CKPT [--out FILE] [--height H --width W] [--fp16 true]``."""
    from jsonargparse import auto_cli

    auto_cli(export, args=list(argv), as_positional=False, prog="dapm-lightning export", description=__doc__)
