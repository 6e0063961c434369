"""Any timm backbone as a multi-scale feature extractor (``features_only``)."""

from __future__ import annotations

import difflib
import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import timm
import torch
from timm.models import clean_state_dict
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
    """A local weights file timm can read, not a whole network's checkpoint, with ``model``'s shapes.

    ``model`` is ``backbone`` as timm builds it; where the file's tensor names do not all match its, a warning.

    timm alone fails on an unreadable file with a bare pickle error, and from a checkpoint of the whole network
    (a dapm-lightning one among them) loads nothing and trains from random weights with a note. A partial match
    is only warned about: timm maps some published layouts on load (each architecture's own filter).

    Raises:
        ValueError: the file cannot be read as weights, is a Lightning checkpoint, or has tensors of ``model``'s names
            in other shapes (timm would stop on them).
    """
    fix = (f"Fix: --{setting} FILE with the {backbone} backbone's timm state dict (a .safetensors or .pth file), "
           "or --model.net.pretrained false to start from random weights.")
    try:
        if path.suffix == ".safetensors":
            from safetensors.torch import load_file

            state: Any = load_file(str(path))
        else:  # as timm reads it
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # a text file, a cut-short copy, pickled classes: each fails its own way
        with path.open("rb") as stream:
            head = stream.read(4)
        pytorch = head == b"PK\x03\x04" or head[:1] == b"\x80"  # torch.save's zip, or its older pickle
        reason = ("a safetensors file cut short or damaged" if path.suffix == ".safetensors" else
                  "not a PyTorch or safetensors file" if not pytorch else
                  "it holds Python objects besides tensors, which are not loaded (weights_only)"
                  if "Weights only load failed" in str(error) else "a PyTorch file cut short or damaged")
        raise ValueError(f"{setting}: {path}: cannot be read as weights: {reason}.\n{fix}") from None
    if isinstance(state, dict) and ("pytorch-lightning_version" in state or any(
            str(k).startswith("net.") for k in (state.get("state_dict") or {}))):
        raise ValueError(f"{setting}: {path}: a Lightning checkpoint of a whole network, not backbone weights."
                         "\nFix: for a dapm-lightning checkpoint, --model.init_weights FILE starts from its weights "
                         "and --ckpt_path FILE resumes its training; or name backbone weights here.")
    if isinstance(state, dict):  # the wrappers timm unwraps, in its order, and the prefixes it removes
        wrappers = ("state_dict_ema", "model_ema", "state_dict", "model")
        key = next((k for k in wrappers if isinstance(state.get(k), dict)), None)
        state = clean_state_dict(state[key] if key else state)
    if not isinstance(state, dict):
        raise ValueError(f"{setting}: {path}: holds a {type(state).__name__}, not a state dict.\n{fix}")
    counted = ("num_batches_tracked",)  # BatchNorm's step counters: absent from some published files
    classifier = getattr(model, "pretrained_cfg", {}).get("classifier") or ()
    heads = tuple(f"{h}." for h in ((classifier,) if isinstance(classifier, str) else classifier))
    body = {k: v for k, v in model.state_dict().items() if not k.endswith(counted) and not k.startswith(heads)}
    tensors = {k: v for k, v in state.items() if isinstance(v, Tensor) and not str(k).endswith(counted)}
    reshaped = [k for k, v in body.items() if k in tensors and tensors[k].shape != v.shape]
    if reshaped:  # timm's load would stop on it, with a list of every size mismatch
        name = reshaped[0]
        raise ValueError(f"{setting}: {path}: not {backbone} weights: {name} is {list(tensors[name].shape)} in the "
                         f"file, {list(body[name].shape)} in {backbone} ({len(reshaped)} tensors of other shapes: "
                         f"another backbone's weights?).\n{fix}")
    missing = [k for k in body if k not in tensors]
    extra = [k for k in tensors if k not in body and not k.startswith(heads)]
    if missing or extra:
        what = (f"{len(body) - len(missing)} of the backbone's {len(body)} tensors are in it (not {missing[0]!r})"
                if missing else f"it holds {len(extra)} tensors the backbone has none of (such as {extra[0]!r})")
        warnings.warn(f"{setting}: {path}: {what}; timm maps some published layouts as it loads, else "
                      f"{'the rest start from random weights' if missing else 'those are left out'}. If the file "
                      f"is another backbone's, name {backbone}'s.", UserWarning, stacklevel=2)


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
            with torch.device("meta"):  # the shapes only: no memory, no initialisation
                reference = timm.create_model(backbone, pretrained=False)
            check_backbone_weights(Path(weights_path), reference, backbone)
        self.body = timm.create_model(backbone, features_only=True, pretrained=pretrained or overlay is not None,
                                      out_indices=tuple(out_indices), pretrained_cfg_overlay=overlay)
        feature_info: Any = self.body.feature_info
        self.channels: list[int] = list(feature_info.channels())
        self.strides: list[int] = list(feature_info.reduction())

    def forward(self, image: Tensor) -> list[Tensor]:
        """``image [B, 3, H, W]`` (per ``input_normalization``) -> feature maps ``[B, C_i, H / s_i, W / s_i]``."""
        return list(self.body(image))
