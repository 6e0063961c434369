"""The evaluation the quickstart and the transfer benchmark share (dapm_lightning/tools/evaluate.py)."""

import pytest
import torch

from dapm_lightning.tools.evaluate import GroundSplit, median_scaled, scale_errors


def test_median_scaled_removes_each_images_scale_only():
    target = torch.rand(2, 1, 8, 8) * 50 + 5
    target[0, 0, 0, :3] = float("inf")  # sky: ignored by the median
    pred = target.clone()
    pred[0] *= 3.0
    pred[1] *= 0.5
    target[1, 0, 0, 0] = 4.0  # the nearest pixel, and still the nearest once wrong: the median is that of any draw
    pred[1, 0, 0, 0] = 1.0  # one wrong pixel stays wrong
    scaled = median_scaled(pred, target)
    valid = torch.isfinite(target)
    assert torch.allclose(scaled[0][valid[0]], target[0][valid[0]], rtol=1e-5)
    assert torch.allclose(scaled[1].flatten()[1:], target[1].flatten()[1:], rtol=1e-5)
    assert not torch.isclose(scaled[1, 0, 0, 0], target[1, 0, 0, 0], rtol=0.05)


def test_scale_errors_separate_the_footprint_from_the_height():
    true = torch.tensor([[40.0, -60.0, 0.0, 60.0], [80.0, -30.0, 5.0, 90.0]], dtype=torch.float64)
    doubled = true.clone()
    doubled[:, 0] *= 2
    assert scale_errors(doubled, true) == pytest.approx({"height_rel": 1.0, "footprint_rel": 1.0})
    same_footprint = true.clone()  # half the height, a wider FoV: the same ground in the picture
    same_footprint[:, 0] /= 2
    same_footprint[:, 3] = torch.rad2deg(2 * torch.atan(2 * torch.tan(torch.deg2rad(true[:, 3]) / 2)))
    errors = scale_errors(same_footprint, true)
    assert errors["height_rel"] == pytest.approx(1.0) and errors["footprint_rel"] == pytest.approx(0.0, abs=1e-9)


def test_ground_split_scores_the_ground_and_what_stands_on_it_apart():
    depth = torch.full((1, 1, 4, 4), 50.0)
    ground = torch.zeros(1, 1, 4, 4, dtype=torch.bool)
    ground[..., 2:, :] = True  # the lower half is flat ground
    depth[..., 0, 0] = float("inf")  # sky counts in neither part
    pred = torch.where(ground, depth, depth * 2)  # right on the ground, twice too far on the objects
    split = GroundSplit()
    split.update(pred, depth, ground)
    assert split.compute() == pytest.approx({"d1_ground": 1.0, "d1_objects": 0.0, "ground_share": 8 / 15})


def test_scale_errors_are_medians_that_one_wild_image_does_not_move():
    true = torch.tensor([[10.0, -60.0, 0.0, 60.0]] * 3, dtype=torch.float64)
    pred = true.clone()
    pred[:, 0] = torch.tensor([11.0, 11.0, 30.0])  # two 10 % high, one three times too high
    assert scale_errors(pred, true) == pytest.approx({"height_rel": 0.1, "footprint_rel": 0.1})


def test_the_ground_share_counts_valid_pixels_only():
    depth = torch.full((1, 1, 2, 2), 50.0)
    depth[..., 0, 0], depth[..., 0, 1] = float("inf"), 0.0  # sky and no depth, both inside the ground mask
    split = GroundSplit()
    split.update(depth.clone(), depth, torch.ones_like(depth, dtype=torch.bool))
    assert split.compute()["ground_share"] == 1.0
