import numpy as np
import pytest
import torch

from dapm_lightning.geometry import (
    POSE_RANGES,
    bin_centers,
    denormalize_pose,
    depth_to_grey,
    flip_pose,
    grey_to_depth,
    normalize_pose,
    quantize,
)


def test_normalize_maps_ranges_to_unit_interval():
    lo = torch.tensor([POSE_RANGES[k][0] for k in ("height", "pitch", "roll", "fov")])
    hi = torch.tensor([POSE_RANGES[k][1] for k in ("height", "pitch", "roll", "fov")])
    torch.testing.assert_close(normalize_pose(lo), torch.zeros(4))
    torch.testing.assert_close(normalize_pose(hi), torch.ones(4))
    p = torch.tensor([[55.0, -45.0, 0.0, 75.0]])
    torch.testing.assert_close(normalize_pose(p), torch.full((1, 4), 0.5))
    torch.testing.assert_close(denormalize_pose(normalize_pose(p)), p)


def test_flip_pose_negates_roll_only():
    p = torch.tensor([10.0, -20.0, 5.0, 60.0])
    torch.testing.assert_close(flip_pose(p), torch.tensor([10.0, -20.0, -5.0, 60.0]))
    with pytest.raises(ValueError, match="shape"):
        flip_pose(torch.zeros(3))


def test_quantize_edges_and_centres():
    x = torch.tensor([0.0, 0.0624, 0.0625, 0.5, 0.999, 1.0, 1.5, -0.2])
    assert quantize(x, 16).tolist() == [0, 0, 1, 8, 15, 15, 15, 0]
    assert quantize(bin_centers(64, x), 64).tolist() == list(range(64))


def test_grey_codec_matches_paper_equation():
    d = np.array([0.0, 1.0, 100.0, 999.9, 1000.0, 2000.0, np.inf])
    grey = depth_to_grey(d)
    expected = np.floor(255 * np.log2(np.minimum(d, 1000) + 1) / np.log2(1001)).astype(np.uint8)
    np.testing.assert_array_equal(grey, expected)
    assert grey[-1] == 255 and grey[-2] == 255
    assert grey_to_depth(np.array([255], np.uint8))[0] == pytest.approx(1000.0, rel=1e-6)
    # one grey level is a factor ~1.027 in depth
    levels = grey_to_depth(np.array([200, 201], np.uint8))
    assert levels[1] / levels[0] == pytest.approx(1.027, abs=0.002)


def test_grey_decodes_by_eq20_over_255_levels():
    # g / 255 of log2(1001): grey 85 is a third of the way, 1001 ** (1/3) - 1 = 9.0033 m; 170 two thirds, 99.07 m
    depth = grey_to_depth(np.array([0, 85, 170], np.uint8))
    np.testing.assert_allclose(depth, [0.0, 1001 ** (1 / 3) - 1, 1001 ** (2 / 3) - 1], rtol=1e-6)


def test_grey_255_decodes_to_exactly_max_depth():
    depth = grey_to_depth(np.array([254, 255], np.uint8), max_depth=1000.0)
    assert depth[1] == np.float32(1000.0) and depth[0] < 1000.0
