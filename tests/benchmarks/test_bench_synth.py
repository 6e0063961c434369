"""The leave-one-family-out benchmark (`bench_synth transfer`) on tiny settings."""

import json

import pytest
import torch

from benchmarks.bench_synth import main, target_check
from dapm_lightning.tools.evaluate import TELEMETRY_ROWS, bound_rows

TINY = ["transfer", "--held-out", "water", "--train", "6", "--val", "2", "--test", "2", "--size", "32",
        "--batch-size", "2", "--workers", "1"]


def test_transfer_trains_with_the_extra_fit_arguments_and_reports_every_family(tmp_path, capsys):
    out = tmp_path / "transfer"
    main([*TINY, "--out", str(out), "--epochs", "1", "--bound-margins", "0", "0.1", "--",
          "--model.net.pose_stages", "2", "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0",
          "--data.init_args.num_workers", "0"])
    report = json.loads((out / "transfer.json").read_text())
    assert report["held_out"] == ["water"] and "water" not in report["trained_on"]
    assert set(report["results"]) == {"downtown", "suburb", "industrial", "farmland", "forest", "water"}
    expected = {"model", "scale_fixed", "mean_pose", "true_pose", *TELEMETRY_ROWS, *bound_rows((0.0, 0.1))}
    assert {"full/cond+bound", "full/cond+bound@0", "height/cond+bound"} <= expected
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


def test_transfer_refuses_to_hold_out_every_family():
    with pytest.raises(SystemExit):
        main(["transfer", "--held-out", "downtown", "suburb", "industrial", "farmland", "forest", "water"])
