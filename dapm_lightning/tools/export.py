"""``dapm-lightning export``: ONNX model (image in; depth, sky probability and pose out), checked on the spot."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

OUTPUT_NAMES = ("depth_m", "sky_prob", "pose")


class ExportWrapper(nn.Module):
    """``image [1, 3, H, W]`` float RGB in [0, 1] -> ``(depth_m [1,1,H,W], sky_prob [1,1,H,W], pose [1,4])``."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, image: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        out = self.net(image)
        if out.depth_m is None or out.pose_physical is None or out.sky_prob is None:
            raise ValueError("ONNX export needs a model with depth, sky map and pose (full DAPM)")
        return out.depth_m, out.sky_prob, out.pose_physical


def export_onnx(net: nn.Module, path: str | Path, size: tuple[int, int], *, checks: int = 3,
                seed: int = 0) -> list[dict[str, float]]:
    """Export ``net`` (a :class:`DAPMNet`) at a fixed input size and compare onnxruntime with PyTorch.

    Returns:
        per random input, the max absolute difference of each output (``depth_m`` in metres).
    """
    import onnxruntime

    wrapper = ExportWrapper(net).eval()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    example = torch.rand(1, 3, *size)
    with torch.no_grad():
        wrapper(example)  # a model without the needed outputs fails here, with a plain message
    torch.onnx.export(wrapper, (example,), str(path), input_names=["image"], output_names=list(OUTPUT_NAMES),
                      dynamo=True)
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    generator = torch.Generator().manual_seed(seed)
    diffs = []
    for _ in range(checks):
        image = torch.rand(1, 3, *size, generator=generator)
        with torch.no_grad():
            reference = wrapper(image)
        outputs = session.run(None, {"image": image.numpy()})
        diffs.append({name: float(np.abs(got - ref.numpy()).max())
                      for name, got, ref in zip(OUTPUT_NAMES, outputs, reference)})
    return diffs


def export_main(argv: Sequence[str]) -> None:
    """``dapm-lightning export --ckpt_path CKPT --format onnx [--out FILE] [--height H --width W]``."""
    parser = argparse.ArgumentParser(prog="dapm-lightning export", description=__doc__)
    parser.add_argument("--ckpt_path", type=Path, required=True)
    parser.add_argument("--format", choices=["onnx"], default="onnx")
    parser.add_argument("--out", type=Path, default=None, help="output file (default: next to the checkpoint)")
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--checks", type=int, default=3, help="random inputs compared with PyTorch")
    args = parser.parse_args(list(argv))
    from dapm_lightning.training.module import DAPMModule

    module = DAPMModule.load_from_checkpoint(str(args.ckpt_path), map_location="cpu", weights_only=True)
    out = args.out or args.ckpt_path.with_suffix(".onnx")
    diffs = export_onnx(module.net.eval(), out, (args.height, args.width), checks=args.checks)
    print(f"wrote {out} (input 'image' [1, 3, {args.height}, {args.width}] float RGB in [0, 1]; "
          f"outputs {', '.join(OUTPUT_NAMES)})")
    for k, diff in enumerate(diffs):
        print(f"check {k}: max |onnxruntime - PyTorch|: " + ", ".join(f"{n} {v:.3g}" for n, v in diff.items()))
