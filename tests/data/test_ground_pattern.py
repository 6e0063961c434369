"""GroundPattern: a pattern painted on the flat ground of the pose, in metres on the ground plane."""

import albumentations as A
import numpy as np
import pytest
import torch

from dapm_lightning.data.transforms import (
    Augmentation,
    GroundPattern,
    GroundRecolour,
    ground_plane_xy,
    train_transform,
)
from dapm_lightning.geometry import ideal_ground_depth
from dapm_lightning.geometry.depth_codec import depth_to_grey


def _ground_and_box(pose: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Grey range depth of a flat ground (the IGD of ``pose``) with a box half as far in the lower left corner."""
    igd = ideal_ground_depth(torch.from_numpy(pose.astype(np.float64)), size)[0, 0].numpy()
    box = np.zeros(size, bool)
    box[size[0] - 8:size[0] - 2, 2:8] = True
    return depth_to_grey(np.where(box, igd * 0.5, igd)).astype(np.uint8), box


@pytest.mark.parametrize("pose", [[50.0, -90.0, 0.0, 60.0], [30.0, -35.0, 12.0, 85.0], [80.0, -10.0, -20.0, 40.0]])
def test_ground_plane_points_lie_at_the_ideal_ground_depth_of_the_pose(pose):
    size = (20, 28)
    xy = ground_plane_xy(np.array(pose), size)
    igd = ideal_ground_depth(torch.tensor([pose], dtype=torch.float64), size)[0, 0].numpy()
    below = igd < 1000.0
    assert below.any()
    reach = np.sqrt(xy[..., 0] ** 2 + xy[..., 1] ** 2 + pose[0] ** 2)  # camera at (0, 0, height)
    np.testing.assert_allclose(reach[below], igd[below], rtol=1e-6)
    above = np.isnan(xy[..., 0])  # the rays that never meet the ground: above the horizon, at the depth limit
    assert (igd[above] == 1000.0).all() and np.isfinite(xy[below]).all()
    assert above.any() != (pose[1] == -90.0)  # the oblique views see the sky, the nadir one does not


def test_at_nadir_the_ground_plane_spans_the_footprint_in_metres():
    height, fov, width = 50.0, 60.0, 32
    xy = ground_plane_xy(np.array([height, -90.0, 0.0, fov]), (width, width))
    pixel = 2 * height * np.tan(np.radians(fov / 2)) / width  # metres per pixel on the ground
    np.testing.assert_allclose(np.diff(xy[..., 1], axis=1), -pixel, rtol=1e-9)  # image right is world -Y
    np.testing.assert_allclose(np.diff(xy[..., 0], axis=0), -pixel, rtol=1e-9)  # image down is world -X


def test_the_pattern_changes_the_ground_only_and_keeps_objects_sky_depth_and_pose():
    pose = np.array([40.0, -20.0, 10.0, 80.0], np.float32)  # sky at the top
    grey, box = _ground_and_box(pose, (48, 48))
    sky = grey == 255
    assert sky.any() and box.any()
    image = np.full((48, 48, 3), (90, 140, 60), np.uint8)
    image[sky] = (120, 160, 230)
    pipeline = A.Compose([GroundPattern(period=(4.0, 4.0), strength=(1.0, 1.0), p=1.0)])
    pipeline.set_random_seed(5)
    out = pipeline(image=image, mask=grey, pose=pose)
    np.testing.assert_array_equal(out["mask"], grey)
    np.testing.assert_array_equal(out["pose"], pose)
    np.testing.assert_array_equal(out["image"][sky | box], image[sky | box])
    ground = ~sky & ~box
    assert len(np.unique(out["image"][ground], axis=0)) > 10  # a pattern, not one colour
    pipeline.set_random_seed(5)
    np.testing.assert_array_equal(pipeline(image=image, mask=grey, pose=pose)["image"], out["image"])


def test_a_pattern_finer_than_the_pixels_fades_to_one_colour_instead_of_aliasing():
    pose = np.array([60.0, -90.0, 0.0, 70.0], np.float32)  # 2.6 m per pixel on the ground
    grey, box = _ground_and_box(pose, (32, 32))
    image = np.full((32, 32, 3), (90, 140, 60), np.uint8)
    for seed in range(6):
        fine = A.Compose([GroundPattern(period=(1.0, 1.0), strength=(1.0, 1.0), p=1.0)])
        fine.set_random_seed(seed)
        coarse = A.Compose([GroundPattern(period=(60.0, 60.0), strength=(1.0, 1.0), p=1.0)])
        coarse.set_random_seed(seed)
        assert len(np.unique(fine(image=image, mask=grey, pose=pose)["image"][~box], axis=0)) == 1
        assert len(np.unique(coarse(image=image, mask=grey, pose=pose)["image"][~box], axis=0)) > 5


def test_the_pattern_leaves_images_without_a_pose_or_grey_depth():
    pose = np.array([40.0, -50.0, 0.0, 70.0], np.float32)
    grey, _ = _ground_and_box(pose, (16, 16))
    image = np.random.default_rng(0).integers(0, 255, (16, 16, 3), dtype=np.uint8)
    pattern = A.Compose([GroundPattern(period=(3.0, 3.0), p=1.0)])
    nan_pose = np.full(4, np.nan, np.float32)
    heights = grey.astype(np.float32) / 8  # Potsdam: metres, not grey levels
    for mask, given in ((grey, nan_pose), (heights, pose), (heights, nan_pose)):
        np.testing.assert_array_equal(pattern(image=image, mask=mask, pose=given)["image"], image)


def test_the_training_pipeline_paints_before_it_recolours_with_the_data_modules_depth_kind(tiny_uapd):
    from dapm_lightning.data.datamodules import UAPDDataModule

    assert not any(isinstance(t, GroundPattern) for t in train_transform().transforms)  # off by default
    module = UAPDDataModule(tiny_uapd, depth_kind="planar", max_depth=500.0,
                            augmentation=Augmentation(ground_pattern_p=0.3, ground_recolour_p=0.5))
    transforms = module.split_transform(True).transforms
    kinds = [type(t) for t in transforms]
    assert kinds.index(GroundPattern) < kinds.index(GroundRecolour)
    [pattern] = [t for t in transforms if isinstance(t, GroundPattern)]
    assert (pattern.depth_kind, pattern.max_depth, pattern.p) == ("planar", 500.0, 0.3)
    with pytest.raises(ValueError, match="ground_pattern_p"):
        Augmentation(ground_pattern_p=-0.1)
    with pytest.raises(ValueError, match="period"):
        GroundPattern(period=(0.0, 4.0))
