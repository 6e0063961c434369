import albumentations as A
import numpy as np
import pytest
import torch

from dapm_lightning.data import UAPDDataset
from dapm_lightning.data.sample import seed_augmentation
from dapm_lightning.data.transforms import (
    Augmentation,
    GroundRecolour,
    PoseAwareCentreZoom,
    PoseAwareHorizontalFlip,
    colour_matrix,
    train_transform,
)
from dapm_lightning.geometry import ideal_ground_depth
from dapm_lightning.geometry.depth_codec import depth_to_grey


def test_flip_moves_image_depth_and_roll_together():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (5, 7, 3), dtype=np.uint8)
    depth = rng.integers(0, 255, (5, 7), dtype=np.uint8)
    pose = np.array([40.0, -30.0, 12.5, 70.0], np.float32)
    out = A.Compose([PoseAwareHorizontalFlip(p=1.0)])(image=image, mask=depth, pose=pose)
    np.testing.assert_array_equal(out["image"], image[:, ::-1])
    np.testing.assert_array_equal(out["mask"], depth[:, ::-1])
    np.testing.assert_array_equal(out["pose"], [40.0, -30.0, -12.5, 70.0])
    kept = A.Compose([PoseAwareHorizontalFlip(p=0.0)])(image=image, mask=depth, pose=pose)
    np.testing.assert_array_equal(kept["pose"], pose)


def test_flipped_sample_igd_is_the_mirrored_igd(tiny_uapd):
    plain = UAPDDataset(tiny_uapd, "train")
    flipped = UAPDDataset(tiny_uapd, "train", A.Compose([PoseAwareHorizontalFlip(p=1.0)]))
    a, b = plain[0], flipped[0]
    torch.testing.assert_close(b["depth"], a["depth"].flip(-1))
    torch.testing.assert_close(b["image"], a["image"].flip(-1))
    size = tuple(a["depth"].shape[-2:])
    torch.testing.assert_close(ideal_ground_depth(b["pose"].double(), size),
                               ideal_ground_depth(a["pose"].double(), size).flip(-1))


@pytest.mark.parametrize("depth_kind", ["range", "planar"])
def test_centre_zoom_is_the_camera_of_the_narrower_fov(depth_kind):
    """The zoomed flat ground is the IGD of the zoomed pose (image and depth alike), off-centre and rolled."""
    size = (48, 64)
    pose = np.array([35.0, -40.0, 12.0, 80.0])
    igd = ideal_ground_depth(torch.from_numpy(pose), size, depth_kind=depth_kind)[0, 0].numpy()
    zoom = PoseAwareCentreZoom(max_zoom=1.5, p=1.0)
    new_pose = zoom.apply_to_pose(pose.astype(np.float32), zoom=1.5)
    np.testing.assert_allclose(np.tan(np.radians(new_pose[3]) / 2) * 1.5, np.tan(np.radians(80.0) / 2), rtol=1e-5)
    np.testing.assert_array_equal(new_pose[:3], pose[:3])
    expected = ideal_ground_depth(torch.from_numpy(new_pose.astype(np.float64)), size,
                                  depth_kind=depth_kind)[0, 0].numpy()
    zoomed = zoom.apply(igd.astype(np.float32), zoom=1.5)  # bilinear, as the image
    below = expected < 300  # away from the horizon, where the depth's curvature makes bilinear samples err
    assert below.mean() > 0.5
    error = np.abs(zoomed[below] / expected[below] - 1)
    assert error.max() < 0.0025 and np.median(error) < 0.0005  # half a pixel off the centre: a median of 0.001
    grey = depth_to_grey(igd, 1000.0).round().astype(np.uint8)
    nearest = zoom.apply_to_mask(grey, zoom=1.5)
    assert set(np.unique(nearest)) <= set(np.unique(grey))  # depths moved, never blended
    out = A.Compose([zoom])(image=np.zeros((*size, 3), np.uint8), mask=grey, pose=pose.astype(np.float32))
    assert 58.0 < out["pose"][3] <= 80.0 and out["mask"].shape == size  # zoom 1.5 at most: 58.4 deg


