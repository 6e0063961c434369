"""Any timm backbone as a multi-scale feature extractor (``features_only``)."""

from __future__ import annotations

import difflib
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import timm
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
        self.body = timm.create_model(backbone, features_only=True, pretrained=pretrained or overlay is not None,
                                      out_indices=tuple(out_indices), pretrained_cfg_overlay=overlay)
        feature_info: Any = self.body.feature_info
        self.channels: list[int] = list(feature_info.channels())
        self.strides: list[int] = list(feature_info.reduction())

    def forward(self, image: Tensor) -> list[Tensor]:
        """``image [B, 3, H, W]`` (per ``input_normalization``) -> feature maps ``[B, C_i, H / s_i, W / s_i]``."""
        return list(self.body(image))
