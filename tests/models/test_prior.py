"""Pose priors in the network: fusion rules, the IGD feature seeing the fused pose, and the losses untouched."""

import math

import pytest
import torch

from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.models import DAPMConfig, DAPMNet, PosePrior, fuse_pose
from dapm_lightning.models.prior import NETWORK_SPREAD_WITHOUT_BINS, PRIOR_FEATURES, bins_spread, prior_features

NAN = float("nan")
TINY = {"backbone": "resnet18", "decoder_channels": 16, "head_channels": 8, "igd_channels": 4, "pose_hidden": 16,
        "depth_bins": (2, 4), "pose_bins": (4,)}


def test_exact_components_replace_unknown_ones_stay_and_uncertain_ones_meet_in_between():
    spec = IGDSpec()
    network = spec.normalize(torch.tensor([[50.0, -40.0, 5.0, 60.0], [30.0, -60.0, 0.0, 90.0]]))
    prior = PosePrior(torch.tensor([[80.0, NAN, -5.0, NAN], [NAN, NAN, NAN, NAN]]), torch.tensor([0.0, 0.0, 2.0, 0.0]))
    spread = torch.full((2, 4), 0.05)
    fused = spec.denormalize(fuse_pose(network, prior, spec, spread))
    assert fused[0, 0] == pytest.approx(80.0) and fused[0, 1] == pytest.approx(-40.0)  # exact: replaced; unknown: kept
    assert fused[0, 3] == pytest.approx(60.0) and torch.allclose(fused[1], spec.denormalize(network)[1])
    # roll: inverse-variance mean of the network (spread 0.05 x 60 deg = 3 deg) and the prior (2 deg)
    weight = 3.0**2 / (3.0**2 + 2.0**2)
    assert fused[0, 2] == pytest.approx(5.0 + weight * (-5.0 - 5.0), abs=1e-4)
    # a much surer network barely moves
    sure = spec.denormalize(fuse_pose(network, prior, spec, torch.full((2, 4), 1e-3)))
    assert abs(float(sure[0, 2]) - 5.0) < 0.01


def test_bins_spread_is_the_standard_deviation_of_the_bins_distribution():
    logits = torch.full((1, 4, 8), -1e4)
    logits[0, 0, 3] = 0.0  # one-hot: the floor
    logits[0, 1, :] = 0.0  # uniform over 8 bins: sqrt((8^2 - 1) / 12) / 8
    logits[0, 2, [0, 7]] = 0.0  # two ends
    logits[0, 3, [2, 3]] = 0.0
    spread = bins_spread(logits)[0]
    assert spread[0] == pytest.approx(1e-3)
    assert spread[1] == pytest.approx(math.sqrt(63 / 12) / 8, rel=1e-5)
    assert spread[2] == pytest.approx(3.5 / 8, rel=1e-5) and spread[3] == pytest.approx(0.5 / 8, rel=1e-5)


def test_prior_reaches_the_depth_through_the_igd_and_is_reported_beside_the_network_pose():
    torch.manual_seed(0)
    net = DAPMNet(DAPMConfig(**TINY)).eval()
    net.depth_pqb.blocks[0].body[-1].bias.data.fill_(-4.0)  # ground, not sky
    image = torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        plain = net(image)
        given = net(image, prior=PosePrior(torch.tensor([[20.0, -30.0, NAN, NAN], [NAN] * 4]), torch.zeros(4)))
    assert torch.equal(given.pose.pose, plain.pose.pose)  # the network's own estimate is unchanged (losses)
    used = given.inference_outputs()
    assert used.pose[0, 0] == pytest.approx(20.0) and used.pose[0, 1] == pytest.approx(-30.0, abs=1e-4)
    assert torch.equal(used.pose[0, 2:], plain.pose.pose[0, 2:])
    assert torch.equal(used.pose_network, plain.pose.pose)
    assert not torch.allclose(given.depth_m[0], plain.depth_m[0])  # the depth head saw the prior's ground
    assert torch.equal(given.depth_m[1], plain.depth_m[1])  # nothing known: the same as without a prior
    assert set(plain.inference_outputs().named()) == {"depth_m", "sky_prob", "pose"}


def test_without_pose_bins_the_fixed_spread_is_used():
    spec = IGDSpec()
    network = torch.full((1, 4), 0.5)
    prior = PosePrior(torch.tensor([[NAN, NAN, NAN, 100.0]]), torch.tensor([0.0, 0.0, 0.0, 9.0]))
    fused = fuse_pose(network, prior, spec, None)
    prior_spread = 9.0 / 90.0
    weight = NETWORK_SPREAD_WITHOUT_BINS**2 / (NETWORK_SPREAD_WITHOUT_BINS**2 + prior_spread**2)
    assert fused[0, 3] == pytest.approx(0.5 + weight * (spec.normalize(torch.tensor([[0, 0, 0, 100.0]]))[0, 3] - 0.5))
    with pytest.raises(ValueError, match="sigma must be >= 0"):
        PosePrior(torch.zeros(1, 4), torch.tensor([-1.0, 0, 0, 0]))


