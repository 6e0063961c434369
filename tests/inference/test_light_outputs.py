"""Light, useful defaults: pictures, sky, camera and the tables; raw depth and the PLY on request."""

import cv2
import numpy as np
import pytest

from dapm_lightning.cli import main
from dapm_lightning.inference.postprocess import Prediction
from dapm_lightning.inference.run_folder import PER_IMAGE_FILES
from dapm_lightning.inference.writers import OUTPUT_KINDS, check_outputs
from tests.conftest import run_main
from tests.inference.test_predict import read_ply_independently


@pytest.fixture()
def photo(tmp_path):
    folder = tmp_path / "photos"
    folder.mkdir()
    rng = np.random.default_rng(3)
    cv2.imwrite(str(folder / "DJI_0001.JPG"), rng.integers(0, 255, (300, 400, 3), np.uint8))
    return folder


def test_outputs_by_name_comma_lists_and_all():
    assert check_outputs(None) == ["depth_color", "sky", "camera"]
    assert check_outputs(["depth_npy,camera", "sky", "camera"]) == ["depth_npy", "camera", "sky"]
    assert check_outputs("all") == list(OUTPUT_KINDS) and check_outputs(["all", "npz"]) == list(OUTPUT_KINDS)
    with pytest.raises(ValueError, match=r"unknown output 'depth_np' \(did you mean depth_npy\?\); choose from "):
        check_outputs("camera,depth_np")
    # each kind's file name is known to the run folder: an earlier run's file of it is removed, a scan leaves it out
    assert list(PER_IMAGE_FILES) == list(OUTPUT_KINDS)


def test_the_default_run_is_light_and_all_is_everything(checkpoint, photo, tmp_path, capsys):
    out = tmp_path / "default"
    main(["predict", str(photo), "--ckpt_path", str(checkpoint), "--out", str(out), "--device", "cpu"])
    assert capsys.readouterr().out.strip().endswith(
        f"depth_color, sky, camera per image; poses.csv, contact_sheet.png in {out}/")
    assert sorted(p.name for p in out.iterdir()) == [".dapm_predict", "DJI_0001_camera.json",
                                                     "DJI_0001_depth_color.png", "DJI_0001_sky.png",
                                                     "contact_sheet.png", "poses.csv", "poses.json"]
    assert sum(p.stat().st_size for p in out.iterdir()) < 1_000_000
    every = tmp_path / "all"
    main(["predict", str(photo), "--ckpt_path", str(checkpoint), "--out", str(every), "--device", "cpu",
          "--outputs", "all"])
    assert sorted(p.name for p in every.glob("DJI_0001*")) == sorted(name.format("DJI_0001")
                                                                     for name in PER_IMAGE_FILES.values())
    chosen = tmp_path / "chosen"
    main(["predict", str(photo), "--ckpt_path", str(checkpoint), "--out", str(chosen), "--device", "cpu",
          "--outputs", "depth_npy,points", "--contact_sheet", "0"])
    assert sorted(p.name for p in chosen.iterdir()) == [".dapm_predict", "DJI_0001_depth.npy",
                                                        "DJI_0001_points.ply", "poses.csv", "poses.json"]
    # the cloud at about the network's resolution, not one point per photo pixel
    shape = np.load(chosen / "DJI_0001_depth.npy").shape
    points = len(read_ply_independently(chosen / "DJI_0001_points.ply"))
    assert shape == (300, 400) and points <= 2 * 64 * 64
    dense = tmp_path / "dense"
    main(["predict", str(photo), "--ckpt_path", str(checkpoint), "--out", str(dense), "--device", "cpu",
          "--outputs", "points", "--points_stride", "1", "--points_max_depth", "1e6"])
    assert len(read_ply_independently(dense / "DJI_0001_points.ply")) > 4 * points
    code, err = run_main(["predict", str(photo), "--ckpt_path", str(checkpoint), "--outputs", "depth,camera"], capsys)
    assert code == 2 and "unknown output 'depth'" in err


@pytest.mark.parametrize("limit", [0.0, -5.0, float("nan")])
def test_a_point_limit_that_would_drop_every_point_is_refused(tmp_path, limit):
    from dapm_lightning.inference.writers import PredictionFiles

    with pytest.raises(ValueError, match="points_max_depth must be a distance above 0 m"):
        PredictionFiles(tmp_path / "out", ["points"], points_max_depth=limit)
    assert not (tmp_path / "out").exists()  # refused before the run folder is made


def test_auto_stride_is_about_the_network_resolution():
    prediction = Prediction(None, None, None, size=(3000, 4000), network_size=(55, 74))
    assert prediction.auto_stride() == 54
    assert Prediction(None, None, None, size=(30, 40), network_size=(48, 64)).auto_stride() == 1
    assert Prediction(None, None, None, size=(30, 40)).auto_stride() == 1


@pytest.mark.parametrize("kind", ["range", "planar"])
def test_strided_points_are_exactly_those_of_the_full_grid(kind):
    import torch

    from dapm_lightning.geometry import depth_to_points

    depth = 20 + 80 * torch.rand(2, 47, 65, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    pose = torch.tensor([[40.0, -35.0, 4.0, 70.0], [12.0, -80.0, -10.0, 95.0]], dtype=torch.float64)
    full = depth_to_points(depth, pose, depth_kind=kind)
    for stride in (1, 3, 54):
        assert torch.equal(depth_to_points(depth, pose, depth_kind=kind, stride=stride), full[:, ::stride, ::stride])
