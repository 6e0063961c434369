import re

import pytest

from dapm_lightning.data import format_uapd_filename, parse_uapd_filename
from dapm_lightning.data.synthetic import FAMILIES

EXAMPLE = "Town03_000123_x_-12.5_y_40.1_z_57.20_pitch_-63.40_roll_12.75_yaw_33.0_fov_88.10.png"


def test_design_example():
    p = parse_uapd_filename(EXAMPLE)
    assert (p["height"], p["pitch"], p["roll"], p["fov"]) == (57.2, -63.4, 12.75, 88.1)
    assert (p["x"], p["y"], p["yaw"]) == (-12.5, 40.1, 33.0)
    assert p["tokens"] == ["Town03", "000123"]


def test_any_order_integers_directory_and_extension():
    p = parse_uapd_filename("some/dir/fov_90_roll_-5_pitch_-90_z_10_extra.jpg")
    assert (p["height"], p["pitch"], p["roll"], p["fov"]) == (10.0, -90.0, -5.0, 90.0)
    assert p["tokens"] == ["extra"]


def test_values_out_of_range_and_unrounded_are_kept():
    p = parse_uapd_filename("z_150.123456_pitch_45_roll_-90_fov_179.5.png")
    assert p["height"] == 150.123456 and p["pitch"] == 45.0 and p["roll"] == -90.0


def test_repeated_key_with_same_value_is_fine():
    assert parse_uapd_filename("z_10_z_10.0_pitch_1_roll_2_fov_3")["height"] == 10.0


@pytest.mark.parametrize("name, message", [
    ("x_1_pitch_-10_roll_0_fov_60.png", "missing pose key"),
    ("z_abc_pitch_-10_roll_0_fov_60.png", "not a number"),
    ("z_nan_pitch_-10_roll_0_fov_60.png", "not a number"),
    ("z_10_pitch_-10_roll_0_fov_60_z_11.png", "twice"),
    ("z_10_pitch_-10_roll_0_fov.png", "not a number"),
])
def test_errors_name_the_file(name, message):
    with pytest.raises(ValueError, match=message) as info:
        parse_uapd_filename(name)
    assert name in str(info.value)


@pytest.mark.parametrize("name, shown", [
    ("a_z_67.33_pitch_-70_roll_-27_fov_0.png", "fov_0: fov must be within (0, 180) degrees"),
    ("a_z_67.33_pitch_-70_roll_-27_fov_180.png", "fov_180: fov must be within (0, 180) degrees"),
    ("a_z_67.33_pitch_-70_roll_-27_fov_-60.png", "fov_-60: fov must be within (0, 180) degrees"),
    ("a_z_-50.43_pitch_-53_roll_12.57_fov_109.54.png", "z_-50.43: height must be > 0 m"),
    ("a_z_0_pitch_-53_roll_12.57_fov_109.54.png", "z_0: height must be > 0 m"),
    ("a_z_30_pitch_-270_roll_0_fov_60.png", "pitch_-270: pitch must be within [-180, 180] degrees"),
    ("a_z_30_pitch_-60_roll_181_fov_60.png", "roll_181: roll must be within [-180, 180] degrees"),
])
def test_a_pose_no_camera_can_have_is_refused_naming_the_file(name, shown):
    """Physically impossible values used to load and train (the IGD clamps a negative height to 0)."""
    with pytest.raises(ValueError) as info:
        parse_uapd_filename(name)
    assert str(info.value).startswith(f"{name}: a pose no camera can have ({shown}"), info.value
    assert "the file name is wrong" in str(info.value)


def test_the_limits_of_a_possible_pose_are_kept():
    p = parse_uapd_filename("z_0.01_pitch_-180_roll_180_fov_179.9.png")
    assert (p["height"], p["pitch"], p["roll"], p["fov"]) == (0.01, -180.0, 180.0, 179.9)
    assert parse_uapd_filename("z_5_pitch_180_roll_-180_fov_0.5.png")["fov"] == 0.5


@pytest.mark.parametrize("tokens, pose, extra", [
    (["Town03", "000123"], (57.2, -63.4, 12.75, 88.1), None),
    (["synth", "000007", "forest"], (10.004, -99.996, -30.0, 120.0), {"lensk": -0.1234, "lenskcube": 0.05}),
    ([], (0.5, 5.0, 0.0, 30.0), None),
])
def test_format_reads_back(tokens, pose, extra):
    name = format_uapd_filename(tokens, pose, x=-12.5, y=40.125, yaw=33.0, extra=extra)
    parsed = parse_uapd_filename(name)
    assert [parsed[k] for k in ("height", "pitch", "roll", "fov")] == [round(v, 2) for v in pose]
    assert (parsed["x"], parsed["y"], parsed["yaw"]) == (-12.5, 40.12, 33.0)
    for key, value in (extra or {}).items():
        assert parsed[key] == round(value, 3)
    assert name.endswith(".png") and name.startswith("_".join(tokens))


@pytest.mark.parametrize("tokens, extra", [(["a_b"], None), (["pitch"], None), ([""], None),
                                           ([], {"fov": 1.0}), ([], {"k2": 1.0})])
def test_format_refuses_what_would_not_read_back(tokens, extra):
    with pytest.raises(ValueError, match="read back|must be letters"):
        format_uapd_filename(tokens, (50.0, -45.0, 0.0, 90.0), extra=extra)


def test_the_names_written_have_the_pose_keys_in_the_published_uapd_order():
    """The published set's names carry ``_z_H_pitch_P_yaw_Y_roll_R_fov_F`` (with decimals), which the authors'
    evaluation matches as one pattern; before, ``roll`` came before ``yaw`` and that evaluation found no pose."""
    published = re.compile(r"_z_(-?\d+\.\d+)_pitch_(-?\d+\.\d+)_yaw_(-?\d+\.\d+)_roll_(-?\d+\.\d+)_fov_(\d+\.\d+)")
    name = format_uapd_filename(["Town03", "000123"], (57.2, -63.4, -12.75, 88.1), x=-1.0, y=2.0, yaw=-33.0,
                                extra={"lensk": 0.1})
    assert published.search(name).groups() == ("57.20", "-63.40", "-33.00", "-12.75", "88.10")


def test_both_writers_use_the_one_format():
    from dapm_lightning.data.synthetic import render_sample
    from dapm_lightning.tools.carla_collect import CarlaConfig, sample_params

    name = render_sample(0, "train", 3, (16, 16))[0]
    assert parse_uapd_filename(name)["tokens"][-1] in FAMILIES
    params = sample_params(CarlaConfig(samples=1), 0)
    assert params.name() == format_uapd_filename([params.town, "000000"], (params.height, params.pitch, params.roll,
                                                 params.fov), x=params.x, y=params.y, yaw=params.yaw)
