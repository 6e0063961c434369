"""Weight initialisation: PyTorch's defaults, or the authors' (github.com/ThisIsLT/DAPM, ``model/dapm.py``)."""

from __future__ import annotations

from typing import Literal

from torch import nn

WeightInit = Literal["pytorch", "authors"]

POSE_LINEAR_BIAS = 0.01
"""The authors' bias of every linear layer of the pose decoder (and its bins)."""


def init_depth_decoder_like_authors(decoder: nn.Module) -> None:
    """The authors' FPN: every conv (squeeze-excitation included) Kaiming-normal (``fan_out``, ReLU) with bias 0."""
    for module in decoder.modules():
        if isinstance(module, nn.Conv2d):
            nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
            if module.bias is not None:
                nn.init.zeros_(module.bias)


def init_pose_like_authors(pose_modules: nn.Module) -> None:
    """The authors' pose decoder: linears Xavier-normal with bias 0.01, convs Kaiming-normal (``fan_out``, ReLU)."""
    for module in pose_modules.modules():
        if isinstance(module, nn.Linear):
            nn.init.xavier_normal_(module.weight)
            nn.init.constant_(module.bias, POSE_LINEAR_BIAS)
        elif isinstance(module, nn.Conv2d):
            nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
