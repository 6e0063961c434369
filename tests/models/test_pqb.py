"""The PQB soft-argmax by value: the probability-weighted bin centre."""

import math

import pytest
import torch

from dapm_lightning.models.pqb import DepthPQB, PosePQB, expected_value, stage_probabilities


def test_expected_value_is_the_probability_weighted_bin_centre():
    # four bins of [0, 1]: centres 0.125, 0.375, 0.625, 0.875
    one_hot = torch.tensor([[0.0, 0.0, 30.0, 0.0]])
    assert expected_value(one_hot).item() == pytest.approx(0.625, abs=1e-6)
    uniform = torch.zeros(1, 4)
    assert expected_value(uniform).item() == pytest.approx(0.5)
    # two equal bins of weight e and one of weight 1: (e * 0.125 + e * 0.375 + 0.875) / (2e + 1)
    logits = torch.tensor([[1.0, 1.0, -100.0, 0.0]])
    e = math.e
    assert expected_value(logits).item() == pytest.approx((e * 0.125 + e * 0.375 + 0.875) / (2 * e + 1), rel=1e-5)


def test_expected_value_per_pixel_along_the_bins_dimension():
    logits = torch.full((2, 3, 4, 5), -50.0)
    logits[0, 0] = 50.0  # all pixels of image 0: the first of three bins (centre 1/6)
    logits[1, 2] = 50.0  # image 1: the last (centre 5/6)
    value = expected_value(logits, dim=1)
    assert value.shape == (2, 1, 4, 5)
    torch.testing.assert_close(value[0], torch.full((1, 4, 5), 1 / 6))
    torch.testing.assert_close(value[1], torch.full((1, 4, 5), 5 / 6))
    pose_logits = logits[:, :, 0, :4].permute(0, 2, 1)  # [B, 4 components, 3 bins], bins last
    torch.testing.assert_close(expected_value(pose_logits, dim=-1)[..., 0], torch.tensor([[1 / 6] * 4, [5 / 6] * 4]))


def test_pose_stage_probabilities_are_over_each_components_bins():
    """A constant added to all bins of one component changes no distribution over the bins, so not the refined pose."""
    torch.manual_seed(0)
    pqb = PosePQB(8, (4, 6), hidden=16).eval()
    feature, pose_init = torch.randn(2, 8), torch.rand(2, 4)
    with torch.no_grad():
        before, _ = pqb(feature, pose_init)
        last = pqb.stages[0][-1]  # the first stage's logits [B, 4 components x 4 bins]
        last.bias += torch.tensor([3.0, -2.0, 0.5, 7.0]).repeat_interleave(4)
        after, logits = pqb(feature, pose_init)
    assert logits[0].shape == (2, 4, 4)
    torch.testing.assert_close(after, before)


def test_the_sky_stage_is_a_sigmoid_and_reaches_the_next_stages():
    logits = torch.tensor([0.0, 2.0, -1.0]).view(1, 1, 1, 3)
    torch.testing.assert_close(stage_probabilities(logits), 1 / (1 + torch.exp(-logits)))  # one logit: BCE's sigmoid
    torch.testing.assert_close(stage_probabilities(torch.zeros(1, 4, 1, 3)).sum(dim=1), torch.ones(1, 1, 3))
    torch.manual_seed(0)
    pqb = DepthPQB(feature_channels=4, igd_channels=0, bins=(2, 4), channels=8).eval()
    feature, depth_init = torch.randn(1, 4, 5, 5), torch.rand(1, 1, 5, 5)
    with torch.no_grad():
        before, sky_before, bins_before = pqb(feature, depth_init, None)
        pqb.blocks[0].body[-1].bias += 4.0  # only the sky logit moves
        after, sky_after, bins_after = pqb(feature, depth_init, None)
    torch.testing.assert_close(sky_after, sky_before + 4.0)
    assert not torch.allclose(bins_after[0], bins_before[0])  # the 4-bin stage sees the sky probability
    assert not torch.allclose(after, before)
