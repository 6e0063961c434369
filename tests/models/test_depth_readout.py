"""``depth_readout: bins_mode``: the output depth read from the last bins stage's most probable bin."""

import pytest
import torch

from dapm_lightning.geometry import MAX_DEPTH_M
from dapm_lightning.geometry.depth_codec import decode_igd_ratio, decode_log_depth, encode_log_depth
from dapm_lightning.models import DAPMConfig, DAPMNet, PosePrior
from dapm_lightning.models.pqb import bins_mode, expected_value
from dapm_lightning.training.checkpointing import load_dapm_module
from dapm_lightning.training.module import DAPMModule

TINY = {"backbone": "resnet18", "decoder_channels": 16, "head_channels": 8, "igd_channels": 4, "pose_hidden": 16,
        "depth_bins": (2, 8), "pose_bins": (4,)}
POSES = torch.tensor([[40.0, -50.0, 5.0, 70.0], [120.0, -30.0, -8.0, 90.0]])


def test_the_mode_stays_at_the_stronger_of_two_modes_where_the_mean_falls_between():
    logits = torch.full((1, 8, 1, 3), -20.0)
    logits[0, 2, 0, 0], logits[0, 6, 0, 0] = 5.0, 4.0  # ground or object: two modes
    logits[0, 0, 0, 1] = logits[0, 1, 0, 1] = 5.0  # at the first bin: no neighbour below
    logits[0, 4, 0, 2], logits[0, 5, 0, 2] = 5.0, 5.0 + torch.log(torch.tensor(3.0))  # one mode over two bins
    mode, mean = bins_mode(logits).flatten(), expected_value(logits).flatten()
    assert mode[0] == pytest.approx(2.5 / 8, abs=1e-4) and mean[0] == pytest.approx(0.447, abs=0.01)
    assert mode[1] == pytest.approx((0.5 + 1.5) / 2 / 8, abs=1e-4)  # the missing neighbour has no weight
    assert mode[2] == pytest.approx((4.5 * 0.25 + 5.5 * 0.75) / 8, abs=1e-3)  # sub-bin precision


def test_the_mode_moves_continuously_through_a_tie_where_an_argmax_jumps():
    """Rounding noise (ONNX, bf16, int8) must not move the depth by a bin: at a tie the readout is continuous."""
    logits = torch.full((1, 8, 1, 1), -20.0)
    logits[0, 2], logits[0, 6] = 5.0, 5.0
    nudged = logits.clone()
    nudged[0, 6] += 1e-4
    assert (bins_mode(nudged) - bins_mode(logits)).abs().item() < 1e-3  # an argmax moves 0.5 here
    assert bins_mode(logits).item() == pytest.approx(4.5 / 8, abs=1e-3)  # at an exact tie: between the modes
    untrained = torch.randn(2, 16, 5, 7) * 1e-3  # near-uniform bins: the readout barely moves with the logits
    shift = bins_mode(untrained + torch.randn_like(untrained) * 1e-6) - bins_mode(untrained)
    assert shift.abs().max() < 1e-4


@pytest.mark.parametrize("parametrization", ["absolute", "igd_ratio"])
def test_the_readout_changes_the_output_depth_not_the_head_the_loss_trains(parametrization):
    torch.manual_seed(0)
    head = DAPMNet(DAPMConfig(**TINY, depth_parametrization=parametrization)).eval()
    head.depth_pqb.blocks[0].body[-1].bias.data.fill_(-4.0)  # mostly land, not all sky
    mode = DAPMNet(DAPMConfig(**TINY, depth_parametrization=parametrization, depth_readout="bins_mode")).eval()
    mode.load_state_dict(head.state_dict())  # no weight differs: a checkpoint reads out either way
    image, prior = torch.rand(2, 3, 40, 56), PosePrior(POSES, torch.zeros(4))
    with torch.no_grad():
        a, b = head(image, prior=prior).depth, mode(image, prior=prior).depth
    torch.testing.assert_close(a.depth_norm, b.depth_norm)  # Eq. 17 trains the head's either way
    assert a.readout_norm is None and b.readout_norm.shape == b.depth_norm.shape
    decoded = (decode_log_depth(b.readout_norm, MAX_DEPTH_M) if b.igd_m is None
               else decode_igd_ratio(b.readout_norm, b.igd_m, MAX_DEPTH_M))
    land = b.sky_logits <= 0
    torch.testing.assert_close(b.depth_m[land], decoded[land])
    assert land.float().mean() > 0.5 and not torch.allclose(a.depth_m[land], b.depth_m[land])
    # the maps the test outputs write show the readout
    torch.testing.assert_close(b.log_depth_norm(MAX_DEPTH_M)[land], encode_log_depth(b.depth_m, MAX_DEPTH_M)[land],
                               rtol=1e-4, atol=1e-4)


def test_bins_mode_needs_bins():
    with pytest.raises(ValueError, match="depth_readout 'bins_mode' needs a depth-bins stage"):
        DAPMConfig(**{**TINY, "depth_bins": (2,)}, depth_readout="bins_mode")
    with pytest.raises(ValueError, match="depth_readout must be one of head, bins_mode"):
        DAPMConfig(**TINY, depth_readout="median")


def test_a_checkpoint_reads_out_either_way_but_keeps_its_architecture(tmp_path):
    torch.manual_seed(0)
    module = DAPMModule(DAPMConfig(**TINY, depth_parametrization="igd_ratio"))
    path = tmp_path / "model.ckpt"
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams),
                "pytorch-lightning_version": "2.6.0"}, path)
    loaded = load_dapm_module(path, net_overrides={"depth_readout": "bins_mode"})
    assert loaded.net.config.depth_readout == "bins_mode" and load_dapm_module(path).net.config.depth_readout == "head"
    with pytest.raises(ValueError, match="net_overrides cannot change \\['depth_parametrization'\\]"):
        load_dapm_module(path, net_overrides={"depth_parametrization": "absolute"})
