"""The IGD bound: depth capped by the flat ground of the known pose, in every way to predict."""

import json

import cv2
import numpy as np
import pytest
import torch

from dapm_lightning.cli import main
from dapm_lightning.geometry import MAX_DEPTH_M, IGDSpec
from dapm_lightning.geometry.igd import ideal_ground_depth
from dapm_lightning.inference.predictor import DAPMPredictor
from dapm_lightning.inference.prior import bound_by_ground
from dapm_lightning.models.dapm import InferenceOutput
from dapm_lightning.models.prior import IGD_BOUND_MARGIN, PosePrior, PriorSettings

NAN = float("nan")
POSE = (45.5, -35.0, 2.5, 70.0)
SLACK = 1.05  # the cap is applied at the network size; resizing to the input's size moves it a little


def test_bound_caps_below_the_horizon_only_where_the_height_is_known():
    horizon = (45.5, -10.0, 2.5, 70.0)  # the horizon in view
    pose = torch.tensor([horizon, horizon])
    igd = ideal_ground_depth(pose, (24, 40))
    output = InferenceOutput(depth_m=(3 * igd).clamp(max=MAX_DEPTH_M), sky_prob=torch.full_like(igd, 0.9),
                             pose=pose)
    prior = PosePrior(torch.tensor([[45.5, NAN, NAN, NAN], [NAN, -10.0, NAN, NAN]]), torch.zeros(4))
    bounded = bound_by_ground(output, prior, IGDSpec(), 0.1)
    ground = igd[0] < MAX_DEPTH_M / 1.1
    assert ground.any() and (~ground).any()
    torch.testing.assert_close(bounded.depth_m[0][ground], 1.1 * igd[0][ground])
    assert (bounded.sky_prob[0][ground] == 0).all() and (bounded.sky_prob[0][~ground] == 0.9).all()
    torch.testing.assert_close(bounded.depth_m[0][~ground], output.depth_m[0][~ground])  # above the horizon
    torch.testing.assert_close(bounded.depth_m[1], output.depth_m[1])  # no height known: no bound
    assert bound_by_ground(output, None, IGDSpec(), 0.1) is output
    with pytest.raises(ValueError, match="igd_bound"):
        PriorSettings(igd_bound=-0.5)


@pytest.mark.parametrize("depth_kind", ["range", "planar"])
def test_bound_and_scale_fit_measure_against_the_true_ground_with_the_paper_igd(depth_kind):
    """A paper-IGD model (the paper configs) predicts real depth: a correct flat-ground depth is neither capped nor
    rescaled, and its points lie at z = 0 (the paper's formula is 0.62-1.22 times the true ground at this pose)."""
    from dapm_lightning.geometry import depth_to_points, valid_points
    from dapm_lightning.inference.prior import apply_pose_prior, as_prior

    spec = IGDSpec(model="paper", depth_kind=depth_kind)
    pose = torch.tensor([[50.0, -30.0, 20.0, 110.0]], dtype=torch.float64)
    size = (24, 32)
    true = ideal_ground_depth(pose, size, depth_kind=depth_kind)
    approx = ideal_ground_depth(pose, size, model="paper", depth_kind=depth_kind)
    ground = (true < MAX_DEPTH_M) & (approx < MAX_DEPTH_M)
    assert ((approx / true)[ground] < 0.8).any()  # where the paper's formula falls short of the true ground
    output = InferenceOutput(depth_m=true.clone(), sky_prob=(true >= MAX_DEPTH_M).double(), pose=pose)
    prior = as_prior([{"height_m": 50.0}])
    bounded = bound_by_ground(output, prior, spec, IGD_BOUND_MARGIN)
    torch.testing.assert_close(bounded.depth_m, true)  # was cut to 0.68 of it
    points = depth_to_points(bounded.depth_m, pose, depth_kind=depth_kind)[valid_points(bounded.depth_m)]
    assert points[:, 2].abs().max() < 1e-6  # was up to 19 m above the ground
    network = pose * torch.tensor([0.8, 1.0, 1.0, 1.0], dtype=torch.float64)  # 20 % short of the known height
    made = ideal_ground_depth(network, size, depth_kind=depth_kind)
    fitted = apply_pose_prior(InferenceOutput(depth_m=made, sky_prob=(made >= MAX_DEPTH_M).double(), pose=network),
                              prior, "scale", spec)
    assert fitted.scale_from == ["ground"]
    torch.testing.assert_close(fitted.output.depth_m[ground], true[ground])  # was 1 % short


