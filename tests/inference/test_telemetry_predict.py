"""Telemetry in prediction: the CSV contract end to end, conditioning, the scale fit, the outputs' sources."""

import csv
import json

import cv2
import numpy as np
import pytest
import torch

from dapm_lightning.cli import main
from dapm_lightning.geometry.igd import IGDSpec, ideal_ground_depth
from dapm_lightning.inference.predictor import DAPMPredictor
from dapm_lightning.inference.prior import apply_pose_prior, as_prior, ground_scale
from dapm_lightning.models.dapm import InferenceOutput
from dapm_lightning.models.prior import PosePrior
from dapm_lightning.training.module import DAPMModule, PriorTraining

NAN = float("nan")


@pytest.fixture()
def flight(tmp_path):
    folder = tmp_path / "flight"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for name, shape in (("a", (40, 60)), ("b", (48, 48)), ("c", (30, 50))):
        cv2.imwrite(str(folder / f"{name}.png"), rng.integers(0, 255, (*shape, 3), np.uint8))
    table = tmp_path / "flight.csv"
    table.write_text("name,height_m,pitch_deg,roll_deg,fov_deg\na.png,45.5,-35,2.5,70\nb,,-60,,\n")
    return folder, table


def test_csv_telemetry_through_the_one_line_command(checkpoint, flight, tmp_path, capsys):
    folder, table = flight
    out = tmp_path / "out"
    main(["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(out), "--device", "cpu",
          "--telemetry", str(table), "--outputs", "depth_npy", "camera", "points"])
    assert capsys.readouterr().out.strip().endswith(f"in {out}/")
    a = json.loads((out / "a_camera.json").read_text())["pose"]
    assert {k: v["value"] for k, v in a.items()} == pytest.approx(
        {"height_m": 45.5, "pitch_deg": -35.0, "roll_deg": 2.5, "fov_deg": 70.0}, abs=1e-4)
    assert {v["source"] for v in a.values()} == {"telemetry"} and a["height_m"]["network"] != 45.5
    b = json.loads((out / "b_camera.json").read_text())["pose"]
    assert b["pitch_deg"]["source"] == "telemetry" and b["height_m"]["source"] == "network"
    assert b["height_m"]["value"] == b["height_m"]["network"]
    k = np.array(json.loads((out / "a_camera.json").read_text())["K"])
    assert k[0, 0] == pytest.approx(60 / (2 * np.tan(np.radians(35.0))))  # the telemetry's FoV, at the input size
    with (out / "poses.csv").open() as handle:
        rows = {row["name"]: row for row in csv.DictReader(handle)}
    assert rows["a"]["height_m"] == "45.5" and rows["a"]["height_m_source"] == "telemetry"
    assert rows["c"]["pitch_deg_source"] == "network" and float(rows["c"]["pitch_deg"]) == float(
        rows["c"]["pitch_deg_network"])
    # depth in metres from the same checkpoint without telemetry differs where the prior entered the IGD
    plain = tmp_path / "plain"
    main(["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(plain), "--device", "cpu",
          "--outputs", "depth_npy", "--no_metadata"])
    assert not np.array_equal(np.load(out / "a_depth.npy"), np.load(plain / "a_depth.npy"))
    np.testing.assert_array_equal(np.load(out / "c_depth.npy"), np.load(plain / "c_depth.npy"))


def test_bad_telemetry_names_the_file_and_line(checkpoint, flight, tmp_path, capsys):
    folder, table = flight
    table.write_text("name,height_m,pitch_deg,roll_deg,fov_deg\na.png,high,-35,2.5,70\n")
    with pytest.raises(SystemExit) as info:
        main(["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(tmp_path / "o"),
              "--telemetry", str(table)])
    err = capsys.readouterr().err
    assert info.value.code == 1 and "flight.csv" in err and "line 2" in err and len(err.splitlines()) <= 4


def test_ground_scale_recovers_a_known_scale_and_falls_back_to_the_heights():
    spec = IGDSpec()
    pose = torch.tensor([[40.0, -30.0, 5.0, 70.0]])
    size = (48, 64)
    igd = spec.depth(pose, size)
    sky = igd >= 1000
    depth = torch.where(sky, torch.full_like(igd, 1000.0), igd * 0.5)  # the right shape at half the scale
    network = pose.clone()
    network[0, 0] = 20.0  # the network's height: half the truth, so its own ground matches its depth
    scale, method = ground_scale(depth, sky, spec.depth(pose, size), spec.depth(network, size),
                                 torch.tensor([2.0]), 1000.0)
    assert method == ["ground"] and float(scale[0]) == pytest.approx(2.0, rel=1e-5)
    nadir_sky = torch.ones_like(sky)  # nothing the model sees as ground: the heights decide
    scale, method = ground_scale(depth, nadir_sky, igd, igd, torch.tensor([1.7]), 1000.0)
    assert method == ["height"] and float(scale[0]) == pytest.approx(1.7)
    scale, method = ground_scale(depth, nadir_sky, igd, igd, torch.tensor([NAN]), 1000.0)
    assert method == ["none"] and float(scale[0]) == 1.0
    outputs = InferenceOutput(depth_m=depth, sky_prob=sky.float(), pose=network)
    fixed, sources, methods = apply_pose_prior(outputs, PosePrior(torch.tensor([[40.0, NAN, NAN, NAN]]),
                                                                  torch.zeros(4)), "scale", spec)
    assert methods == ["ground"] and sources[0] == {"height": "telemetry", "pitch": "network", "roll": "network",
                                                    "fov": "network"}
    torch.testing.assert_close(fixed.depth_m[~sky], igd[~sky], rtol=1e-4, atol=1e-3)
    assert (fixed.depth_m[sky] == 1000.0).all() and float(fixed.pose[0, 0]) == pytest.approx(40.0)


