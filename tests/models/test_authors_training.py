"""The authors' training choices as switches (configs/paper): input normalisation, dropouts, initialisation."""

import math

import pytest
import torch
import yaml
from torch import nn

from dapm_lightning.data.transforms import AUTHORS_AUGMENTATION, Augmentation
from dapm_lightning.models import PAPER_NETWORK, DAPMConfig, DAPMNet
from dapm_lightning.models.blocks import ResidualConvBlock, ResidualLinear, ResidualMLPBlock
from dapm_lightning.models.config import AUTHORS_TRAINING
from dapm_lightning.models.decoders import PoseDecoder
from tests.conftest import CONFIGS, QUICKSTART

DROPOUT_AND_INIT = {k: v for k, v in AUTHORS_TRAINING.items() if k != "input_normalization"}


def build(**changes):
    torch.manual_seed(0)
    return DAPMNet(DAPMConfig(backbone="resnet18", **{**PAPER_NETWORK, **changes}))


def test_the_authors_values():
    assert dict(AUTHORS_TRAINING) == {"input_normalization": "none", "block_dropout": 0.1, "pose_dropout": 0.2,
                                      "linear_dropout": 0.3, "weight_init": "authors"}
    assert AUTHORS_AUGMENTATION == Augmentation(brightness=0.5, contrast=0.5, saturation=0.5, color_jitter_p=1.0,
                                                noise_std=(0.05, 0.05), noise_p=0.5, flip_p=0.5)


@pytest.mark.parametrize("config", sorted(p.name for p in (CONFIGS / "paper").glob("*.yaml")))
def test_paper_configs_follow_the_authors_code(config):
    values = yaml.safe_load((CONFIGS / "paper" / config).read_text())
    net = values["model"]["net"]
    assert {k: net[k] for k in AUTHORS_TRAINING} == dict(AUTHORS_TRAINING)
    assert net["igd"]["model"] == "paper"
    assert values["model"]["authors_pose_metrics"] is True
    assert Augmentation(**values["data"]["init_args"]["augmentation"]) == AUTHORS_AUGMENTATION


def test_efficient_variant_and_quickstart_keep_this_projects_choices():
    defaults = DAPMConfig()
    efficient = yaml.safe_load((CONFIGS / "variants" / "efficient.yaml").read_text())["model"]["net"]
    assert {k: efficient[k] for k in AUTHORS_TRAINING} == {k: getattr(defaults, k) for k in AUTHORS_TRAINING}
    assert efficient["igd"] == {"model": "pinhole"}
    quickstart = yaml.safe_load(QUICKSTART.read_text())["model"]["net"]
    built = DAPMConfig(**quickstart)  # the quickstart leaves the rest to the defaults
    assert built.igd.model == "pinhole" and not set(AUTHORS_TRAINING) & set(quickstart)
    assert defaults.input_normalization == "imagenet" and defaults.weight_init == "pytorch"
    assert (defaults.block_dropout, defaults.pose_dropout, defaults.linear_dropout) == (0.0, 0.0, 0.0)


@pytest.mark.parametrize("mode", ["imagenet", "none"])
def test_input_normalization_is_what_the_encoder_sees(mode):
    net = build(input_normalization=mode).eval()
    seen = []
    net.encoder.register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    image = torch.rand(1, 3, 32, 32)
    net(image)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    torch.testing.assert_close(seen[0], (image - mean) / std if mode == "imagenet" else image)


def test_dropout_and_init_keep_the_weights_layout_and_the_eval_output():
    """Existing checkpoints load into either network, and dropout acts only in training."""
    default, authors = build(), build(**DROPOUT_AND_INIT)
    def layout(net):
        return {k: v.shape for k, v in net.state_dict().items()}

    assert layout(default) == layout(authors)
    authors.load_state_dict(default.state_dict())
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        a, b = default.eval()(image), authors.eval()(image)
    torch.testing.assert_close(a.depth.depth_norm, b.depth.depth_norm)
    torch.testing.assert_close(a.pose.pose_norm, b.pose.pose_norm)


