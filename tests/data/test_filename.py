import pytest

from dapm_lightning.data import parse_uapd_filename

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
