"""The paper's network (configs/paper) and the efficient variant (configs/variants) as switches."""

import pytest
import torch
import yaml
from torch.utils.flop_counter import FlopCounterMode

from dapm_lightning.models import EFFICIENT_NETWORK, PAPER_NETWORK, DAPMConfig, DAPMNet
from dapm_lightning.models.blocks import ResidualConvBlock, SqueezeExcite
from dapm_lightning.models.config import AUTHORS_TRAINING
from dapm_lightning.models.pqb import EncoderPosePQB
from dapm_lightning.training.loss import DAPMLoss, LossConfig
from tests.conftest import CONFIGS, QUICKSTART
from tests.models.test_dapm import targets_for

PAPER_PARAMS_M = 42.82  # paper Table 7; the authors' released model has exactly 42,820,323


def count(module: torch.nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def test_paper_network_has_the_papers_size_at_resnet50():
    net = DAPMNet(DAPMConfig(backbone="resnet50", **PAPER_NETWORK))
    assert abs(count(net) / 1e6 - PAPER_PARAMS_M) / PAPER_PARAMS_M < 0.01
    efficient = DAPMNet(DAPMConfig(backbone="resnet50", **EFFICIENT_NETWORK))
    assert count(efficient) < 0.92 * count(net)  # the same pose branch; lighter depth heads


def test_efficient_variant_needs_a_fraction_of_the_papers_compute():
    def gmac(net: DAPMNet) -> float:
        with torch.no_grad(), FlopCounterMode(display=False) as counter:
            net.eval()(torch.rand(1, 3, 128, 128))
        return counter.get_total_flops() / 2e9

    paper, efficient = (gmac(DAPMNet(DAPMConfig(backbone="resnet50", **c))) for c in (PAPER_NETWORK, EFFICIENT_NETWORK))
    assert efficient < 0.15 * paper  # 26.9 vs 226.3 GMAC at 512x512 (make bench)


def test_encoder_pose_bins_have_the_authors_parameter_count():
    # per stage: residual conv block 2048 -> 256 (two 3x3 convs, BN, 1x1 shortcut) + residual linear block to 4n
    conv = 2048 * 256 * 9 + 256 * 256 * 9 + 2 * 2 * 256 + 2048 * 256 + 256

    def linear(i, o):  # Linear, LN, Linear, LN, shortcut Linear when the widths differ
        return i * o + o + 2 * o + o * o + o + 2 * o + (i * o + o if i != o else 0)

    expected = 2 * conv + linear(256, 64) + linear(256, 256) + linear(64 + 256, 256) + linear(4 + 64 + 256, 4)
    assert count(EncoderPosePQB(2048, (16, 64), 256)) == expected
    assert expected == 5_871_296 + 5_966_592 + 231_168 + 2_636  # the authors' quant_net_16/64, residual_net_64/_


def test_paper_configs_and_variant_overlay_say_what_the_code_builds():
    for name in ("uapd_dapm", "uapd_dapm_d", "uapd_dapm_p", "potsdam_dapm_d"):
        config = yaml.safe_load((CONFIGS / "paper" / f"{name}.yaml").read_text())
        net = config["model"]["net"]
        assert {k: net[k] for k in PAPER_NETWORK} == dict(PAPER_NETWORK), name
        assert net["backbone"] == "resnet50.tv_in1k" and net["pretrained"] is True, name
        assert config["model"]["loss"]["depth_space"] == "log_norm", name
        assert config["model"]["loss"]["use_gradient_loss"] is False, name  # code-only: opt-in
    overlay = yaml.safe_load((CONFIGS / "variants" / "efficient.yaml").read_text())["model"]["net"]
    # the network's shape and this project's training (the defaults), undoing a paper config's
    assert overlay == {**EFFICIENT_NETWORK, **{k: getattr(DAPMConfig, k) for k in AUTHORS_TRAINING},
                       "igd": {"model": "pinhole"}}
    assert {k: getattr(DAPMConfig(), k) for k in EFFICIENT_NETWORK} == dict(EFFICIENT_NETWORK)  # the defaults
    quick = yaml.safe_load(QUICKSTART.read_text())["model"]["net"]
    # the rest: the efficient defaults; the quickstart's depth is relative to the IGD (issue 31), the paper's absolute
    assert set(quick) == {"backbone", "pretrained", "decoder_channels", "depth_parametrization", "depth_readout"}
    assert quick["depth_parametrization"] == "igd_ratio" and DAPMConfig().depth_parametrization == "absolute"
    assert quick["depth_readout"] == "bins_mode" and DAPMConfig().depth_readout == "head"


@pytest.mark.parametrize("branches", [{}, {"use_pose": False, "use_igd_feature": False},
                                      {"use_depth": False, "use_igd_feature": False}])
def test_paper_network_every_parameter_gets_a_gradient(branches):
    settings = {**PAPER_NETWORK, "decoder_channels": 32, "head_channels": 16, "igd_channels": 8,
                "pose_hidden": 32, "pose_projection": 32, **branches}
    net = DAPMNet(DAPMConfig(backbone="resnet18", **settings))
    loss = DAPMLoss(LossConfig(depth_space="log_norm", use_gradient_loss=True,
                               use_igd_loss=net.config.use_pose and net.config.use_depth), net.config.igd)
    out = net(torch.rand(2, 3, 32, 32))
    terms = loss(out, targets_for(2, (32, 32)))
    assert torch.isfinite(terms["total"])
    terms["total"].backward()
    unused = [n for n, p in net.named_parameters() if p.grad is None]
    assert not unused, unused[:5]
    if net.config.use_pose:
        assert [t.shape[1:] for t in out.pose.bin_logits] == [(4, 16), (4, 64)]
    if net.config.use_depth:
        assert out.depth.depth_norm.shape == (2, 1, 32, 32) and out.depth.bin_logits[0].shape[-2:] == (32, 32)
        assert sum(isinstance(m, SqueezeExcite) for m in net.depth_decoder.modules()) == 3


def test_residual_additions_of_the_initial_estimates():
    torch.manual_seed(0)
    pqb = EncoderPosePQB(64, (16, 64), 32).eval()
    feature, init_logit = torch.randn(3, 64, 2, 2), torch.randn(3, 4)
    with_init, _ = pqb(feature, init_logit)
    pqb.residual_init = False
    alone, _ = pqb(feature, init_logit)
    assert torch.allclose(with_init - alone, init_logit, atol=1e-6)

    settings = {**PAPER_NETWORK, "decoder_channels": 16, "head_channels": 8, "igd_channels": 4, "pose_hidden": 16,
                "pose_projection": 16}
    net = DAPMNet(DAPMConfig(backbone="resnet18", **settings)).eval()
    last = net.depth_pqb.head[-1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.zeros_(last.bias)
    with torch.no_grad():
        out = net(torch.rand(1, 3, 32, 32))
    # head output 0: refined = sigmoid(initial depth + IGD), both at full resolution (head_stride 1)
    expected = torch.sigmoid(out.depth.depth_init_norm + out.depth.igd_norm)
    assert torch.allclose(out.depth.depth_norm, expected, atol=1e-6)


def test_residual_conv_block_projects_when_widths_differ():
    block = ResidualConvBlock(8, 4)
    assert isinstance(block.shortcut, torch.nn.Conv2d) and block(torch.rand(1, 8, 5, 5)).shape == (1, 4, 5, 5)
    assert isinstance(ResidualConvBlock(8).shortcut, torch.nn.Identity)


def test_unknown_pose_bins_source_is_refused():
    with pytest.raises(ValueError, match="pose_bins_source"):
        DAPMConfig(pose_bins_source="mlp")
    with pytest.raises(ValueError, match="pose_stages"):
        DAPMConfig(pose_stages=5)