def test_dropouts_sit_where_the_authors_have_them():
    authors, default = build(**DROPOUT_AND_INIT), build()
    conv_blocks = [m for m in authors.modules() if isinstance(m, ResidualConvBlock)]
    assert len(conv_blocks) == 6  # FPN: 3 fusions + the head's block; conv pose bins: 2 stages
    assert all(isinstance(b.body[-1], nn.Dropout2d) and b.body[-1].p == 0.1 for b in conv_blocks)
    linear_blocks = [m for m in authors.modules() if isinstance(m, (ResidualLinear, ResidualMLPBlock))]
    assert len(linear_blocks) == 2 + 2 + 1 + 1  # pose decoder MLP, per-stage heads, the 64-stage fusion, the head
    assert all(isinstance(b.body[2][1], nn.Dropout) and b.body[2][1].p == 0.3 for b in linear_blocks)
    assert authors.pose_decoder.projection_dropout.p == 0.2
    # the default network: only the FPN laterals' Dropout2d (0.1)
    assert [m.p for m in default.modules() if isinstance(m, nn.Dropout2d)] == [0.1, 0.1, 0.1]
    assert all(m.p == 0 for m in default.modules() if isinstance(m, nn.Dropout))


def test_dropout_by_value_in_training():
    x = torch.randn(2, 4, 5, 5)
    block = ResidualConvBlock(4, dropout=1.0).train()  # the body dropped entirely: relu(x + 0)
    torch.testing.assert_close(block(x), x.relu())
    linear = ResidualLinear(6, 6, activate=False, dropout=1.0).train()
    v = torch.randn(3, 6)
    torch.testing.assert_close(linear(v), v + linear.body[4](linear.body[3](torch.zeros(3, 6))))
    decoder = PoseDecoder([8, 16], projection=4, hidden=8, depth_grid=2, projection_dropout=1.0).train()
    seen = []
    for projection in [*decoder.projections, decoder.depth_projection]:
        projection.register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    decoder([torch.rand(2, 8, 4, 4), torch.rand(2, 16, 2, 2)], torch.rand(2, 1, 8, 8))
    assert len(seen) == 3 and all(torch.equal(s, torch.zeros_like(s)) for s in seen)


def test_authors_initialisation_by_value():
    net, default = build(weight_init="authors"), build()
    pose_linears = [m for part in (net.pose_decoder, net.pose_pqb) for m in part.modules() if isinstance(m, nn.Linear)]
    assert pose_linears and all(torch.equal(m.bias, torch.full_like(m.bias, 0.01)) for m in pose_linears)
    assert not all(torch.equal(m.bias, torch.full_like(m.bias, 0.01))
                   for m in default.pose_decoder.modules() if isinstance(m, nn.Linear))
    for m in pose_linears:  # Xavier-normal: std sqrt(2 / (fan_in + fan_out))
        if m.weight.numel() >= 20000:
            expected = math.sqrt(2.0 / (m.in_features + m.out_features))
            assert m.weight.std().item() == pytest.approx(expected, rel=0.05)
            assert (m.weight.abs() > math.sqrt(3) * expected).float().mean() > 0.05  # normal, not uniform
    depth_convs = [m for m in net.depth_decoder.modules() if isinstance(m, nn.Conv2d)]
    assert all(torch.equal(m.bias, torch.zeros_like(m.bias)) for m in depth_convs if m.bias is not None)
    pose_convs = [m for m in net.pose_pqb.modules() if isinstance(m, nn.Conv2d)]
    for m in depth_convs + pose_convs:  # Kaiming-normal, fan_out, ReLU gain: std sqrt(2 / (out x k x k))
        if m.weight.numel() >= 20000:
            expected = math.sqrt(2.0 / (m.out_channels * m.kernel_size[0] * m.kernel_size[1]))
            assert m.weight.std().item() == pytest.approx(expected, rel=0.05)
            assert (m.weight.abs() > math.sqrt(3) * expected).float().mean() > 0.05  # normal, not uniform
    # the depth bins heads, the IGD feature and the encoder keep PyTorch's (the same draws as the default network)
    for part in ("depth_pqb", "igd_feature", "to_head", "encoder"):
        for (name, a), b in zip(getattr(net, part).state_dict().items(), getattr(default, part).state_dict().values()):
            assert torch.equal(a, b), f"{part}.{name}"


@pytest.mark.parametrize(("setting", "value", "message"), [
    ("input_normalization", "imagenet1k", "input_normalization must be 'imagenet' or 'none'"),
    ("weight_init", "xavier", "weight_init must be 'pytorch' or 'authors'"),
    ("block_dropout", 1.0, r"block_dropout must be in \[0, 1\)"),
    ("pose_dropout", -0.1, r"pose_dropout must be in \[0, 1\)")])
def test_bad_settings_are_refused(setting, value, message):
    with pytest.raises(ValueError, match=message):
        DAPMConfig(backbone="resnet18", **{setting: value})
