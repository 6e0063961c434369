import cv2
import numpy as np
import pytest

from dapm_lightning.data import DatasetError, PotsdamDataset


def test_crops_split_and_schema(tiny_potsdam):
    train = PotsdamDataset(tiny_potsdam, "train", crop_size=32)
    val = PotsdamDataset(tiny_potsdam, "val", crop_size=32)
    assert (len(train), len(val)) == (10, 2)
    assert PotsdamDataset(tiny_potsdam, "val", crop_size=32, seed=0).names == val.names
    sample = val[0]
    assert sample["image"].shape == (3, 32, 32) and sample["depth"].shape == (1, 32, 32)
    assert not sample["has_pose"] and np.isnan(sample["pose"].numpy()).all()


def test_unpaired_tile_and_nan_heights_are_named(tiny_potsdam, tmp_path):
    import shutil
    root = tmp_path / "p"
    shutil.copytree(tiny_potsdam, root, ignore=shutil.ignore_patterns("crops_*"))
    cv2.imwrite(str(root / "rgb" / "top_potsdam_7_7_RGB.tif"), np.zeros((32, 32, 3), np.uint8))
    with pytest.raises(DatasetError, match="top_potsdam_7_7_RGB.tif: no height tile"):
        PotsdamDataset(root, "train", crop_size=32)
    (root / "rgb" / "top_potsdam_7_7_RGB.tif").unlink()
    height_path = next((root / "height").iterdir())
    height = cv2.imread(str(height_path), cv2.IMREAD_UNCHANGED)
    height[:] = np.nan
    cv2.imwrite(str(height_path), height)
    ds = PotsdamDataset(root, "train", crop_size=32)
    with pytest.raises(ValueError, match="non-finite height"):
        for i in range(len(ds)):
            ds[i]
