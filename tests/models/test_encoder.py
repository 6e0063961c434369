import warnings

import pytest
import timm
import torch
from safetensors.torch import save_file

from dapm_lightning.models import Encoder


def test_local_weights_file_is_loaded(tmp_path):
    source = timm.create_model("resnet18", pretrained=False)
    with torch.no_grad():
        source.conv1.weight.fill_(0.123)
    path = tmp_path / "resnet18.safetensors"
    save_file(source.state_dict(), str(path))
    encoder = Encoder("resnet18", weights_path=str(path))
    assert torch.all(encoder.body.conv1.weight == 0.123)
    assert not torch.all(Encoder("resnet18").body.conv1.weight == 0.123)


def test_missing_weights_file_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.pth"):
        Encoder("resnet18", weights_path=str(tmp_path / "nope.pth"))


def test_a_weights_file_timm_cannot_use_is_refused_naming_it(tmp_path):
    """timm alone fails on a bare pickle error, or loads nothing from a whole network's checkpoint and trains from
    random weights: each such file is refused naming the setting, the file and what it is."""
    text = tmp_path / "notes.pth"
    text.write_text("not weights")
    whole = tmp_path / "run.ckpt"
    torch.save({"state_dict": {"net.encoder.body.conv1.weight": torch.zeros(1)}, "pytorch-lightning_version": "2"},
               whole)
    cut = tmp_path / "cut.pth"
    torch.save(timm.create_model("resnet18", pretrained=False).state_dict(), cut)
    cut.write_bytes(cut.read_bytes()[:100_000])
    cut_safetensors = tmp_path / "cut.safetensors"
    save_file(timm.create_model("resnet18", pretrained=False).state_dict(), str(cut_safetensors))
    cut_safetensors.write_bytes(cut_safetensors.read_bytes()[:100_000])
    objects = tmp_path / "pickled.pth"
    torch.save({"model": torch.nn.Linear(2, 2)}, objects)
    for path, said in ((text, "not a PyTorch or safetensors file"), (cut, "a PyTorch file cut short or damaged"),
                       (cut_safetensors, "a safetensors file cut short or damaged"),
                       (objects, "holds Python objects besides tensors"),
                       (whole, "a Lightning checkpoint of a whole network")):
        with pytest.raises(ValueError) as raised:
            Encoder("resnet18", weights_path=str(path))
        assert str(raised.value).startswith(f"model.net.weights_path: {path}: ") and said in str(raised.value)
        assert "Fix: " in str(raised.value)


def test_weights_in_the_layouts_timm_reads_load_and_another_backbones_are_warned_about(tmp_path):
    """Wrapped (``state_dict``), prefixed by DDP or torch.compile, without the classifier or BatchNorm's counters:
    loaded with no warning; a deeper ResNet's file loads its matching tensors, with a warning naming the count."""
    source = timm.create_model("resnet18", pretrained=False)
    with torch.no_grad():
        source.conv1.weight.fill_(0.25)
    state = {k: v for k, v in source.state_dict().items() if not k.startswith("fc.")
             and not k.endswith("num_batches_tracked")}
    wrapped = tmp_path / "wrapped.pth"
    torch.save({"state_dict": {f"_orig_mod.module.{k}": v for k, v in state.items()}, "epoch": 3}, wrapped)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)
        encoder = Encoder("resnet18", weights_path=str(wrapped))
    assert torch.all(encoder.body.conv1.weight == 0.25)
    deeper = tmp_path / "resnet34.safetensors"
    save_file(timm.create_model("resnet34", pretrained=False).state_dict(), str(deeper))
    with pytest.warns(UserWarning, match=r"resnet34.safetensors: it holds 80 tensors the backbone has none of "
                                         r"\(such as 'layer1.2.bn1.bias'\)"):
        Encoder("resnet18", weights_path=str(deeper))
    bottleneck = tmp_path / "resnet50.safetensors"
    save_file(timm.create_model("resnet50", pretrained=False).state_dict(), str(bottleneck))
    with pytest.raises(ValueError, match=r"resnet50.safetensors: not resnet18 weights: layer1.0.conv1.weight is "
                                         r"\[64, 64, 1, 1\] in the file, \[64, 64, 3, 3\] in resnet18"):
        Encoder("resnet18", weights_path=str(bottleneck))


def test_stages_and_strides():
    encoder = Encoder("resnet18")
    features = encoder(torch.rand(1, 3, 64, 96))
    assert encoder.strides == [4, 8, 16, 32]
    assert [f.shape[-2:] for f in features] == [(16, 24), (8, 12), (4, 6), (2, 3)]


def test_public_names_of_the_design_contract():
    from dapm_lightning.data import UAPDDataset, parse_uapd_filename  # noqa: F401
    from dapm_lightning.geometry import (  # noqa: F401
        POSE_RANGES,
        decode_log_depth,
        denormalize_pose,
        encode_log_depth,
        ideal_ground_depth,
        normalize_pose,
    )
    from dapm_lightning.metrics import DepthMetrics, PoseMetrics  # noqa: F401
    assert POSE_RANGES["pitch"] == (-100.0, 10.0)


def test_unknown_backbone_names_the_setting_and_the_closest_models():
    from dapm_lightning.models.config import DAPMConfig

    expected = r"model\.net\.backbone: unknown timm model 'resnet5O' \(closest: resnet50\b.*\); list them with"
    with pytest.raises(ValueError, match=expected):
        DAPMConfig(backbone="resnet5O")  # refused when the settings are built, before any network or data
    with pytest.raises(ValueError, match="unknown timm model 'resnet5O'"):
        Encoder("resnet5O")
    DAPMConfig(backbone="resnet18.a1_in1k")  # a pretrained tag is a timm model
    DAPMConfig(backbone="hf-hub:timm/resnet18.a1_in1k")  # hub sources are left to timm.create_model
