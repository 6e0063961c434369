import json

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from dapm_lightning.tools.predict import DEPTH16_SCALE, DAPMPredictor, ImageFolderDataset, network_size, to_rgb8
from dapm_lightning.training.lightning_cli import run_lightning_cli
from tests.conftest import CONFIGS, QUICKSTART


@pytest.fixture()
def image_folder(tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(0)
    cv2.imwrite(str(folder / "colour.jpg"), rng.integers(0, 255, (45, 70, 3), np.uint8))
    cv2.imwrite(str(folder / "grey.png"), rng.integers(0, 255, (30, 30), np.uint8))
    cv2.imwrite(str(folder / "rgba16.png"), rng.integers(0, 65535, (40, 52, 4), np.uint16))
    return folder


def test_any_input_kind_is_handled_or_refused(image_folder):
    ds = ImageFolderDataset(image_folder, image_width=64)
    for i in range(len(ds)):
        item = ds[i]
        assert item["image"].dtype == torch.uint8 and item["image"].shape[0] == 3
        assert item["image"].shape[2] == 64 and item["image"].shape[1] % 32 == 0
    with pytest.raises(ValueError, match="float32"):
        to_rgb8(np.zeros((4, 4), np.float32), "x.tif")
    with pytest.raises(ValueError, match="channels"):
        to_rgb8(np.zeros((4, 4, 5), np.uint8), "x.tif")
    assert network_size(480, 640, 512) == (384, 512)


def test_cli_predict_writes_depth_files_and_poses(checkpoint, image_folder, tmp_path):
    out = tmp_path / "pred"
    run_lightning_cli(["predict", "--config", str(QUICKSTART), "--config",
                       str(CONFIGS / "predict.yaml"), "--ckpt_path", str(checkpoint),
                       "--data.init_args.folder", str(image_folder), "--data.init_args.image_width", "64",
                       "--trainer.callbacks.output_dir", str(out)])
    for name, shape in (("colour", (45, 70)), ("grey", (30, 30)), ("rgba16", (40, 52))):
        depth = np.load(out / f"{name}_depth.npy")
        assert depth.shape == shape and depth.dtype == np.float32 and (depth > 0).all() and (depth <= 1000).all()
        depth16 = cv2.imread(str(out / f"{name}_depth16.png"), cv2.IMREAD_UNCHANGED)
        assert depth16.dtype == np.uint16
        np.testing.assert_allclose(depth16 / DEPTH16_SCALE, depth, atol=0.5 / DEPTH16_SCALE + 1e-4)
        assert cv2.imread(str(out / f"{name}_depth_color.png")).shape == (*shape, 3)
    poses = json.loads((out / "poses.json").read_text())
    assert [p["name"] for p in poses] == ["colour", "grey", "rgba16"]
    assert set(poses[0]) == {"name", "height_m", "pitch_deg", "roll_deg", "fov_deg"}
    assert (out / "poses.csv").read_text().splitlines()[0] == "name,height_m,pitch_deg,roll_deg,fov_deg"


def test_python_api_numpy_and_pil(checkpoint):
    predictor = DAPMPredictor.from_checkpoint(checkpoint, image_width=64)
    rgb = np.random.default_rng(1).integers(0, 255, (50, 80, 3), np.uint8)
    a = predictor(rgb)
    b = predictor(Image.fromarray(rgb))
    assert a.depth_m.shape == (50, 80) and a.sky.shape == (50, 80)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    assert set(a.pose) == {"height", "pitch", "roll", "fov"}
    # channel order: an RGB array is not read as BGR (swapping R and B changes the input)
    assert not np.array_equal(predictor(rgb[..., ::-1].copy()).depth_m, a.depth_m)
