"""Any timm backbone as a multi-scale feature extractor (``features_only``)."""

from __future__ import annotations

import difflib
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import timm
import torch
from torch import Tensor, nn


def check_backbone(name: str, setting: str = "model.net.backbone") -> None:
    """Raise a ValueError naming ``setting``, the closest timm models and how to list them, unless timm has ``name``.

    Names with a pretrained tag (``resnet50.a1_in1k``) are timm models; hub and local sources
    (``hf-hub:...``, ``local-dir:...``) are left to ``timm.create_model``.
    """
    if ":" in name or timm.is_model(name):
        return
    closest = difflib.get_close_matches(name, timm.list_models(), n=4, cutoff=0.5)
    hint = f" (closest: {', '.join(closest)})" if closest else ""
    letters = re.match(r"[A-Za-z]+", name)
    pattern = f"{letters.group(0).lower() if letters else ''}*"
    raise ValueError(f"{setting}: unknown timm model {name!r}{hint}; list them with "
                     f"`python -c \"import timm; print(timm.list_models('{pattern}'))\"`")


def check_backbone_weights(path: Path, model: nn.Module, backbone: str, setting: str = "model.net.weights_path"
                           ) -> None:
    """A local weights file holds the state dict of ``model`` (``backbone``, built by timm).

    Every tensor of its body is there in its shape, and none that ``model`` lacks (a deeper model's layers); the
    classifier may be left out.

    timm alone would load a damaged or foreign file with a bare pickle error, or load nothing from another model's
    weights (a whole dapm-lightning checkpoint among them) and train from random weights with a note.

    Raises:
        ValueError: the file cannot be read as weights, is a whole network's checkpoint, or misses tensors.
    """
    fix = (f"Fix: --{setting} FILE with the {backbone} backbone's timm (or torchvision) state dict, a .safetensors "
           "or .pth file, or --model.net.pretrained false to start from random weights.")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state: Any = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # a text file, a cut-short copy, pickled classes: each fails its own way
        with path.open("rb") as stream:
            head = stream.read(4)
        pytorch = head == b"PK\x03\x04" or head[:1] == b"\x80"  # torch.save's zip, or its older pickle
        reason = ("not a PyTorch or safetensors file" if not pytorch else
                  "it holds Python objects besides tensors, which are not loaded (weights_only)"
                  if "Weights only load failed" in str(error) else "a PyTorch file cut short or damaged")
        raise ValueError(f"{setting}: {path}: cannot be read as weights: {reason}.\n{fix}") from None
    if isinstance(state, dict) and ("pytorch-lightning_version" in state or any(
            str(k).startswith("net.") for k in (state.get("state_dict") or {}))):
        raise ValueError(f"{setting}: {path}: a dapm-lightning checkpoint (the whole network), not backbone weights."
                         "\nFix: --model.init_weights FILE to start from its weights, --ckpt_path FILE to resume its "
                         "training, or name backbone weights here.")
    for key in ("state_dict", "model", "state_dict_ema"):  # the wrappers timm unwraps
        if isinstance(state, dict) and isinstance(state.get(key), dict):
            state = state[key]
            break
    if not isinstance(state, dict):
        raise ValueError(f"{setting}: {path}: holds a {type(state).__name__}, not a state dict.\n{fix}")
    def bare(key: Any) -> str:  # DDP's and timm's feature wrappers' prefixes
        return str(key).removeprefix("module.").removeprefix("model.")

    counted = ("num_batches_tracked",)  # BatchNorm's step counters: absent from torchvision's files
    tensors = {bare(k): v for k, v in state.items() if isinstance(v, Tensor) and not str(k).endswith(counted)}
    own = {bare(k): v for k, v in model.state_dict().items() if not k.endswith(counted)}
    classifier = getattr(model, "pretrained_cfg", {}).get("classifier") or ()
    heads = (classifier,) if isinstance(classifier, str) else tuple(classifier)
    body = {k: v for k, v in own.items() if not k.startswith(tuple(f"{h}." for h in heads))}
    wrong = [k for k, v in body.items() if k not in tensors or tuple(tensors[k].shape) != tuple(v.shape)]
    foreign = sorted(set(tensors) - set(own))
    if wrong or foreign:
        what = (f"{len(body) - len(wrong)} of the backbone's {len(body)} tensors are there in their shapes (not "
                f"{wrong[0]!r})" if wrong else
                f"it holds {len(foreign)} tensors the backbone has no place for, such as {foreign[0]!r}")
        raise ValueError(f"{setting}: {path}: not {backbone} weights: {what}.\n{fix}")


class Encoder(nn.Module):
    """A timm backbone returning feature maps of several stages, shallow to deep.

    Args:
        backbone: timm model name (``"resnet50"``, the paper's; ``"resnet18"`` for CPU runs).
        pretrained: load ImageNet weights. From the hub, or from ``weights_path`` when given
            (a local ``.safetensors``/``.pth`` file, loaded by timm with ``weights_only`` semantics).
        weights_path: local weights file for machines without internet.
        out_indices: timm feature indices; ``(1, 2, 3, 4)`` are ResNet's four residual stages
            (strides 4, 8, 16, 32).
    """

    def __init__(self, backbone: str = "resnet50", *, pretrained: bool = False, weights_path: str | None = None,
                 out_indices: Sequence[int] = (1, 2, 3, 4)) -> None:
        super().__init__()
        check_backbone(backbone)
        overlay = None
        if weights_path is not None:
            if not Path(weights_path).is_file():
                raise FileNotFoundError(f"{weights_path}: backbone weights file not found")
            overlay = {"file": str(weights_path)}
        if weights_path is not None:  # checked against the backbone's own tensors before timm reads it
            check_backbone_weights(Path(weights_path), timm.create_model(backbone, pretrained=False), backbone)
        self.body = timm.create_model(backbone, features_only=True, pretrained=pretrained or overlay is not None,
                                      out_indices=tuple(out_indices), pretrained_cfg_overlay=overlay)
        feature_info: Any = self.body.feature_info
        self.channels: list[int] = list(feature_info.channels())
        self.strides: list[int] = list(feature_info.reduction())

    def forward(self, image: Tensor) -> list[Tensor]:
        """``image [B, 3, H, W]`` (per ``input_normalization``) -> feature maps ``[B, C_i, H / s_i, W / s_i]``."""
        return list(self.body(image))