def test_python_api_priors_as_dicts_arrays_and_modes(checkpoint):
    rgb = np.random.default_rng(2).integers(0, 255, (40, 60, 3), np.uint8)
    for mode in ("condition", "scale", "both"):
        predictor = DAPMPredictor.from_checkpoint(checkpoint, image_width=64, telemetry_mode=mode)
        one = predictor(rgb, prior={"height_m": 33.0, "fov": 75.0})
        assert one.pose["height"] == pytest.approx(33.0) and one.pose["fov"] == pytest.approx(75.0)
        assert one.pose_source == {"height": "telemetry", "pitch": "network", "roll": "network", "fov": "telemetry"}
        several = predictor([rgb, rgb], prior=[np.array([33.0, NAN, NAN, 75.0]), None])
        np.testing.assert_allclose(several[0].depth_m, one.depth_m, rtol=1e-5)
        assert set(several[1].pose_source.values()) == {"network"} and several[1].pose == several[1].pose_network
    with pytest.raises(ValueError, match="unknown key"):
        as_prior([{"altitude": 3.0}])
    from dapm_lightning.inference.telemetry import PoseTelemetry

    rows = as_prior([PoseTelemetry(height_m=30.0), torch.tensor([NAN, -50.0, NAN, NAN]), None]).value
    assert rows[0, 0] == 30.0 and rows[1, 1] == -50.0 and rows[2].isnan().all() and rows[0, 1:].isnan().all()
    with pytest.raises(ValueError, match="telemetry_mode"):
        DAPMPredictor.from_checkpoint(checkpoint, telemetry_mode="guess")


def test_training_priors_depend_on_the_image_and_epoch_only():
    settings = PriorTraining(enabled=True, image_fraction=1.0, component_probability=0.5)
    pose = torch.tensor([[50.0, -40.0, 3.0, 70.0]]).repeat(400, 1)
    has_pose = torch.ones(400, dtype=torch.bool)
    has_pose[::2] = False
    names = [f"img{k}" for k in range(400)]
    first = settings.sample(pose, has_pose, names, epoch=0)
    torch.manual_seed(123)  # the global random state plays no part
    split = [settings.sample(pose[k:k + 7], has_pose[k:k + 7], names[k:k + 7], epoch=0) for k in range(0, 400, 7)]
    torch.testing.assert_close(torch.cat([p.value for p in split]), first.value, equal_nan=True)  # any batching
    other_epoch = settings.sample(pose, has_pose, names, epoch=1)
    assert not torch.equal(other_epoch.value.isnan(), first.value.isnan())
    known = first.known
    assert not known[::2].any()  # images without a pose get no prior
    assert 0.4 < known[1::2].float().mean() < 0.6
    noise = (first.value - pose)[:, 0]
    assert noise[noise.isfinite()].std() == pytest.approx(3.0, rel=0.3)
    assert PriorTraining().sample(pose, has_pose, names, 0) is None  # off by default: nothing drawn
    with pytest.raises(ValueError, match="model.prior_training"):
        PriorTraining(image_fraction=2.0)


def test_the_module_trains_with_priors_and_keeps_the_setting_in_checkpoints(tmp_path):
    module = DAPMModule(net={"backbone": "resnet18", "decoder_channels": 16, "head_channels": 8, "igd_channels": 4,
                             "pose_hidden": 16, "depth_bins": (2, 4), "pose_bins": (4,)},
                        prior_training=PriorTraining(enabled=True, image_fraction=1.0, component_probability=1.0))
    pose = torch.tensor([[50.0, -40.0, 3.0, 70.0]] * 2)
    batch = {"image": torch.rand(2, 3, 32, 32), "depth": ideal_ground_depth(pose, (32, 32)), "pose": pose,
             "has_pose": torch.ones(2, dtype=torch.bool), "name": ["x", "y"]}
    loss, out = module._shared_step(batch, "train")
    assert out.pose.used is not None and torch.isfinite(loss)
    assert module.hparams["prior_training"]["enabled"] is True


