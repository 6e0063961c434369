import matplotlib
import numpy as np
import pytest
import torch

from dapm_lightning.geometry import ideal_ground_depth
from dapm_lightning.inference.postprocess import make_prediction
from dapm_lightning.tools.render_pointcloud import render, view_box


def test_render_writes_a_figure_without_touching_global_matplotlib_state(tmp_path):
    backend, params = matplotlib.get_backend(), dict(matplotlib.rcParams)
    import matplotlib.pyplot as plt

    figures = plt.get_fignums()
    pose = torch.tensor([40.0, -30.0, 10.0, 80.0])
    prediction = make_prediction("x", (24, 32), ideal_ground_depth(pose[None], (24, 32))[0], None, pose)
    rgb = np.random.default_rng(0).integers(0, 255, (24, 32, 3), np.uint8)
    out = render(rgb, prediction, tmp_path / "view.png", stride=2)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000
    assert matplotlib.get_backend() == backend and dict(matplotlib.rcParams) == params
    assert plt.get_fignums() == figures


def test_view_box_frames_the_scene_not_its_far_outliers():
    rng = np.random.default_rng(0)
    scene = np.c_[rng.uniform(10, 60, (1000, 1)), rng.uniform(-20, 20, (1000, 1)), rng.uniform(0, 15, (1000, 1))]
    far = np.array([[900.0, 400.0, 0.0]] * 5)  # ground points near the horizon
    low, high, span = view_box(np.r_[scene, far], height=30.0)
    assert span == high[0] - low[0] == high[1] - low[1]
    assert 50 < span < 70  # the scene's 50 m extent plus the camera at the origin, not the 900 m outlier
    assert np.all(low <= [0.0, 0.0]) and np.all(high >= [0.0, 0.0])  # the camera is in view
    assert view_box(scene[:3], height=80.0)[2] == 80.0  # a high camera sets the side


def test_render_with_and_without_telemetry_from_a_checkpoint(checkpoint, tmp_path):
    import cv2

    from dapm_lightning.tools.render_pointcloud import render_main

    image = tmp_path / "frame.png"
    cv2.imwrite(str(image), np.random.default_rng(1).integers(0, 255, (48, 64, 3), np.uint8))
    one = render_main(checkpoint, image, tmp_path / "one.png")
    two = render_main(checkpoint, image, tmp_path / "two.png", telemetry=[40.0, -35.0, 0.0, 70.0])
    width = lambda path: cv2.imread(str(path)).shape[1]  # noqa: E731
    assert width(two) > 1.4 * width(one)  # a third panel: the cloud with telemetry


def _render(args, capsys):
    """``python -m dapm_lightning.tools.render_pointcloud ARGS`` expected to exit: ``(status, stderr)``."""
    from dapm_lightning.tools.render_pointcloud import main

    with pytest.raises(SystemExit) as stop:
        main(args)
    return stop.value.code, capsys.readouterr().err


def test_missing_files_and_a_depth_only_model_are_short_messages(checkpoint, tiny_uapd, tmp_path, capsys):
    """A missing --image was called undecodable, a missing --ckpt_path and a DAPM(D) checkpoint ended in tracebacks."""
    import cv2

    from tests.conftest import _one_step_quickstart

    image = tmp_path / "frame.png"
    cv2.imwrite(str(image), np.zeros((48, 64, 3), np.uint8))
    out = ["--out", str(tmp_path / "view.png")]
    code, err = _render(["--ckpt_path", str(checkpoint), "--image", str(tmp_path / "nope.png"), *out], capsys)
    assert code == 1 and f"--image {tmp_path / 'nope.png'}: no such image file" in err, err
    assert "Fix: check the path" in err and "decoded" not in err and "Traceback" not in err
    code, err = _render(["--ckpt_path", str(checkpoint), "--image", str(tmp_path), *out], capsys)
    assert code == 1 and "a folder, not an image file" in err and "Traceback" not in err, err
    code, err = _render(["--ckpt_path", str(tmp_path / "nope.ckpt"), "--image", str(image), *out], capsys)
    assert code == 1 and f"{tmp_path / 'nope.ckpt'}: no such checkpoint file" in err and "Traceback" not in err, err
    code, err = _render(["--ckpt_path", str(checkpoint), "--imag", str(image)], capsys)
    assert code == 2 and "Traceback" not in err, err  # a usage error
    depth_only = _one_step_quickstart(tiny_uapd, tmp_path / "dapm_d", "--model.net.use_pose", "false",
                                      "--model.net.use_igd_feature", "false", "--model.net.depth_parametrization",
                                      "absolute", "--model.net.depth_readout", "head")
    code, err = _render(["--ckpt_path", str(depth_only), "--image", str(image), *out], capsys)
    assert code == 1 and "DAPM(D), depth only: no pose branch" in err and "Traceback" not in err, err
    assert "Fix: pass a full DAPM checkpoint" in err and not (tmp_path / "view.png").exists()
    with pytest.raises(FileNotFoundError):  # --debug: the traceback
        _render(["--ckpt_path", str(tmp_path / "nope.ckpt"), "--image", str(image), "--debug"], capsys)
