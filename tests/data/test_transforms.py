import albumentations as A
import numpy as np
import torch

from dapm_lightning.data import UAPDDataset
from dapm_lightning.data.transforms import PoseAwareHorizontalFlip, train_transform
from dapm_lightning.geometry import ideal_ground_depth


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
