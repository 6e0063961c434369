"""The second renderer (`bench_foreign`): its geometry agrees with the IGD's, and a checkpoint runs through it."""

import json

import numpy as np
import pytest
import torch

from benchmarks.bench_foreign import camera_rays, main, render, sample_world, view, write_set
from dapm_lightning.data.uapd import UAPDDataset, parse_uapd_filename
from dapm_lightning.geometry.igd import ideal_ground_depth

POSES = [(50.0, -60.0, 0.0, 70.0), (12.0, -95.0, 20.0, 110.0), (90.0, -10.0, -25.0, 40.0), (30.0, 5.0, 10.0, 90.0)]


def empty_world(pose):
    world = sample_world(np.random.default_rng(0), pose)
    world["boxes"], world["trees"] = world["boxes"][:0], world["trees"][:0]
    return world


@pytest.mark.parametrize("pose", POSES)
def test_flat_ground_range_is_the_igd_written_apart(pose):
    """Two implementations of docs/conventions.md: where the ground is seen they agree, the rest is sky in both."""
    _, depth = render(pose, (24, 32), empty_world(pose))
    igd = ideal_ground_depth(torch.tensor([pose], dtype=torch.float64), (24, 32), depth_kind="range")[0, 0].numpy()
    seen = np.isfinite(depth) & (depth < 999.0)
    assert seen.any() and np.allclose(depth[seen], igd[seen], rtol=1e-6)
    assert (igd[~np.isfinite(depth)] == 1000.0).all()


def test_roll_turns_the_horizon_right_end_up():
    rays = camera_rays((50.0, 0.0, 20.0, 90.0), (33, 33))
    # the horizon's right end rises, so on the middle row the right edge looks below it, the left edge above
    assert rays[16, -1, 2] < 0 < rays[16, 0, 2]


def test_objects_only_bring_the_depth_nearer_and_are_drawn_otherwise():
    pose = (40.0, -50.0, 5.0, 80.0)
    world = sample_world(np.random.default_rng(3), pose)
    assert len(world["boxes"]) and len(world["trees"])
    rgb, depth = render(pose, (48, 48), world)
    flat_rgb, flat = render(pose, (48, 48), empty_world(pose) | {k: world[k] for k in ("ground", "ground_bands",
                                                                                         "road_angle", "road_offsets",
                                                                                         "sun", "visibility")})
    nearer = depth < flat - 1e-6
    assert (depth <= flat + 1e-9).all() and nearer.mean() > 0.05
    assert (np.abs(rgb.astype(int) - flat_rgb.astype(int)).sum(-1)[nearer] > 0).mean() > 0.9


def test_written_views_read_back_with_their_pose_and_depth(tmp_path):
    names = write_set(tmp_path, 3, 32, seed=1)
    data = UAPDDataset(tmp_path, "val")
    assert len(data) == 3 and sorted(names) == sorted(p.name for p in (tmp_path / "val" / "rgb").iterdir())
    name, rgb, depth = view(1, 2, 32)
    sample = data[data.names.index(name)]
    meta = parse_uapd_filename(name)
    assert np.allclose(sample["pose"].numpy(), [meta[k] for k in ("height", "pitch", "roll", "fov")], atol=1e-4)
    seen = np.isfinite(depth) & (depth < 900)
    read = sample["depth"][0].numpy()
    assert seen.any() and np.allclose(read[seen], depth[seen], rtol=0.03)  # one grey level: a factor of 1.027
    assert np.abs(sample["image"].permute(1, 2, 0).numpy() * 255 - rgb).max() <= 1


def test_a_checkpoint_is_measured_and_judged(tmp_path, capsys):
    from benchmarks.bench_synth import main as synth

    synth(["transfer", "--held-out", "water", "--train", "6", "--val", "2", "--test", "2", "--size", "32",
           "--batch-size", "2", "--workers", "1", "--out", str(tmp_path / "t"), "--epochs", "1",
           "--test-families", "water", "--", "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0",
           "--data.init_args.num_workers", "0"])
    checkpoint = next((tmp_path / "t").rglob("*.ckpt"))
    report = main(["--checkpoint", str(checkpoint), "--out", str(tmp_path / "f"), "--count", "4", "--size", "32"])
    saved = json.loads((tmp_path / "f" / "foreign.json").read_text())
    assert saved["verdict"] == report["verdict"] and set(saved["verdict"]) == {"beats_igd", "keeps_ground"}
    assert saved["results"]["true_pose"]["d1_ground"] == 1.0
    assert "flat ground of that telemetry" in capsys.readouterr().out


def test_a_missing_checkpoint_is_named_before_anything_is_rendered(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["--checkpoint", str(tmp_path / "none.ckpt"), "--out", str(tmp_path / "f")])
    assert info.value.code == 2 and "none.ckpt: no such checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "f").exists()


def test_a_sloped_ground_is_a_tilted_plane_through_the_nadir_point():
    pose = (40.0, -50.0, 10.0, 80.0)
    world = sample_world(np.random.default_rng(5), pose, slope=12.0)
    assert np.degrees(np.arccos(world["ground_normal"][2])) == pytest.approx(12.0)
    world["boxes"], world["trees"] = world["boxes"][:0], world["trees"][:0]
    tilt = np.radians(12.0)
    world["ground_normal"] = np.array([0.0, np.sin(tilt), np.cos(tilt)])  # sideways: one side rises, one falls
    _, depth = render(pose, (32, 32), world)
    rays = camera_rays(pose, (32, 32))
    seen = np.isfinite(depth)
    points = np.array([0.0, 0.0, 40.0]) + (depth / np.linalg.norm(rays, axis=-1))[..., None] * rays
    normal = world["ground_normal"]
    assert np.abs(points[seen] @ normal).max() < 1e-6 * depth[seen].max()
    igd = ideal_ground_depth(torch.tensor([pose], dtype=torch.float64), (32, 32), depth_kind="range")[0, 0].numpy()
    assert (depth[seen] < igd[seen] * 0.97).any() and (depth[seen] > igd[seen] * 1.03).any()  # uphill and downhill


def test_level_worlds_do_not_depend_on_the_slope_option():
    pose = (40.0, -50.0, 10.0, 80.0)
    level = sample_world(np.random.default_rng(5), pose)
    zero = sample_world(np.random.default_rng(5), pose, slope=0.0)
    assert all(np.array_equal(level[k], zero[k]) for k in level)
    tilted = sample_world(np.random.default_rng(5), pose, slope=8.0)
    assert np.array_equal(level["boxes"], tilted["boxes"]) and not np.array_equal(level["ground_normal"],
                                                                                   tilted["ground_normal"])