def test_centre_zoom_keeps_the_fov_range_and_leaves_images_without_a_pose():
    zoom = PoseAwareCentreZoom(max_zoom=3.0, p=1.0)
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (16, 16, 3), dtype=np.uint8)
    for fov in (31.0, 40.0, 120.0):
        for _ in range(20):
            out = A.Compose([zoom])(image=image, mask=image[..., 0], pose=np.array([30, -50, 0, fov], np.float32))
            assert 30.0 - 1e-4 <= out["pose"][3] <= fov
    nan = np.full(4, np.nan, np.float32)
    out = A.Compose([zoom])(image=image, mask=image[..., 0], pose=nan)
    np.testing.assert_array_equal(out["image"], image)
    assert np.isnan(out["pose"]).all()
    with pytest.raises(ValueError, match="max_zoom must be >= 1"):
        Augmentation(max_zoom=0.5)
    assert [type(t) for t in train_transform(Augmentation(zoom_p=0.3)).transforms][0] is PoseAwareCentreZoom


def test_centre_zoom_moves_a_depth_edge_without_blending_its_two_depths():
    """A roof edge (two grey levels, nothing between) stays two grey levels: no made-up depth along the edge."""
    grey = np.full((16, 20), 40, np.uint8)
    grey[:, 10:] = 200
    zoom = PoseAwareCentreZoom(max_zoom=1.5, p=1.0)
    for factor in (1.1, 1.37, 1.5):
        assert set(np.unique(zoom.apply_to_mask(grey, zoom=factor)).tolist()) == {40, 200}
    out = A.Compose([zoom])(image=np.zeros((16, 20, 3), np.uint8), mask=grey,
                            pose=np.array([30, -50, 0, 80.0], np.float32))
    assert set(np.unique(out["mask"]).tolist()) == {40, 200}


def test_centre_zoom_leaves_a_pose_narrower_than_the_fov_range_as_it_is():
    """A FoV already below the range's lower end cannot be zoomed further: image and FoV stay, never widened."""
    zoom = PoseAwareCentreZoom(max_zoom=1.5, p=1.0)  # min_fov: the range's 30 degrees
    image = np.random.default_rng(0).integers(0, 255, (16, 16, 3), dtype=np.uint8)
    pose = np.array([30, -50, 0, 20.0], np.float32)
    for _ in range(10):
        out = A.Compose([zoom])(image=image, mask=image[..., 0], pose=pose)
        np.testing.assert_array_equal(out["image"], image)
        np.testing.assert_array_equal(out["pose"], pose)


def test_train_pipeline_is_photometric_plus_pose_aware_flip_only():
    pipeline = train_transform()
    geometric = [t for t in pipeline.transforms if isinstance(t, A.DualTransform)]
    assert [type(t) for t in geometric] == [PoseAwareHorizontalFlip]
    rng = np.random.default_rng(1)
    depth = rng.integers(0, 255, (8, 9), dtype=np.uint8)
    for _ in range(10):
        out = pipeline(image=rng.integers(0, 255, (8, 9, 3), dtype=np.uint8), mask=depth,
                       pose=np.array([1.0, 2.0, 3.0, 4.0], np.float32))
        flipped = out["pose"][2] == -3.0
        np.testing.assert_array_equal(out["mask"], depth[:, ::-1] if flipped else depth)


def _ground_and_box(pose: np.ndarray, size: tuple[int, int], depth_kind: str = "range",
                    max_depth: float = 1000.0) -> tuple[np.ndarray, np.ndarray]:
    """Depth grey levels of a flat ground (the IGD of ``pose``) with a box nearer than it, and the box's mask."""
    igd = ideal_ground_depth(torch.from_numpy(pose.astype(np.float64)), size, depth_kind=depth_kind,
                             max_depth=max_depth)[0, 0].numpy()
    box = np.zeros(size, bool)
    box[size[0] - 6:size[0] - 2, 2:6] = True
    return depth_to_grey(np.where(box, igd * 0.5, igd), max_depth).round().astype(np.uint8), box