def test_a_pose_branch_told_the_telemetry_reads_it_in_its_decoder_and_its_head():
    torch.manual_seed(0)
    net = DAPMNet(DAPMConfig(**TINY, pose_prior_input=True)).eval()
    image = torch.rand(2, 3, 64, 64)
    height_known = PosePrior(torch.tensor([[20.0, NAN, NAN, NAN], [NAN] * 4]), torch.tensor([3.0, 1.0, 1.0, 2.0]))
    with torch.no_grad():
        plain = net(image)
        told = net(image, prior=height_known)
        unknown = net(image, prior=PosePrior(torch.full((2, 4), NAN), torch.zeros(4)))
    assert not torch.allclose(told.pose.pose[0], plain.pose.pose[0])  # the network's own estimate moves: all four
    assert torch.equal(told.pose.pose[1], plain.pose.pose[1])  # nothing known for this image
    assert torch.equal(unknown.pose.pose, plain.pose.pose)  # nothing known anywhere: as without a prior
    features = prior_features(height_known, net.config.igd, image)
    assert features.shape == (2, PRIOR_FEATURES) and torch.equal(features[1], torch.zeros(PRIOR_FEATURES))
    assert features[0, :4].tolist() == [1, 0, 0, 0] and features[0, 4] == pytest.approx((20 - 10) / 90)
    assert features[0, 8] == pytest.approx(3 / 90)  # the normalised sigma
    # both parts read it: the decoder's projection and the refinement head receive gradients from a told pose
    net.train()
    net(image, prior=height_known).pose.pose_norm.sum().backward()
    assert net.pose_decoder.prior_projection.weight.grad.abs().sum() > 0
    first = net.pose_pqb.head.body[0]  # the head's input layer: initial logit, telemetry, bins logits
    assert first.in_features == 4 + PRIOR_FEATURES + sum(4 * n for n in TINY["pose_bins"])
    assert first.weight.grad[:, 4:4 + PRIOR_FEATURES].abs().sum() > 0


def test_a_network_told_nothing_has_no_telemetry_weights_and_switches_need_their_branch():
    net = DAPMNet(DAPMConfig(**TINY))
    assert net.pose_decoder.prior_projection is None and net.pose_pqb.prior_features == 0
    with pytest.raises(ValueError, match="pose_prior_input needs the pose branch"):
        DAPMConfig(**{**TINY, "use_depth": True, "use_pose": False, "use_igd_feature": False}, pose_prior_input=True)


def test_an_igd_feature_told_the_telemetry_changes_the_depth_and_not_the_pose():
    torch.manual_seed(0)
    net = DAPMNet(DAPMConfig(**TINY, depth_prior_input=True)).eval()
    net.depth_pqb.blocks[0].body[-1].bias.data.fill_(-4.0)  # ground, not sky
    assert net.igd_feature.body[0][0].in_channels == 1 + PRIOR_FEATURES
    image = torch.rand(2, 3, 64, 64)
    with torch.no_grad():
        plain = net(image)
        own = plain.pose.pose
        # the network's own pose given back as exact telemetry: the same IGD, only the telemetry vector differs
        told = net(image, prior=PosePrior(own.clone(), torch.zeros(4)))
    assert torch.equal(told.pose.pose, own)  # the pose branch is not told
    assert torch.allclose(told.depth.igd_norm, plain.depth.igd_norm, atol=1e-5)
    assert not torch.allclose(told.depth_m, plain.depth_m)  # the depth head read what is known
    with pytest.raises(ValueError, match="depth_prior_input needs the IGD feature"):
        DAPMConfig(**TINY, use_igd_feature=False, depth_prior_input=True)


def test_a_prior_is_made_when_any_component_is_known_and_none_when_nothing_is():
    from dapm_lightning.models.prior import PosePrior

    partial = PosePrior.from_rows(torch.tensor([[NAN, NAN, NAN, NAN], [NAN, -40.0, NAN, NAN]]), (0.0, 1.0, 1.0, 2.0))
    assert partial is not None and partial.known.tolist() == [[False] * 4, [False, True, False, False]]
    assert PosePrior.from_rows(torch.full((2, 4), NAN), (0.0, 1.0, 1.0, 2.0)) is None


def test_the_network_is_told_a_prior_far_outside_the_range_clamped():
    spec = IGDSpec()
    prior = PosePrior(torch.tensor([[5000.0, -40.0, NAN, NAN]]), torch.tensor([0.0, 0.0, 0.0, 0.0]))
    features = prior_features(prior, spec, torch.zeros(1, 3))
    value = features[0, 4:8]
    pitch = float(spec.normalize(torch.tensor([[50.0, -40.0, 0.0, 60.0]]))[0, 1])
    assert value[0] == 1.5 and value[1] == pytest.approx(pitch)
    assert value[2:].tolist() == [0.0, 0.0]


def test_prior_settings_refuse_a_negative_sigma():
    from dapm_lightning.models.prior import PriorSettings

    with pytest.raises(ValueError, match="four standard deviations >= 0"):
        PriorSettings(sigma=(3.0, -1.0, 1.0, 2.0))
    assert PriorSettings(sigma=(0, 0, 0, 0)).sigma == (0.0, 0.0, 0.0, 0.0)
