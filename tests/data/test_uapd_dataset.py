from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from dapm_lightning.data import DatasetError, UAPDDataset, parse_uapd_filename
from dapm_lightning.data.errors import BadFileError
from dapm_lightning.data.sample import depth_masks
from dapm_lightning.data.uapd import read_depth_grey
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


def test_evaluation_loaders_keep_the_set_order_at_their_own_batch_size(tiny_uapd):
    """validate and test read their splits whole, in the set's order, in batches of eval_batch_size."""
    from dapm_lightning.data.datamodules import UAPDDataModule

    module = UAPDDataModule(tiny_uapd, test_split="train", batch_size=3, eval_batch_size=2, num_workers=0)
    module.setup("validate")
    assert set(module.datasets) == {"val"}
    module.setup("test")
    for split, loader in (("val", module.val_dataloader()), ("test", module.test_dataloader())):
        batches, count = [batch["name"] for batch in loader], len(module.datasets[split])  # val 3, train 4
        assert [len(names) for names in batches] == [min(2, count - start) for start in range(0, count, 2)]
        assert [name for names in batches for name in names] == [Path(n).stem for n in module.datasets[split].names]


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


@pytest.mark.parametrize("bad", ["16bit", "grey16+rgb"])
def test_depth_must_be_8bit(uapd_copy, bad):
    path = uapd_copy / "train" / "depth" / _name(uapd_copy)
    grey = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.uint16) * 257
    cv2.imwrite(str(path), grey if bad == "16bit" else np.dstack([grey] * 3))
    with pytest.raises(DatasetError, match="depth must be 8-bit grey, RGB or RGBA") as info:
        UAPDDataset(uapd_copy, "train")
    assert str(path) in str(info.value)


@pytest.mark.parametrize("container", ["RGB", "RGBA", "grey+alpha"])
def test_depth_as_rgb_or_rgba_with_equal_channels_loads_as_grey(uapd_copy, container):
    """The authors read depth with OpenCV's grayscale flag: an RGB(A) copy of the grey map is the same map."""
    name = _name(uapd_copy)
    path = uapd_copy / "train" / "depth" / name
    grey = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    before = UAPDDataset(uapd_copy, "train")
    index = before.names.index(name)
    expected = before[index]["depth"]
    alpha = np.full_like(grey, 7)  # any alpha is ignored
    if container == "grey+alpha":
        Image.fromarray(np.dstack([grey, alpha]), "LA").save(path)
    else:
        cv2.imwrite(str(path), np.dstack([grey] * 3 + ([alpha] if container == "RGBA" else [])))
    after = UAPDDataset(uapd_copy, "train")
    assert after.depth_containers[index] == container
    assert set(after.depth_containers) == {"grey", container}
    assert torch.equal(after[index]["depth"], expected)
    np.testing.assert_array_equal(read_depth_grey(path), cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))


def test_depth_with_unequal_channels_names_carlas_raw_encoding(uapd_copy):
    """CARLA's raw 24-bit depth (R + 256 G + 65536 B) must not be read as grey: refused with the conversion."""
    name = _name(uapd_copy)
    path = uapd_copy / "train" / "depth" / name
    grey = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    bgr = np.dstack([grey // 3, grey // 2, grey])
    cv2.imwrite(str(path), bgr)
    dataset = UAPDDataset(uapd_copy, "train")  # the header is fine; the channels are checked when read
    with pytest.raises(ValueError, match="colours differ") as info:
        dataset[dataset.names.index(name)]
    text = str(info.value)
    assert str(path) in text and "CARLA's raw 24-bit depth" in text and "decode_carla_depth" in text
    assert "depth_to_grey" in text and "docs/conventions.md, Depth encoding" in text


def test_depth_whose_third_channel_alone_differs_is_refused(uapd_copy):
    """Every colour channel is compared with the first, the last one too (alpha aside)."""
    name = _name(uapd_copy)
    path = uapd_copy / "train" / "depth" / name
    grey = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), np.dstack([grey, grey, grey // 2]))
    dataset = UAPDDataset(uapd_copy, "train")
    with pytest.raises(ValueError, match="colours differ"):
        dataset[dataset.names.index(name)]


def test_an_rgb_changed_to_another_size_after_the_scan_is_named_when_read(uapd_copy):
    name = _name(uapd_copy)
    dataset = UAPDDataset(uapd_copy, "train")
    path = uapd_copy / "train" / "rgb" / name
    cv2.imwrite(str(path), np.zeros((TINY_HW[0] + 2, TINY_HW[1], 3), np.uint8))
    with pytest.raises(BadFileError, match="differs from its depth") as info:
        dataset[dataset.names.index(name)]
    assert str(path) in str(info.value)


def test_a_grey_rgb_image_is_refused(uapd_copy):
    path = uapd_copy / "train" / "rgb" / _name(uapd_copy)
    cv2.imwrite(str(path), cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))
    with pytest.raises(DatasetError, match="rgb must be 8-bit RGB or RGBA, got 8-bit grey"):
        UAPDDataset(uapd_copy, "train")


def test_a_samples_meta_holds_the_other_tokens_not_the_pose(tiny_uapd):
    dataset = UAPDDataset(tiny_uapd, "train")
    meta = dataset[dataset.names.index(next(n for n in dataset.names if "Town03" in n))]["meta"]
    assert meta == {"yaw": 12.5, "x": -3.0, "tokens": ["Town03", "000777"]}


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


def test_a_set_rendered_with_another_depth_limit_is_refused_naming_the_limit_to_read_it_with(uapd_copy):
    """`synth --max_depth 500` records its limit in synth.json; read with 1000 m every depth would be wrong."""
    (uapd_copy / "synth.json").write_text('{"max_depth": 500.0, "size": 32}')
    with pytest.raises(DatasetError, match="rendered with a depth limit of 500 m") as refused:
        UAPDDataset(uapd_copy, "train")
    assert "--data.init_args.max_depth 500 --model.net.igd.max_depth 500" in refused.value.fix
    depth = UAPDDataset(uapd_copy, "train", max_depth=500.0)[0]["depth"]  # read with its own limit
    assert float(depth.max()) <= 500.0
    (uapd_copy / "synth.json").write_text('{"size": 32}')  # no limit recorded: the given one is used
    assert len(UAPDDataset(uapd_copy, "train")) > 0
    for bad in ('"far"', "0", "Infinity", "true"):  # a record naming no usable limit: refused, not read as 1000 m
        (uapd_copy / "synth.json").write_text(f'{{"max_depth": {bad}}}')
        with pytest.raises(DatasetError, match="max_depth") as refused:
            UAPDDataset(uapd_copy, "train")
        assert str(uapd_copy / "synth.json") in str(refused.value) and "dapm-lightning synth --max_depth" in \
            refused.value.fix
