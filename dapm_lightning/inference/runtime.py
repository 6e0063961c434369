"""Runtimes: what runs the network in prediction, behind one small interface.

A :class:`Runtime` takes a batch of images at the network size and the prior the network may be given, and
returns an :class:`~dapm_lightning.models.dapm.InferenceOutput`; the post-processing after it is the same for
all (:func:`~dapm_lightning.inference.postprocess.batch_predictions`). :class:`TorchRuntime` runs a PyTorch
module (eager or ``torch.compile``, channels-last, autocast); :class:`OnnxRuntime` an exported ONNX model in
onnxruntime. A new runtime (TensorRT, OpenVINO, ...) is one more class with ``takes_prior`` and ``__call__``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Final, Literal, Protocol, get_args

import torch
from torch import Tensor, nn

from dapm_lightning.geometry.image import unit_image
from dapm_lightning.inference.inputs import SIZE_MULTIPLE, network_size, resize_images
from dapm_lightning.models.dapm import InferenceOutput
from dapm_lightning.models.prior import PosePrior

Precision = Literal["32", "bf16", "16"]
"""Arithmetic of the PyTorch runtime: float32, or autocast to bfloat16 / float16 (half precision: GPUs)."""
PRECISIONS: Final[tuple[str, ...]] = get_args(Precision)


class Runtime(Protocol):
    """Runs the network on ``[B, 3, h, w]`` images (uint8, or float in [0, 1]) at the network size."""

    takes_prior: bool
    """Whether a pose prior can be given to the network (else it is applied afterwards, ``scale`` mode)."""

    def __call__(self, images: Tensor, prior: PosePrior | None = None) -> InferenceOutput:
        """The outputs at the network size (``pose_spread`` included, for fusing a prior afterwards)."""
        ...


def resolve_device(device: str) -> str:
    """``"auto"``: ``"cuda"`` when a GPU is there, else ``"cpu"``; ``"cuda"`` without one is refused."""
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: no CUDA GPU is available here (use --device cpu or auto)")
    return device


def apply_inference_options(module: nn.Module, channels_last: bool, compile: bool) -> nn.Module:
    """Channels-last and/or ``torch.compile`` on ``module``'s network in place; returns ``module``."""
    net = getattr(module, "net", module)
    if channels_last:
        net.to(memory_format=torch.channels_last)
    if compile and not getattr(net, "_dapm_compiled", False):
        net.compile(dynamic=False)
        net._dapm_compiled = True
    return module


class TorchRuntime:
    """A PyTorch module returning a ``DAPMOutput`` (a ``DAPMModule`` or a ``DAPMNet``), in eval mode on ``device``.

    Args:
        module: the model. device: ``cpu``, ``cuda``, ``cuda:N`` or ``auto``.
        precision: ``32``, ``bf16`` or ``16`` (autocast). channels_last: NHWC convolutions.
        compile: ``torch.compile`` the network (each new input size compiles again).
    """

    takes_prior = True

    def __init__(self, module: nn.Module, device: str = "cpu", precision: Precision = "32",
                 channels_last: bool = False, compile: bool = False) -> None:
        if str(precision) not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
        self.device = torch.device(resolve_device(device))
        self.precision, self.channels_last = str(precision), channels_last
        self.module = apply_inference_options(module.eval().to(self.device), channels_last, compile)

    def _autocast(self) -> Any:
        if self.precision == "32":
            return torch.autocast(self.device.type, enabled=False)
        return torch.autocast(self.device.type, dtype=torch.bfloat16 if self.precision == "bf16" else torch.float16)

    @torch.no_grad()
    def __call__(self, images: Tensor, prior: PosePrior | None = None) -> InferenceOutput:
        images = unit_image(images.to(self.device, non_blocking=True))
        if self.channels_last:
            images = images.contiguous(memory_format=torch.channels_last)
        with self._autocast():
            out = self.module(images, prior.to(self.device)) if prior is not None else self.module(images)
        return out.inference_outputs(spread=True)


class OnnxRuntime:
    """An exported ONNX model (``dapm-lightning export``) in onnxruntime on the CPU, float32.

    The model takes no prior (telemetry is applied after it, ``scale`` mode). Its input sides are multiples of
    32: images are resized to the nearest such size, and the outputs resized back by the post-processing.
    """

    takes_prior = False

    def __init__(self, path: str | Path, session: Any = None) -> None:
        import onnxruntime

        self.path = Path(path)
        self.session = session or onnxruntime.InferenceSession(str(self.path), providers=["CPUExecutionProvider"])
        self.names = [output.name for output in self.session.get_outputs()]

    def __call__(self, images: Tensor, prior: PosePrior | None = None) -> InferenceOutput:
        feed = unit_image(images.cpu()).float()
        feed = resize_images(feed, network_size(feed.shape[-2], feed.shape[-1], None, SIZE_MULTIPLE))
        values = self.session.run(None, {"image": feed.numpy()})
        return InferenceOutput(**{name: torch.from_numpy(value) for name, value in zip(self.names, values)})
