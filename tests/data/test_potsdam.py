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


def isprs_download(root, product_tiles=((2, 10), (3, 11)), rgb_tiles=((2, 10), (3, 11))):
    """The unpacked ISPRS layout: 2_Ortho_RGB (ids not padded), 1_DSM_normalisation 8-bit JPEG and 1_DSM float TIFF."""
    rng = np.random.default_rng(0)
    for sub in ("2_Ortho_RGB", "1_DSM_normalisation", "1_DSM"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    for a, b in rgb_tiles:
        cv2.imwrite(str(root / "2_Ortho_RGB" / f"top_potsdam_{a}_{b}_RGB.tif"),
                    rng.integers(0, 255, (64, 96, 3), np.uint8))
    for a, b in product_tiles:
        ndsm = np.zeros((64, 96), np.uint8)
        ndsm[:, 48:] = 128  # half ground (height 0), half grey 128
        cv2.imwrite(str(root / "1_DSM_normalisation" / f"dsm_potsdam_{a:02d}_{b:02d}_normalized_lastools.jpg"), ndsm,
                    [cv2.IMWRITE_JPEG_QUALITY, 100])
        cv2.imwrite(str(root / "1_DSM" / f"dsm_potsdam_{a:02d}_{b:02d}.tif"), np.full((64, 96), 42.5, np.float32))
    return root


def test_isprs_download_without_renaming(tmp_path):
    import torch

    from dapm_lightning.geometry import decode_log_depth

    root = isprs_download(tmp_path / "isprs")
    ndsm = [PotsdamDataset(root, s, crop_size=32) for s in ("train", "val")]
    assert (len(ndsm[0]), len(ndsm[1])) == (10, 2)
    depths = np.stack([s["depth"].numpy() for d in ndsm for s in (d[i] for i in range(len(d)))])
    # grey g read as the authors read a depth PNG: normalised log depth g / 255; ground stays exactly 0 m
    grey128 = decode_log_depth(torch.tensor(128 / 255.0, dtype=torch.float64)).item()
    assert np.isclose(depths.min(), 0.0) and (depths == 0).mean() > 0.3
    assert np.allclose(depths[depths > 0], grey128, rtol=0.05)
    scaled = np.stack([s["depth"].numpy() for s in PotsdamDataset(root, "train", crop_size=32, ndsm_scale=0.1)])
    assert (scaled == 0).mean() > 0.3 and np.allclose(scaled[scaled > 0], 12.8, atol=0.3)  # grey 128 x 0.1 m
    dsm = PotsdamDataset(root, "train", crop_size=32, product="dsm")
    assert np.allclose(dsm[0]["depth"].numpy(), 42.5)


def test_the_split_is_drawn_by_its_seed_and_rounds_the_val_fraction(tiny_potsdam):
    """12 crops: val_fraction 0.3 gives round(3.6) = 4 val crops; train and val part the crops; seeds split apart."""
    splits = {seed: [PotsdamDataset(tiny_potsdam, split, crop_size=32, val_fraction=0.3, seed=seed).names
                     for split in ("train", "val")] for seed in (0, 1)}
    for train, val in splits.values():
        assert (len(train), len(val)) == (8, 4) and not set(train) & set(val)
    assert set(splits[0][1]) != set(splits[1][1])


def test_the_ndsm_grey_level_is_the_authors_normalised_log_depth_and_depths_stop_below_the_limit(tmp_path):
    import torch

    from dapm_lightning.geometry import MAX_DEPTH_M, MIN_DEPTH_M, decode_log_depth

    root = isprs_download(tmp_path / "isprs")  # grey 128 exactly (a JPEG's uniform blocks keep it)
    depths = np.stack([s["depth"].numpy() for s in PotsdamDataset(root, "train", crop_size=32)])
    grey128 = decode_log_depth(torch.tensor(128 / 255.0, dtype=torch.float64)).item()
    np.testing.assert_allclose(depths[depths > 0], grey128, rtol=1e-5)
    for a, b in ((2, 10), (3, 11)):  # a DSM beyond the limit (metres above datum): the limit, not past it
        cv2.imwrite(str(root / "1_DSM" / f"dsm_potsdam_{a:02d}_{b:02d}.tif"), np.full((64, 96), 1500, np.float32))
    dsm = PotsdamDataset(root, "val", crop_size=32, product="dsm")
    assert np.allclose(dsm[0]["depth"].numpy(), MAX_DEPTH_M - MIN_DEPTH_M)


def test_isprs_unpaired_and_missing_product_are_named(tmp_path):
    root = isprs_download(tmp_path / "a", product_tiles=((2, 10),), rgb_tiles=((2, 10), (4, 12)))
    with pytest.raises(DatasetError, match="top_potsdam_4_12_RGB.tif: no height tile"):
        PotsdamDataset(root, "train", crop_size=32)
    root = isprs_download(tmp_path / "b", product_tiles=((2, 10), (5, 13)), rgb_tiles=((2, 10),))
    with pytest.raises(DatasetError, match="dsm_potsdam_05_13_normalized_lastools.jpg: no RGB tile"):
        PotsdamDataset(root, "train", crop_size=32)
    root = isprs_download(tmp_path / "c")
    import shutil
    shutil.rmtree(root / "1_DSM")
    with pytest.raises(DatasetError, match="1_DSM: missing folder"):
        PotsdamDataset(root, "train", crop_size=32, product="dsm")


def test_bad_tiles_are_listed_together_or_skipped_with_one_warning(tmp_path):
    """A tile without its height tile, an undecodable one and a pair of mismatched sizes: raise lists all three with a
    fix that works; skip leaves them out with one warning naming each and cuts the good tile (before: skip still
    stopped at the first unpaired tile, telling the user to skip)."""
    import warnings

    from dapm_lightning.data.potsdam import TILE_FIX
    from dapm_lightning.tools.errors import describe

    root = isprs_download(tmp_path / "isprs", product_tiles=((2, 10), (4, 12), (5, 13)),
                          rgb_tiles=((2, 10), (3, 11), (4, 12), (5, 13)))
    damaged = root / "2_Ortho_RGB" / "top_potsdam_4_12_RGB.tif"
    damaged.write_bytes(b"not a tiff")
    resized = root / "1_DSM_normalisation" / "dsm_potsdam_05_13_normalized_lastools.jpg"
    cv2.imwrite(str(resized), np.zeros((64, 80), np.uint8))
    expected = [f"{root / '2_Ortho_RGB' / 'top_potsdam_3_11_RGB.tif'}: no height tile for id (3, 11)",
                f"{damaged}: cannot be decoded",
                f"{resized}: size (80, 64) differs from top_potsdam_5_13_RGB.tif (96, 64)"]
    with pytest.raises(DatasetError) as info:
        PotsdamDataset(root, "train", crop_size=32)
    assert info.value.problems == expected and info.value.fix == TILE_FIX
    assert "--data.init_args.on_bad_file skip" in describe(info.value)[0]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        train = PotsdamDataset(root, "train", crop_size=32, on_bad_file="skip")
    told = [str(w.message) for w in caught if "bad tile" in str(w.message)]
    assert len(told) == 1 and "leaving out 3 bad tile(s)" in told[0] and all(p in told[0] for p in expected)
    with pytest.warns(UserWarning, match="leaving out 3 bad tile"):  # the crops cut without them, reused
        val = PotsdamDataset(root, "val", crop_size=32, on_bad_file="skip")
    assert len(train) + len(val) == 6 and all(n.startswith("top_potsdam_2_10_RGB") for n in train.names + val.names)
    with pytest.raises(DatasetError) as info:  # raise refuses crops cut so, naming the folder to delete
        PotsdamDataset(root, "train", crop_size=32)
    assert info.value.problems == expected and f"Fix: delete {train.crops} (its crops were cut" in info.value.fix


def test_a_missing_root_is_named_as_such(tmp_path):
    with pytest.raises(DatasetError) as info:
        PotsdamDataset(tmp_path / "nowhere", "train", crop_size=32)
    assert info.value.problems == [f"{tmp_path / 'nowhere'}: no such folder"]
    assert info.value.fix.startswith("Fix: give data.init_args.root the unpacked ISPRS Potsdam download")
    assert not (tmp_path / "nowhere").exists()


def test_tiles_smaller_than_one_crop_are_named_with_the_crop_size_to_use(tmp_path):
    isprs_download(tmp_path)  # 96x64 tiles
    with pytest.raises(DatasetError) as info:
        PotsdamDataset(tmp_path, "train", crop_size=512)
    assert info.value.problems[0].endswith("96x64 pixels, smaller than one 512x512 crop"), info.value.problems
    assert info.value.fix.startswith("Fix: a smaller --data.init_args.crop_size")