def _capped(depth: np.ndarray, camera: dict, margin: float) -> None:
    pose = torch.tensor([[camera["pose"][k]["value"] for k in ("height_m", "pitch_deg", "roll_deg", "fov_deg")]])
    igd = ideal_ground_depth(pose.double(), depth.shape)[0, 0].numpy()
    inside = igd < 0.8 * MAX_DEPTH_M / (1 + margin)
    assert inside.mean() > 0.3
    assert (depth[inside] <= (1 + margin) * igd[inside] * SLACK).all()


@pytest.fixture()
def flight(tmp_path):
    folder = tmp_path / "flight"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name, shape in (("a", (40, 60)), ("b", (48, 48))):
        cv2.imwrite(str(folder / f"{name}.png"), rng.integers(0, 255, (*shape, 3), np.uint8))
    table = tmp_path / "flight.csv"
    table.write_text("name,height_m,pitch_deg,roll_deg,fov_deg\na.png,45.5,-35,2.5,70\nb.png,5,-60,0,60\n")
    return folder, table


def test_every_way_to_predict_bounds_the_same(absolute_checkpoint, flight, tmp_path, monkeypatch):
    checkpoint = absolute_checkpoint  # absolute depth: free to go past the ground, so the bound has work to do
    folder, table = flight
    one_line, lightning = tmp_path / "one_line", tmp_path / "lightning"
    main(["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(one_line), "--device", "cpu",
          "--telemetry", str(table), "--outputs", "depth_npy", "camera"])  # on by default
    off = tmp_path / "off"
    main(["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(off), "--device", "cpu",
          "--telemetry", str(table), "--outputs", "depth_npy", "--no_igd_bound"])
    monkeypatch.chdir(tmp_path)  # configs/predict.yaml: the package's own
    main(["predict", "--config", "configs/predict.yaml", "--ckpt_path", str(checkpoint),
          "--data.init_args.source", str(folder), "--data.init_args.telemetry", str(table),
          "--data.init_args.num_workers", "0", "--data.init_args.igd_bound", str(IGD_BOUND_MARGIN),
          "--trainer.callbacks.output_dir", str(lightning), "--trainer.callbacks.outputs", "[depth_npy]"])
    api = DAPMPredictor.from_checkpoint(checkpoint, igd_bound=IGD_BOUND_MARGIN)
    free = DAPMPredictor.from_checkpoint(checkpoint, igd_bound=None)
    for name, pose in (("a", POSE), ("b", (5.0, -60.0, 0.0, 60.0))):  # b: 5 m up, the net's depth is far
        depth = np.load(one_line / f"{name}_depth.npy")
        np.testing.assert_allclose(np.load(lightning / f"{name}_depth.npy"), depth, rtol=1e-5)
        rgb = cv2.cvtColor(cv2.imread(str(folder / f"{name}.png")), cv2.COLOR_BGR2RGB)
        np.testing.assert_allclose(api(rgb, prior=np.array(pose)).depth_m, depth, rtol=1e-5)
        _capped(depth, json.loads((one_line / f"{name}_camera.json").read_text()), IGD_BOUND_MARGIN)
    unbounded = free(rgb, prior=np.array(pose)).depth_m
    np.testing.assert_allclose(np.load(off / "b_depth.npy"), unbounded, rtol=1e-5)
    assert (np.load(one_line / "b_depth.npy") <= unbounded + 1e-3).all()
    assert not np.allclose(np.load(one_line / "b_depth.npy"), unbounded)  # the bound acts
    assert np.array_equal(free(rgb).depth_m, api(rgb).depth_m)  # no telemetry: no bound


@pytest.mark.slow
def test_the_onnx_runtime_bounds_too(absolute_checkpoint, tmp_path):
    # the relative-depth model predicts a few % of the ground here: nothing to cap, the check could not fail
    api = DAPMPredictor.from_checkpoint(absolute_checkpoint, igd_bound=0.0)
    onnx = DAPMPredictor(api.module, onnx_path=tmp_path / "m.onnx", igd_bound=0.0)
    free = DAPMPredictor.from_checkpoint(tmp_path / "m.onnx", igd_bound=None)  # the same graph, no bound
    rgb = np.random.default_rng(1).integers(0, 255, (40, 60, 3), np.uint8)
    pose = np.array((5.0, -60.0, 0.0, 60.0))  # 5 m up: the net's depth is far, so the bound has work to do
    result = onnx(rgb, prior=pose)
    _capped(result.depth_m, result.camera_dict(), 0.0)
    unbounded = free(rgb, prior=pose).depth_m
    assert (result.depth_m <= unbounded + 1e-3).all()
    assert not np.allclose(result.depth_m, unbounded)  # the bound acts
