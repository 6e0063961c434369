"""The synthetic benchmarks on tiny settings: the generator's speed, leave-one-family-out (`transfer`, `grid`)."""

import argparse
import json

import pytest
import torch

from benchmarks import bench_synth
from benchmarks.bench_synth import GRID_ROWS, grid_summary, main, target_check
from dapm_lightning.tools.evaluate import TELEMETRY_IGD_ROW, TELEMETRY_ROWS, bound_rows

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
    expected = {"model", "scale_fixed", "mean_pose", "true_pose", TELEMETRY_IGD_ROW, *TELEMETRY_ROWS,
                *bound_rows((0.0, 0.1))}
    assert {"full/cond+bound", "full/cond+bound@0", "height/cond+bound"} <= expected
    assert all(set(rows) == expected for rows in report["results"].values())
    assert len(TELEMETRY_ROWS) == 8 and all(0 <= rows["full/scale"]["d1"] <= 1 for rows in report["results"].values())
    for rows in report["results"].values():  # the true pose's IGD is exact on every ground pixel
        assert rows["true_pose"]["d1"] >= rows["mean_pose"]["d1"] and rows["true_pose"]["height_median"] == 0
        assert {"height_rel", "footprint_rel"} <= set(rows["model"]) and "footprint_rel" in rows["mean_pose"]
        assert rows["true_pose"]["d1_ground"] == 1.0 and 0 < rows["true_pose"]["ground_share"] <= 1
        assert {"d1_ground", "d1_objects"} <= set(rows["full/cond+bound"])
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


def test_grid_holds_out_each_family_in_turn_and_reports_mean_and_worst(tmp_path, capsys):
    out = tmp_path / "grid"
    main(["grid", "--families", "water", "farmland", "--seeds", "0", "--train", "6", "--val", "2", "--test", "2",
          "--size", "32", "--batch-size", "2", "--workers", "1", "--epochs", "1", "--out", str(out),
          "--teacher-forcing", "0", "0", "--", "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0",
          "--data.init_args.num_workers", "0"])
    report = json.loads((out / "grid.json").read_text())
    assert set(report["results"]) == {"water", "farmland"} and set(report["results"]["water"]) == {"0"}
    assert (out / "water_seed0" / "transfer.json").exists() and (out / "farmland_seed0" / "transfer.json").exists()
    held_out = json.loads((out / "water_seed0" / "transfer.json").read_text())
    assert held_out["held_out"] == ["water"] and list(held_out["results"]) == ["water"]  # tested on it alone
    config = (out / "water_seed0" / "transfer_config.yaml").read_text()
    assert "end_share: 0.0" in config and "seed_everything: 0" in config
    full = report["summary"]["full/cond+bound"]
    assert full["d1"] == pytest.approx((full["families"]["water"]["d1"] + full["families"]["farmland"]["d1"]) / 2)
    assert set(report["targets_met"]) == {"full/cond+bound", "height/cond+bound"}
    table = (out / "grid.md").read_text()
    assert table.startswith("| row | water | farmland | mean | worst |") and "| full |" in table
    assert "leave-one-family-out grid" in capsys.readouterr().out


def test_grid_summary_averages_seeds_then_families_and_names_the_worst():
    def rows(d1: float, abs_rel: float) -> dict[str, dict[str, float]]:
        return {"full/cond+bound": {"d1": d1, "abs_rel": abs_rel}}

    summary = grid_summary({"forest": {0: rows(0.6, 0.3), 1: rows(0.8, 0.1)}, "water": {0: rows(0.9, 0.1)}})
    full = summary["full/cond+bound"]
    assert full["families"]["forest"] == pytest.approx({"d1": 0.7, "abs_rel": 0.2})
    assert full["d1"] == pytest.approx(0.8) and full["abs_rel"] == pytest.approx(0.15) and full["worst"] == "forest"
    assert set(summary) == {"full/cond+bound"} and "full/cond+bound" in dict(GRID_ROWS)


def test_speed_row_separates_the_workers_start_from_the_steady_rate(monkeypatch):
    # a run with workers: 3 s to start them, then 10 images/s
    monkeypatch.setattr(bench_synth, "render_seconds",
                        lambda size, counts, workers, rounds=2: [3.0 + c / 10 for c in counts])
    row = bench_synth.speed_row(64, 50, workers=2)
    assert row["images_per_s"] == pytest.approx(50 / 8) and row["steady_images_per_s"] == pytest.approx(10)
    assert row["start_s"] == pytest.approx(3.0)
    one = bench_synth.speed_row(64, 50, workers=1)  # in the calling process: nothing to start
    assert one["steady_images_per_s"] == one["images_per_s"] == pytest.approx(50 / 8) and one["start_s"] == 0
    # noise: the longer run no slower than the short one: no rate is made up
    monkeypatch.setattr(bench_synth, "render_seconds", lambda size, counts, workers, rounds=2: [4.0 for _ in counts])
    row = bench_synth.speed_row(64, 50, workers=2)
    assert row["steady_images_per_s"] is None and row["start_s"] is None


def test_speed_prints_a_row_per_size_and_worker_count(capsys):
    rows = bench_synth.speed(argparse.Namespace(sizes=[16], images=4))["speed"]
    assert [(r["size"], r["workers"], r["images"]) for r in rows] == [(16, 1, 4), (16, 2, 4)]
    assert all(r["images_per_s"] > 0 for r in rows)
    printed = capsys.readouterr().out
    assert "steady" in printed and "start s" in printed


@pytest.mark.parametrize("command", ["transfer", "grid"])
def test_the_transfer_benchmarks_default_to_the_quickstart_s_data_and_batch(command, monkeypatch, tmp_path):
    """Without --train/--val/--size/--batch-size, `transfer` and `grid` train on what `make demo` trains on, so
    their figures are the quickstart's whatever its config says (read from a config with other values, so defaults
    written out as today's numbers fail)."""
    import yaml

    config = yaml.safe_load(bench_synth.QUICKSTART_CONFIG.read_text())
    config["data"]["init_args"].update(train_size=1234, val_size=56, image_size=48, batch_size=12)
    other = tmp_path / "quickstart.yaml"
    other.write_text(yaml.safe_dump(config))
    monkeypatch.setattr(bench_synth, "QUICKSTART_CONFIG", other)
    seen = {}
    monkeypatch.setattr(bench_synth, command, lambda args: seen.update(vars(args)))
    main([command])
    assert (seen["train"], seen["val"], seen["size"], seen["batch_size"]) == (1234, 56, 48, 12)
    assert seen["epochs"] is None  # the quickstart's trainer.max_epochs (_quickstart_config keeps it)