def _colours(image: np.ndarray, where: np.ndarray) -> np.ndarray:
    return np.unique(image[where], axis=0)


def test_colour_matrix_turns_scales_and_keeps_grey():
    np.testing.assert_allclose(colour_matrix(0.0, 1.0, 1.0), np.eye(3), atol=1e-12)
    grey = np.array([100.0, 100.0, 100.0])
    np.testing.assert_allclose(colour_matrix(123.0, 1.6, 0.5) @ grey, grey / 2, atol=1e-9)  # no chroma to turn
    green = np.array([60.0, 160.0, 40.0])
    washed = colour_matrix(0.0, 0.0, 1.0) @ green
    np.testing.assert_allclose(washed, washed.mean(), atol=1e-9)  # saturation 0: the grey of the same luma
    turned = colour_matrix(180.0, 1.0, 1.0) @ green
    assert turned[1] < turned[0] and turned[1] < turned[2]  # green turned half-way round: magenta


@pytest.mark.parametrize(("depth_kind", "max_depth"), [("range", 1000.0), ("planar", 1000.0), ("range", 300.0)])
def test_ground_recolour_recolours_ground_and_objects_apart_and_keeps_sky_depth_and_pose(depth_kind, max_depth):
    pose = np.array([40.0, -10.0, 25.0, 90.0], np.float32)  # the horizon tilted across the picture: sky on top
    grey, box = _ground_and_box(pose, (24, 24), depth_kind, max_depth)
    sky = grey == 255
    assert sky.any() and (~sky & ~box).sum() > 100
    image = np.full((24, 24, 3), (90, 140, 60), np.uint8)  # ground and box the same colour
    image[sky] = (120, 160, 230)
    pipeline = A.Compose([GroundRecolour(depth_kind, max_depth, p=1.0)])
    pipeline.set_random_seed(3)
    out = pipeline(image=image, mask=grey, pose=pose)
    np.testing.assert_array_equal(out["mask"], grey)
    np.testing.assert_array_equal(out["pose"], pose)
    np.testing.assert_array_equal(out["image"][sky], image[sky])
    ground, objects = _colours(out["image"], ~sky & ~box), _colours(out["image"], box)
    assert len(objects) == 1 and not (objects[0] == image[box][0]).all()
    assert len(ground) == 1 and not (ground[0] == objects[0]).all()
    pipeline.set_random_seed(3)
    np.testing.assert_array_equal(pipeline(image=image, mask=grey, pose=pose)["image"], out["image"])
    other_kind = "planar" if depth_kind == "range" else "range"  # told the wrong depth, it finds another ground
    wrong = A.Compose([GroundRecolour(other_kind, max_depth, p=1.0)])
    wrong.set_random_seed(3)
    assert len(_colours(wrong(image=image, mask=grey, pose=pose)["image"], ~sky & ~box)) > 1


def test_ground_recolour_rounds_the_changed_colours_to_the_nearest_level():
    """The recoloured levels are rounded, not truncated (which darkens every changed pixel by half a level)."""
    pose = np.array([40.0, -50.0, 0.0, 70.0], np.float32)
    grey, _ = _ground_and_box(pose, (16, 16))
    image = np.random.default_rng(0).integers(0, 170, (16, 16, 3), dtype=np.uint8)
    brighter = A.Compose([GroundRecolour(hue=0.0, saturation=(1.0, 1.0), brightness=(1.3, 1.3), p=1.0)])
    out = brighter(image=image, mask=grey, pose=pose)["image"].astype(np.float64)
    expected = image.astype(np.float64) @ colour_matrix(0.0, 1.0, 1.3).T  # both regions: the same change
    below = grey < 255
    assert below.mean() > 0.5
    np.testing.assert_allclose(out[below], np.clip(expected[below], 0, 255), atol=0.5 + 1e-3)


