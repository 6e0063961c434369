"""The PQB soft-argmax by value: the probability-weighted bin centre."""

import math

import pytest
import torch

from dapm_lightning.models.pqb import expected_value


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