def test_both_mode_leaves_conditioned_metric_depth_alone_and_depth_only_models_take_a_full_prior():
    spec = IGDSpec()
    used = torch.tensor([[100.0, -40.0, 0.0, 60.0]])
    own = torch.tensor([[60.0, -40.0, 0.0, 60.0]])
    depth = spec.depth(used, (32, 48))  # conditioned: already the ground of the pose used, in metres
    sky = depth >= 1000
    outputs = InferenceOutput(depth_m=depth, sky_prob=sky.float(), pose=used, pose_network=own)
    prior = PosePrior(torch.tensor([[100.0, NAN, NAN, NAN]]), torch.zeros(4))
    fixed, _, methods = apply_pose_prior(outputs, prior, "both", spec)
    assert methods == ["ground"]
    torch.testing.assert_close(fixed.depth_m, depth)  # scale 1, not known / network height
    full = PosePrior(used, torch.zeros(4))
    depth_only, sources, methods = apply_pose_prior(InferenceOutput(depth_m=depth * 0.5, sky_prob=sky.float()),
                                                    full, "scale", spec)
    assert torch.equal(depth_only.pose, used) and set(sources[0].values()) == {"telemetry"}
    assert methods == ["ground"] and torch.allclose(depth_only.depth_m[~sky], depth[~sky], rtol=1e-4)
    partial = PosePrior(torch.tensor([[100.0, NAN, NAN, NAN]]), torch.zeros(4))
    unchanged, _, methods = apply_pose_prior(InferenceOutput(depth_m=depth, sky_prob=sky.float()), partial,
                                             "scale", spec)
    assert unchanged.pose is None and methods == ["none"]


def test_without_ground_in_view_the_scale_is_the_known_over_the_predicted_height():
    spec = IGDSpec()
    own = torch.tensor([[50.0, -90.0, 0.0, 60.0]])  # nadir: ground everywhere, but the depth is a roof's
    depth = spec.depth(own, (32, 48)) * 0.3
    outputs = InferenceOutput(depth_m=depth, sky_prob=torch.zeros_like(depth), pose=own)
    prior = PosePrior(torch.tensor([[100.0, NAN, NAN, NAN]]), torch.zeros(4))
    fixed, _, methods = apply_pose_prior(outputs, prior, "scale", spec)
    assert methods == ["height"] and fixed.pose[0, 0] == 100.0
    torch.testing.assert_close(fixed.depth_m, depth * 2.0)  # 100 m known / 50 m predicted


def test_the_ground_scale_is_the_median_ratio_over_the_ground():
    """The median, not the mean: a few pixels farther off (within the ground band) do not move it."""
    igd = torch.full((1, 1, 10, 10), 100.0)
    depth = torch.full_like(igd, 50.0)
    depth[..., :3, :] = 45.0  # 30 % of the ground at a ratio of 2.22 instead of 2
    scale, methods = ground_scale(depth, torch.zeros_like(igd, dtype=torch.bool), igd, None,
                                  torch.tensor([NAN]), 1000.0)
    assert methods == ["ground"] and scale.tolist() == pytest.approx([2.0])


def test_csv_telemetry_through_the_documented_config_form(checkpoint, flight, tmp_path, monkeypatch):
    folder, table = flight
    monkeypatch.chdir(tmp_path)  # configs/predict.yaml: the package's own
    out = tmp_path / "lightning"
    main(["predict", "--config", "configs/predict.yaml", "--ckpt_path", str(checkpoint),
          "--data.init_args.source", str(folder), "--data.init_args.telemetry", str(table),
          "--data.init_args.num_workers", "0", "--trainer.callbacks.output_dir", str(out),
          "--trainer.callbacks.outputs", "depth_npy,camera"])
    camera = json.loads((out / "a_camera.json").read_text())["pose"]
    assert camera["height_m"] == {"value": pytest.approx(45.5), "source": "telemetry",
                                  "network": camera["height_m"]["network"]}
    one_line = tmp_path / "one_line"
    main(["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(one_line), "--device", "cpu",
          "--telemetry", str(table), "--outputs", "depth_npy"])
    for name in ("a", "b", "c"):  # the two forms give the same metric depth
        np.testing.assert_allclose(np.load(out / f"{name}_depth.npy"), np.load(one_line / f"{name}_depth.npy"),
                                   rtol=1e-5)


def test_scale_mode_fuses_with_the_networks_own_bins_spread():
    spec = IGDSpec()
    network = torch.tensor([[60.0, -40.0, 0.0, 60.0]])
    prior = PosePrior(torch.tensor([[30.0, NAN, NAN, NAN]]), torch.tensor([9.0, 0.0, 0.0, 0.0]))
    sure, unsure = torch.full((1, 4), 0.01), torch.full((1, 4), 0.5)
    height = {}
    for name, spread in (("sure", sure), ("unsure", unsure), ("fixed", None)):
        outputs = InferenceOutput(pose=network, pose_spread=spread)
        fused, _, _ = apply_pose_prior(outputs, prior, "scale", spec)
        height[name] = float(fused.pose[0, 0])
    assert 59.0 < height["sure"] < 60.0 and 30.0 < height["unsure"] < 32.0  # the surer side wins
    assert height["unsure"] < height["fixed"] < height["sure"]