def test_ground_recolour_leaves_images_without_a_pose_or_grey_depth():
    pose = np.array([40.0, -50.0, 0.0, 70.0], np.float32)
    grey, _ = _ground_and_box(pose, (16, 16))
    image = np.random.default_rng(0).integers(0, 255, (16, 16, 3), dtype=np.uint8)
    recolour = A.Compose([GroundRecolour(p=1.0)])
    nan_pose = np.full(4, np.nan, np.float32)
    heights = grey.astype(np.float32) / 8  # Potsdam: metres, not grey levels
    for mask, given in ((grey, nan_pose), (heights, pose), (heights, nan_pose)):
        np.testing.assert_array_equal(recolour(image=image, mask=mask, pose=given)["image"], image)
    assert not (recolour(image=image, mask=grey, pose=pose)["image"] == image).all()


def test_ground_recolour_in_the_training_pipeline_uses_the_data_modules_depth_kind(tiny_uapd):
    from dapm_lightning.data.datamodules import UAPDDataModule

    assert not any(isinstance(t, GroundRecolour) for t in train_transform().transforms)  # off by default
    module = UAPDDataModule(tiny_uapd, depth_kind="planar", max_depth=500.0,
                            augmentation=Augmentation(ground_recolour_p=0.4))
    [recolour] = [t for t in module.split_transform(True).transforms if isinstance(t, GroundRecolour)]
    assert (recolour.depth_kind, recolour.max_depth, recolour.p) == ("planar", 500.0, 0.4)
    assert module.split_transform(False) is None
    with pytest.raises(ValueError, match="ground_recolour_p"):
        Augmentation(ground_recolour_p=1.5)


def test_a_samples_transforms_draw_apart():
    """Each transform of a seeded pipeline makes its own draws: whether one applies says nothing of another."""
    pipeline = A.Compose([A.InvertImg(p=0.5), PoseAwareHorizontalFlip(p=0.5)])
    image = np.full((4, 6, 3), 10, np.uint8)
    image[:, 0] = 200
    pose = np.array([40.0, -30.0, 12.5, 70.0], np.float32)
    inverted, flipped = [], []
    for index in range(200):
        seed_augmentation(pipeline, 5, 0, index)
        out = pipeline(image=image, mask=np.zeros((4, 6), np.uint8), pose=pose)
        inverted.append(bool(out["image"].max() == 245 or out["image"].min() == 55))
        flipped.append(bool(out["pose"][2] < 0))
    agree = sum(a == b for a, b in zip(inverted, flipped, strict=True))
    assert 60 < sum(flipped) < 140 and 60 < sum(inverted) < 140
    assert 60 < agree < 140  # one shared seed per transform made them agree on every sample


def test_the_centre_zoom_draws_alike_with_or_without_a_pose():
    """The zoom's draw is made for an image without a pose too: the transforms after it draw the same either way."""
    pipeline = A.Compose([PoseAwareCentreZoom(p=1.0), A.GaussNoise(std_range=(0.1, 0.1), p=1.0)])
    image = np.full((6, 8, 3), 100, np.uint8)  # a zoom keeps a uniform image as it is
    noisy = []
    for pose in (np.array([30, -50, 0, 80.0], np.float32), np.full(4, np.nan, np.float32)):
        seed_augmentation(pipeline, 5, 0, 3)
        noisy.append(pipeline(image=image, mask=np.zeros((6, 8), np.uint8), pose=pose)["image"])
    assert not (noisy[0] == image).all()
    np.testing.assert_array_equal(noisy[0], noisy[1])


NO_NETWORK = """
import urllib.request

def refused(*args, **kwargs):
    raise SystemExit("a network request at import: " + str(args[1:2]))

urllib.request.OpenerDirector.open = refused
import dapm_lightning.data.datamodules
print("imported")
"""


def test_importing_the_data_code_asks_no_server_anything():
    """albumentations asked PyPI for a newer version as each process imported it (every DDP rank, fork server and
    spawned worker; a cluster node without internet waits on it)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = {name: value for name, value in os.environ.items() if name != "NO_ALBUMENTATIONS_UPDATE"}
    result = subprocess.run([sys.executable, "-c", NO_NETWORK], capture_output=True, text=True, timeout=120,
                            cwd=Path(__file__).resolve().parents[2], env=env)
    assert result.returncode == 0 and "imported" in result.stdout, result.stderr[-2000:]
