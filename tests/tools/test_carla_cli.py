"""collect-carla's command line: every CarlaConfig field settable, settings files, ranges from POSE_RANGES."""

import dataclasses
import json

import pytest
import yaml

from dapm_lightning.cli import main
from dapm_lightning.geometry import POSE_RANGES
from dapm_lightning.tools.carla_collect import CarlaConfig, build_parser, parse_config

CHANGED = {"out": "elsewhere", "host": "carla.local", "port": 2222, "timeout_s": 5.5, "towns": ["Town05"],
           "samples": 12, "reset_every": 3, "seed": 9, "val_fraction": 0.5, "image_size": 64, "vehicles": 1,
           "walkers": 2, "hour": [9.0, 10.0], "x_m": [-1.0, 1.0], "y_m": [-2.0, 2.0], "height_m": [20.0, 30.0],
           "pitch_deg": [-80.0, -70.0], "roll_deg": [-5.0, 5.0], "yaw_deg": [0.0, 90.0], "fov_deg": [60.0, 70.0],
           "lens_k": [0.0, 0.1], "lens_kcube": [0.0, 0.05], "lens_x_size": [0.4, 0.5], "lens_y_size": [0.4, 0.6],
           "pause_s": 0.0}


def test_every_field_is_a_described_flag_and_settable():
    names = [f.name for f in dataclasses.fields(CarlaConfig)]
    assert sorted(names) == sorted(CHANGED)  # this test changes every field
    help_text = build_parser().format_help()
    for name in names:
        assert f"--{name} " in help_text or f"--{name}\n" in help_text, name
    assert "range of the pitch in degrees" in help_text and "``" not in help_text
    args = []
    for name, value in CHANGED.items():
        args += [f"--{name}", json.dumps(value) if isinstance(value, list) else str(value)]
    config = parse_config(args)
    for name, value in CHANGED.items():
        got = getattr(config, name)
        assert (list(got) if isinstance(got, tuple) else got) == value, name


def test_pose_ranges_are_the_uapd_ranges_and_checked():
    defaults = CarlaConfig()
    assert (defaults.height_m, defaults.pitch_deg, defaults.roll_deg, defaults.fov_deg) == tuple(
        POSE_RANGES[k] for k in ("height", "pitch", "roll", "fov"))
    with pytest.raises(ValueError, match="pitch_deg must be a range"):
        CarlaConfig(pitch_deg=(10.0, -100.0))


def test_settings_file_and_print_config(tmp_path, capsys):
    config = tmp_path / "carla.yaml"
    config.write_text(yaml.safe_dump({"samples": 7, "fov_deg": [40, 50], "towns": ["Town03", "Town04"]}))
    parsed = parse_config(["--config", str(config), "--seed", "3"])
    assert (parsed.samples, parsed.fov_deg, parsed.towns, parsed.seed) == (7, (40.0, 50.0), ("Town03", "Town04"), 3)
    with pytest.raises(SystemExit) as info:
        main(["collect-carla", "--config", str(config), "--print_config"])
    assert info.value.code == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["samples"] == 7 and printed["height_m"] == list(POSE_RANGES["height"])
    assert set(printed) == {f.name for f in dataclasses.fields(CarlaConfig)}  # a complete, reusable settings file
