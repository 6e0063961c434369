"""The leave-one-family-out benchmark (`bench_synth transfer`) on tiny settings."""

import json

import pytest
import torch

from dapm_lightning.tools.bench_synth import TELEMETRY_ROWS, main, median_scaled, scale_errors, target_check

TINY = ["transfer", "--held-out", "water", "--train", "6", "--val", "2", "--test", "2", "--size", "32",
        "--batch-size", "2", "--workers", "1"]


def test_transfer_trains_with_the_extra_fit_arguments_and_reports_every_family(tmp_path, capsys):
    out = tmp_path / "transfer"
    main([*TINY, "--out", str(out), "--epochs", "1", "--", "--model.net.pose_stages", "2",
          "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0", "--data.init_args.num_workers", "0"])
    report = json.loads((out / "transfer.json").read_text())
    assert report["held_out"] == ["water"] and "water" not in report["trained_on"]
    assert set(report["results"]) == {"downtown", "suburb", "industrial", "farmland", "forest", "water"}
    expected = {"model", "scale_fixed", "mean_pose", "true_pose", *TELEMETRY_ROWS}
    assert all(set(rows) == expected for rows in report["results"].values())
    assert len(TELEMETRY_ROWS) == 8 and all(0 <= rows["full/scale"]["d1"] <= 1 for rows in report["results"].values())
    for rows in report["results"].values():  # the true pose's IGD is exact on every ground pixel
        assert rows["true_pose"]["d1"] >= rows["mean_pose"]["d1"] and rows["true_pose"]["height_median"] == 0
        assert {"height_rel", "footprint_rel"} <= set(rows["model"]) and "footprint_rel" in rows["mean_pose"]
    assert "water" in report["target_misses"]
    checkpoint = next(out.rglob("*.ckpt"))
    assert torch.load(checkpoint, weights_only=True)["hyper_parameters"]["net"]["pose_stages"] == 2
    assert "never seen in training" in capsys.readouterr().out


def test_target_check_names_each_miss():
    base = {"height_median": 20.0, "pitch_median": 20.0, "roll_median": 10.0, "fov_median": 20.0}
    good = {"height_median": 9.0, "pitch_median": 10.0, "roll_median": 4.0, "fov_median": 8.0, "d1": 0.6,
            "abs_rel": 0.3}
    assert target_check(good, base) == []
    misses = target_check({**good, "fov_median": 10.5, "d1": 0.4}, base)
    assert len(misses) == 2 and misses[0].startswith("fov_median") and misses[1].startswith("d1")


def test_median_scaled_removes_each_images_scale_only():
    target = torch.rand(2, 1, 8, 8) * 50 + 5
    target[0, 0, 0, :3] = float("inf")  # sky: ignored by the median
    pred = target.clone()
    pred[0] *= 3.0
    pred[1] *= 0.5
    pred[1, 0, 0, 0] = 1.0  # one wrong pixel stays wrong
    scaled = median_scaled(pred, target)
    valid = torch.isfinite(target)
    assert torch.allclose(scaled[0][valid[0]], target[0][valid[0]], rtol=1e-5)
    assert torch.allclose(scaled[1].flatten()[1:], target[1].flatten()[1:], rtol=0.05)
    assert not torch.isclose(scaled[1, 0, 0, 0], target[1, 0, 0, 0], rtol=0.05)


def test_scale_errors_separate_the_footprint_from_the_height():
    true = torch.tensor([[40.0, -60.0, 0.0, 60.0], [80.0, -30.0, 5.0, 90.0]], dtype=torch.float64)
    doubled = true.clone()
    doubled[:, 0] *= 2
    assert scale_errors(doubled, true) == pytest.approx({"height_rel": 1.0, "footprint_rel": 1.0})
    same_footprint = true.clone()  # half the height, a wider FoV: the same ground in the picture
    same_footprint[:, 0] /= 2
    same_footprint[:, 3] = torch.rad2deg(2 * torch.atan(2 * torch.tan(torch.deg2rad(true[:, 3]) / 2)))
    errors = scale_errors(same_footprint, true)
    assert errors["height_rel"] == pytest.approx(1.0) and errors["footprint_rel"] == pytest.approx(0.0, abs=1e-9)


def test_transfer_refuses_to_hold_out_every_family():
    with pytest.raises(SystemExit):
        main(["transfer", "--held-out", "downtown", "suburb", "industrial", "farmland", "forest", "water"])
