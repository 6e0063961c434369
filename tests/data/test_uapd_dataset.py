from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from dapm_lightning.data import DatasetError, UAPDDataset, parse_uapd_filename
from dapm_lightning.data.sample import depth_masks
from dapm_lightning.geometry import grey_to_depth
from tests.conftest import TINY_HW


def test_samples_have_the_documented_schema(tiny_uapd):
    ds = UAPDDataset(tiny_uapd, "train")
    assert len(ds) == 4
    for i in range(len(ds)):
        s = ds[i]
        assert s["image"].shape == (3, *TINY_HW) and s["image"].dtype == torch.float32
        assert 0.0 <= s["image"].min() and s["image"].max() <= 1.0
        assert s["depth"].shape == (1, *TINY_HW)
        assert s["pose"].shape == (4,)
        parsed = parse_uapd_filename(s["name"] + ".png")
        assert s["pose"].tolist() == pytest.approx([parsed[k] for k in ("height", "pitch", "roll", "fov")])
        grey = cv2.imread(str(tiny_uapd / "train" / "depth" / (s["name"] + ".png")), cv2.IMREAD_UNCHANGED)
        np.testing.assert_allclose(s["depth"][0].numpy(), grey_to_depth(grey))
        assert torch.equal(depth_masks(s["depth"])[0][0], torch.from_numpy(grey == 255))


def test_shuffled_name_and_sky(tiny_uapd):
    ds = UAPDDataset(tiny_uapd, "val", image_dtype="uint8")
    above = [ds[i] for i in range(len(ds)) if ds[i]["name"].startswith("idx_3")][0]
    assert above["pose"].tolist() == [30.0, 5.0, 4.0, 90.0]
    assert depth_masks(above["depth"])[0].float().mean() > 0.3  # looking above the horizon
    assert above["image"].dtype == torch.uint8


def _name(root: Path) -> str:
    return sorted((root / "train" / "rgb").iterdir())[0].name


def test_missing_twins_are_all_listed(uapd_copy):
    names = sorted(p.name for p in (uapd_copy / "train" / "rgb").iterdir())
    (uapd_copy / "train" / "depth" / names[0]).unlink()
    (uapd_copy / "train" / "rgb" / names[1]).unlink()
    with pytest.raises(DatasetError) as info:
        UAPDDataset(uapd_copy, "train")
    text = str(info.value)
    assert "no depth twin" in text and names[0] in text
    assert "no rgb twin" in text and names[1] in text
    assert len(info.value.problems) == 2


def test_truncated_png(uapd_copy):
    path = uapd_copy / "train" / "rgb" / _name(uapd_copy)
    path.write_bytes(path.read_bytes()[:-30])
    with pytest.raises(DatasetError, match="truncated") as info:
        UAPDDataset(uapd_copy, "train")
    assert str(path) in str(info.value)


def test_not_a_png(uapd_copy):
    path = uapd_copy / "train" / "depth" / _name(uapd_copy)
    path.write_bytes(b"hello")
    with pytest.raises(DatasetError, match="not a PNG"):
        UAPDDataset(uapd_copy, "train")


@pytest.mark.parametrize("bad", ["rgb", "16bit"])
def test_depth_must_be_single_channel_8bit(uapd_copy, bad):
    path = uapd_copy / "train" / "depth" / _name(uapd_copy)
    grey = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), np.dstack([grey] * 3) if bad == "rgb" else grey.astype(np.uint16) * 257)
    with pytest.raises(DatasetError, match="single-channel 8-bit") as info:
        UAPDDataset(uapd_copy, "train")
    assert str(path) in str(info.value)


def test_size_mismatch(uapd_copy):
    path = uapd_copy / "train" / "rgb" / _name(uapd_copy)
    cv2.imwrite(str(path), np.zeros((TINY_HW[0] + 2, TINY_HW[1], 3), np.uint8))
    with pytest.raises(DatasetError, match="differs from its depth"):
        UAPDDataset(uapd_copy, "train")


def test_bad_name(uapd_copy):
    name = _name(uapd_copy)
    for sub in ("rgb", "depth"):
        src = uapd_copy / "train" / sub / name
        src.rename(src.with_name("broken_name.png"))
    with pytest.raises(DatasetError, match="missing pose key"):
        UAPDDataset(uapd_copy, "train")


def test_missing_and_empty_split(uapd_copy):
    with pytest.raises(DatasetError, match="missing folder"):
        UAPDDataset(uapd_copy, "test")
    for sub in ("rgb", "depth"):
        for p in (uapd_copy / "val" / sub).iterdir():
            p.unlink()
    with pytest.raises(DatasetError, match="no PNG images"):
        UAPDDataset(uapd_copy, "val")


def test_skip_mode_lists_and_keeps_the_rest(uapd_copy):
    name = _name(uapd_copy)
    (uapd_copy / "train" / "depth" / name).unlink()
    with pytest.warns(UserWarning, match=name):
        ds = UAPDDataset(uapd_copy, "train", on_bad_file="skip")
    assert len(ds) == 3 and name not in ds.names
    assert len(ds.skipped) == 1 and name in ds.skipped[0]
