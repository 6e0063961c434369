"""One vocabulary and one grammar: sources named alike in the API and the files, one-line errors for bad settings."""

import cv2
import numpy as np
import pytest

from dapm_lightning.cli import main
from dapm_lightning.inference.predictor import DAPMPredictor
from dapm_lightning.inference.runtime import check_device
from tests.conftest import run_main


def test_the_api_says_network_without_telemetry_and_takes_paths(checkpoint, tmp_path):
    predictor = DAPMPredictor.from_checkpoint(checkpoint)
    rgb = np.random.default_rng(0).integers(0, 255, (30, 40, 3), np.uint8)
    cv2.imwrite(str(tmp_path / "frame.png"), rgb[..., ::-1])
    result = predictor(str(tmp_path / "frame.png"))
    assert result.pose_source == {"height": "network", "pitch": "network", "roll": "network", "fov": "network"}
    assert result.name == "frame" and result.depth_m.shape == (30, 40)
    assert result.pose["height_m"] == result.pose["height"] == result.pose.height  # the files' names work too
    assert list(result.pose.fields()) == ["height_m", "pitch_deg", "roll_deg", "fov_deg"]
    np.testing.assert_array_equal(result.depth_m, predictor(rgb).depth_m)  # the file's pixels, in RGB order
    both = predictor([tmp_path / "frame.png", rgb])
    assert [r.name for r in both] == ["frame", "1"]
    with pytest.raises(FileNotFoundError, match="image 0: .*missing.jpg: no such file"):
        predictor(str(tmp_path / "missing.jpg"))


@pytest.mark.parametrize(("option", "value", "message"), [
    ("--image_width", "0", "argument --image_width: must be at least 1, got 0"),
    ("--batch_size", "-2", "argument --batch_size: must be at least 1, got -2"),
    ("--batch_size", "two", "argument --batch_size: 'two' is not a whole number"),
    ("--contact_sheet", "-1", "argument --contact_sheet: must be 0 or more, got -1"),
    ("--points_max_depth", "-5", "argument --points_max_depth: must be a distance above 0 m, got -5"),
    ("--points_max_depth", "0", "argument --points_max_depth: must be a distance above 0 m, got 0"),
    ("--points_max_depth", "far", "argument --points_max_depth: 'far' is not a number of metres"),
])
def test_sizes_and_counts_are_checked_in_one_line(checkpoint, tmp_path, capsys, option, value, message):
    code, err = run_main(["predict", str(tmp_path), "--ckpt_path", str(checkpoint), option, value], capsys)
    assert code == 2 and message in err.splitlines()[0]


def test_devices_and_precisions_are_checked_before_the_model_loads(checkpoint, tmp_path, capsys, monkeypatch):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((20, 20, 3), np.uint8))

    def no_model(*args, **kwargs):
        raise AssertionError("the model was loaded")

    monkeypatch.setattr(DAPMPredictor, "from_checkpoint", no_model)
    base = ["predict", str(tmp_path / "a.png"), "--ckpt_path", str(checkpoint)]
    code, err = run_main([*base, "--device", "gpu"], capsys)
    assert code == 1 and err.splitlines()[0] == ("error: device 'gpu': unknown (did you mean cuda? use cpu, cuda, "
                                                 "cuda:N or auto)")
    code, err = run_main([*base, "--device", "cpu", "--precision", "16"], capsys)
    assert code == 1 and "precision 16 (float16) does not run on the CPU: use 32 or bf16" in err.splitlines()[0]
    assert check_device("cpu", "bf16") == "cpu"


def test_version_and_mistyped_subcommands(capsys):
    main(["--version"])
    assert capsys.readouterr().out.startswith("dapm-lightning 0.")
    code, err = run_main(["predikt", "x"], capsys)
    assert code == 2 and err.splitlines()[0] == "error: unknown subcommand 'predikt' (did you mean predict?)"
