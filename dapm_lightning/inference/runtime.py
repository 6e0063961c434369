"""Runtimes: what runs the network in prediction, behind one small interface.

A :class:`Runtime` takes a batch of images at the network size and the prior the network may be given, and
returns an :class:`~dapm_lightning.models.dapm.InferenceOutput`; the post-processing after it is the same for
all (:func:`~dapm_lightning.inference.postprocess.batch_predictions`). :class:`TorchRuntime` runs a PyTorch
module (eager or ``torch.compile``, channels-last, autocast); :class:`OnnxRuntime` an exported ONNX model in
onnxruntime. A new runtime (TensorRT, OpenVINO, ...) is one more class with ``takes_prior`` and ``__call__``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Protocol

import torch
from torch import Tensor, nn

from dapm_lightning.geometry.image import unit_image
from dapm_lightning.inference.onnx import METADATA_NET, PRIOR_INPUTS, missing_weights_message, onnx_feed
from dapm_lightning.models.config import DAPMConfig
from dapm_lightning.models.dapm import InferenceOutput
from dapm_lightning.models.prior import PosePrior
from dapm_lightning.options import PRECISIONS as PRECISIONS
from dapm_lightning.options import Precision as Precision


class Runtime(Protocol):
    """Runs the network on ``[B, 3, h, w]`` images (uint8, or float in [0, 1]) at the network size."""

    takes_prior: bool
    """Whether a pose prior can be given to the network (else it is applied afterwards, ``scale`` mode)."""

    def __call__(self, images: Tensor, prior: PosePrior | None = None) -> InferenceOutput:
        """The outputs at the network size (``pose_spread`` included, for fusing a prior afterwards)."""
        ...


DEVICE_ALIASES = {"gpu": "cuda", "cuda0": "cuda:0", "nvidia": "cuda", "cpu0": "cpu", "mac": "mps"}
"""Device names people type, and what torch calls them (named in the message, not guessed)."""


def resolve_device(device: str) -> str:
    """``"auto"``: ``"cuda"`` when a GPU is there, else ``"cpu"``; ``"cuda"`` without one is refused.

    A name torch does not know (``gpu``) is refused in one line with the name it has (``cuda``).
    """
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        torch.device(device)
    except (RuntimeError, TypeError):
        known = DEVICE_ALIASES.get(device.lower())
        hint = f"did you mean {known}? " if known else ""
        raise ValueError(f"device {device!r}: unknown ({hint}use cpu, cuda, cuda:N or auto)") from None
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device {device!r}: no CUDA GPU is available here (use the cpu, or auto)")
    return device


def check_device(device: str, precision: str = "32") -> str:
    """:func:`resolve_device`, and a precision the device cannot run refused in one line (float16 on the CPU)."""
    resolved = resolve_device(device)
    if torch.device(resolved).type == "cpu" and str(precision) == "16":
        raise ValueError("precision 16 (float16) does not run on the CPU: use 32 or bf16 there, or a GPU (cuda)")
    return resolved


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
        self.device = torch.device(check_device(device, precision))
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
    """A model exported by ``dapm-lightning export`` (float32, fp16 or int8), in onnxruntime on the CPU.

    It runs at the network size it is given, as PyTorch does, and takes the prior into the graph (fused before the
    IGD feature as in PyTorch). Its metadata gives the network's settings (:attr:`config`) and training size, so the
    file is all prediction needs. A file that is not such an export is refused with one line saying what it lacks.
    """

    def __init__(self, path: str | Path) -> None:
        import onnxruntime

        self.path = Path(path)
        if not self.path.is_file():
            raise FileNotFoundError(f"{self.path}: no such ONNX file")
        if (missing := missing_weights_message(self.path)) is not None:  # before onnxruntime logs its own error
            raise ValueError(missing)
        try:
            self.session = onnxruntime.InferenceSession(str(self.path), providers=["CPUExecutionProvider"])
        except Exception as error:  # onnxruntime raises its own exception types
            raise ValueError(missing_weights_message(self.path) or (
                f"{self.path}: onnxruntime cannot load it ({str(error).splitlines()[0]}).\nFix: export the "
                f"checkpoint again (dapm-lightning export CKPT --out {self.path}); a large model's weights file "
                "keeps the name it was exported with (NAME.onnx.data of the exported NAME.onnx): keep it beside "
                "the .onnx under that name")) from error
        metadata = self.session.get_modelmeta().custom_metadata_map
        if METADATA_NET not in metadata:
            raise ValueError(f"{self.path}: not a dapm-lightning export: its metadata lacks {METADATA_NET} (the "
                             "network's settings: depth limit, depth kind, pose ranges) and its training size.\n"
                             "Fix: export the checkpoint with `dapm-lightning export --ckpt_path CKPT`")
        try:
            self.config = DAPMConfig.from_dict(json.loads(metadata[METADATA_NET]))
        except ValueError as error:  # settings of another version (an unknown one, a value refused), or not JSON
            raise ValueError(f"{self.path}: its network settings ({METADATA_NET}, exported by dapm-lightning "
                             f"{metadata.get('dapm.version', '?')}) do not load here: {str(error).splitlines()[0]}"
                             "\nFix: predict with the dapm-lightning version that exported it, or export the "
                             "checkpoint again with this one") from error
        trained = json.loads(metadata.get("dapm.train_image_size", "null"))
        self.train_image_size: tuple[int, int] | None = (int(trained[0]), int(trained[1])) if trained else None
        self.input_names = [value.name for value in self.session.get_inputs()]
        self.names = [value.name for value in self.session.get_outputs()]
        self.takes_prior = PRIOR_INPUTS[0] in self.input_names
        # [B, 3, H, W]: names where dynamic, numbers where exported at a fixed size (--dynamic false: [1, 3, H, W])
        dims = self.session.get_inputs()[0].shape
        self.fixed_batch: int | None = dims[0] if isinstance(dims[0], int) else None
        self.fixed_size: tuple[int, int] | None = (dims[2], dims[3]) if all(isinstance(d, int) for d in dims[2:]) \
            else None

    def __call__(self, images: Tensor, prior: PosePrior | None = None) -> InferenceOutput:
        size = (int(images.shape[-2]), int(images.shape[-1]))
        if self.fixed_size is not None and size != self.fixed_size:
            height, width = self.fixed_size
            raise ValueError(f"{self.path}: exported at the fixed size {height}x{width} (--dynamic false); this "
                             f"image's network size is {size[0]}x{size[1]} (height x width, the image's own aspect)."
                             "\nFix: export it again with dynamic sizes (leave --dynamic false out), or predict only "
                             f"images of that aspect, at that size (--image_width {width})")
        if self.fixed_batch is not None and images.shape[0] != self.fixed_batch:  # one image at a time
            parts = [self(images[i:i + 1], None if prior is None else _prior_row(prior, i))
                     for i in range(images.shape[0])]
            return InferenceOutput(**{name: torch.cat([getattr(part, name) for part in parts])
                                      for name in parts[0].named()})
        feed = onnx_feed(unit_image(images.cpu()).float().numpy(), self.input_names, prior)
        outputs = {name: torch.from_numpy(value) for name, value in zip(self.names, self.session.run(None, feed))}
        if prior is None:  # given no prior, the pose used is the network's own (as PyTorch reports it)
            outputs.pop("pose_network", None)
        return InferenceOutput(**outputs)


def _prior_row(prior: PosePrior, index: int) -> PosePrior:
    """Image ``index``'s prior (a row shared by the batch stays as it is)."""
    def row(tensor: Tensor | None) -> Tensor | None:
        return tensor[index:index + 1] if tensor is not None and tensor.shape[0] > 1 else tensor

    return PosePrior(row(prior.value), row(prior.sigma), row(prior.mask))  # type: ignore[arg-type]
