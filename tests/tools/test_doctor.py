import json
import re
import shutil
import warnings
from collections import Counter
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from dapm_lightning.cli import main
from dapm_lightning.data import parse_uapd_filename
from dapm_lightning.data.synthetic import FAMILIES, generate_uapd, render_sample
from dapm_lightning.data.uapd import read_depth_grey
from dapm_lightning.geometry import POSE_RANGES
from dapm_lightning.tools.argv import flag_options, list_options, whole_number
from dapm_lightning.tools.doctor import check_sample, doctor_main
from tests.conftest import QUICKSTART
from tests.data.test_bad_files import damage

DEMO = yaml.safe_load(QUICKSTART.read_text())["data"]["init_args"]
"""The quickstart's (``make demo``'s) data settings: the doctor is checked on data rendered the same way."""


def pose_of(name):
    p = parse_uapd_filename(name)
    return np.array([p["height"], p["pitch"], p["roll"], p["fov"]])


def rename(root, split, name, new):
    for sub in ("rgb", "depth"):
        (root / split / sub / name).rename(root / split / sub / new)


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    return generate_uapd(tmp_path_factory.mktemp("doc") / "d", train=16, val=4, size=64, seed=21, workers=1)


@pytest.fixture(scope="module")
def demo_like(tmp_path_factory):
    """The demo's data at a test size: its render seed, families and effects; every family, poses all over."""
    root = generate_uapd(tmp_path_factory.mktemp("demo") / "d", train=60, val=12, size=(48, 64),
                         seed=DEMO.get("render_seed", 0), workers=1, families=DEMO.get("families"),
                         effects=DEMO.get("effects", True), distortion=DEMO.get("distortion", False))
    names = [p.name for p in sorted((root / "train" / "depth").iterdir())]
    assert set(Counter(n.split("_")[2] for n in names)) == set(FAMILIES)
    poses = np.stack([pose_of(n) for n in names])
    for k, key in enumerate(POSE_RANGES):  # a spread over each UAPD range, not a corner of it
        lo, hi = POSE_RANGES[key]
        assert poses[:, k].min() < lo + 0.25 * (hi - lo) and poses[:, k].max() > hi - 0.25 * (hi - lo)
    return root


def clear_ground(root, names):
    """The names among ``names`` whose depth shows plenty of flat ground for their pose (agreement >= 0.5)."""
    return [n for n in names
            if check_sample(read_depth_grey(root / "train" / "depth" / n), pose_of(n), "range")["agreement"] >= 0.5]


def test_the_demos_data_is_clean(demo_like, tmp_path, capsys):
    assert doctor_main([str(demo_like), "--json", str(tmp_path / "r.json")]) == 0
    report = json.loads((tmp_path / "r.json").read_text())
    assert [(r["split"], r["count"], r["flagged"], r["errors"]) for r in report] == [("train", 60, [], []),
                                                                                   ("val", 12, [], [])]
    assert "no problems found" in capsys.readouterr().out


def test_the_samples_once_flagged_on_the_demos_data_are_clean():
    """Six of the demo's own 2200 images were flagged "pitch and roll swapped fits the depth better": a forest
    canopy near the horizon fitted by a steeper pose (whose ground the real ground then lies beyond), or a few
    objects agreeing by chance where the annotated pose sees no ground. Rendered again here, they pass."""
    size = (DEMO["image_size"], DEMO["image_size"])
    for split, index in (("train", 266), ("train", 860), ("train", 1185), ("train", 1856), ("val", 53),
                         ("val", 178)):
        name, _, grey, _ = render_sample(DEMO.get("render_seed", 0), split, index, size, DEMO.get("families"),
                                         effects=False)
        result = check_sample(grey, pose_of(name), "range")
        assert result["flag"] is None, (name, result)


def test_swapped_pitch_and_roll_is_flagged(demo_like, tmp_path):
    root = shutil.copytree(demo_like, tmp_path / "copy")
    names = [p.name for p in sorted((root / "train" / "depth").iterdir())]
    chosen = next(n for n in clear_ground(root, names) if abs(pose_of(n)[1] - pose_of(n)[2]) > 20)
    p = parse_uapd_filename(chosen)
    swapped = chosen.replace(f"_pitch_{p['pitch']:.2f}_", f"_pitch_{p['roll']:.2f}_").replace(
        f"_roll_{p['roll']:.2f}_", f"_roll_{p['pitch']:.2f}_")
    assert swapped != chosen
    rename(root, "train", chosen, swapped)
    assert doctor_main([str(root), "--json", str(tmp_path / "r.json")]) == 1
    report = {r["split"]: r for r in json.loads((tmp_path / "r.json").read_text())}
    assert [f["name"] for f in report["train"]["flagged"]] == [swapped] and not report["val"]["flagged"]
    assert report["train"]["flagged"][0]["reason"].startswith("pitch and roll swapped fits the depth better")


@pytest.mark.parametrize("change", [-30.0, 30.0])
def test_a_wrong_fov_is_flagged(demo_like, tmp_path, change):
    root = shutil.copytree(demo_like, tmp_path / "copy")
    names = [p.name for p in sorted((root / "train" / "depth").iterdir())]
    lo, hi = POSE_RANGES["fov"]
    chosen = next(n for n in clear_ground(root, names)  # an oblique view: the FoV shapes the ground's depth
                  if -60 < pose_of(n)[1] < -20 and lo <= pose_of(n)[3] + change <= hi)
    fov = pose_of(chosen)[3]
    wrong = chosen.replace(f"_fov_{fov:.2f}", f"_fov_{fov + change:.2f}")
    rename(root, "train", chosen, wrong)
    assert doctor_main([str(root), "--json", str(tmp_path / "r.json")]) == 1
    flagged = json.loads((tmp_path / "r.json").read_text())[0]["flagged"]
    assert [f["name"] for f in flagged] == [wrong] and flagged[0]["reason"].startswith("FoV ")
    found = float(flagged[0]["reason"].split()[1])  # "FoV 65 fits the depth better (...)"
    assert abs(found - fov) <= 10 < abs(found - (fov + change))


def test_lens_distortion_is_not_taken_for_a_wrong_fov(tmp_path):
    """UAPD's images carry a random radial lens distortion, recorded in no name: the pinhole IGD then fails at the
    periphery, where another FoV could fit better. The FoV is judged on the image's centre, so none is flagged."""
    root = generate_uapd(tmp_path / "d", train=24, val=0, size=(48, 64), seed=3, workers=1, distortion=True)
    assert all("_lensk_" in p.name for p in (root / "train" / "depth").iterdir())
    assert doctor_main([str(root), "--splits", "[train]"]) == 0


def test_synthetic_data_is_in_full_agreement(synthetic, capsys, tmp_path):
    before = sorted(p.relative_to(synthetic) for p in synthetic.rglob("*"))
    assert doctor_main([str(synthetic)]) == 0
    assert sorted(p.relative_to(synthetic) for p in synthetic.rglob("*")) == before  # nothing written into the data
    assert doctor_main([str(synthetic), "--json", str(tmp_path / "reports" / "doctor.json")]) == 0
    report = json.loads((tmp_path / "reports" / "doctor.json").read_text())
    assert [r["split"] for r in report] == ["train", "val"]
    assert all(not r["flagged"] and not r["errors"] for r in report)
    assert report[0]["count"] == 16 and report[0]["pose"]["roll"]["outside_range"] == 0
    assert "no problems found" in capsys.readouterr().out


def test_negated_roll_names_are_flagged_exactly(synthetic, tmp_path):
    root = shutil.copytree(synthetic, tmp_path / "copy")
    negated = []
    for rgb in sorted((root / "train" / "rgb").iterdir()):
        p = parse_uapd_filename(rgb.name)
        if abs(p["roll"]) > 12 and -75 < p["pitch"] < -5:
            new = rgb.name.replace(f"_roll_{p['roll']:.2f}_", f"_roll_{-p['roll']:.2f}_")
            rename(root, "train", rgb.name, new)
            negated.append(new)
    assert len(negated) >= 3
    (root / "val" / "depth" / sorted((root / "val" / "depth").iterdir())[0].name).unlink()
    assert doctor_main([str(root), "--json", str(tmp_path / "r.json")]) == 1
    report = {r["split"]: r for r in json.loads((tmp_path / "r.json").read_text())}
    assert sorted(f["name"] for f in report["train"]["flagged"]) == sorted(negated)
    assert all("roll negated" in f["reason"] for f in report["train"]["flagged"])
    assert len(report["val"]["errors"]) == 1 and "no depth twin" in report["val"]["errors"][0]


def test_a_root_that_is_not_a_data_set_exits_2(synthetic, tmp_path, capsys):
    assert doctor_main([str(tmp_path)]) == 2  # a folder, but no ROOT/SPLIT/{rgb,depth}
    assert "not a data set" in capsys.readouterr().err
    assert doctor_main([str(synthetic), "--splits", "[test]"]) == 2  # a split asked for that is not there
    assert "no split test" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(["doctor", str(tmp_path / "missing")])
    assert info.value.code == 2 and f"{tmp_path / 'missing'}: no such folder" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("not a data set")
    with pytest.raises(SystemExit) as info:
        main(["doctor", str(tmp_path / "notes.txt")])
    assert info.value.code == 2 and f"{tmp_path / 'notes.txt'}: a file, not a folder" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(["doctor", str(synthetic), "--no_such_option", "1"])  # a usage error
    assert info.value.code == 2


def test_a_report_path_that_cannot_be_written_exits_2_before_the_scan(synthetic, tmp_path, capsys):
    under_a_file = tmp_path / "notes.txt"
    under_a_file.write_text("mine")
    cases = [(tmp_path, "is a folder"), (under_a_file / "r.json", "cannot be written")]
    if Path("/proc/self").is_dir():  # os.access lets root write there; no file can be made (before: after the scan)
        cases.append((Path("/proc/report.json"), "/proc cannot be written"))
    for json_path, message in cases:
        assert doctor_main([str(synthetic), "--json", str(json_path)]) == 2
        captured = capsys.readouterr()
        assert f"--json {json_path}" in captured.err and message in captured.err and captured.out == ""
    assert under_a_file.read_text() == "mine"


def test_cli_doctor_exit_status_and_settings_file(synthetic, tmp_path, capsys):
    config = tmp_path / "doctor.yaml"
    config.write_text(f"depth_kind: planar\nsplits: [val]\njson: {tmp_path / 'planar.json'}\n")
    with pytest.raises(SystemExit) as info:
        main(["doctor", str(synthetic), "--config", str(config), "--print_config"])
    printed = capsys.readouterr().out
    assert info.value.code == 0 and "depth_kind: planar" in printed and "- val" in printed
    with pytest.raises(SystemExit) as info:
        main(["doctor", str(synthetic), "--config", str(config)])
    report = json.loads((tmp_path / "planar.json").read_text())
    assert [r["split"] for r in report] == ["val"] and report[0]["depth_kind"] == "planar"
    with pytest.raises(SystemExit) as info:
        main(["doctor", str(synthetic), "--json", str(tmp_path / "r.json")])
    assert info.value.code == 0
    assert np.isfinite(json.loads((tmp_path / "r.json").read_text())[0]["ground_agreement"]["median"])


def test_synthetic_images_without_synth_json_are_an_unfinished_render(synthetic, tmp_path, capsys):
    """synth writes synth.json last: a render a full disk cut short left images the doctor called "no problems"."""
    root = tmp_path / "d"
    shutil.copytree(synthetic, root)
    assert doctor_main([str(root)]) == 0
    (root / "synth.json").unlink()
    capsys.readouterr()
    assert doctor_main([str(root)]) == 1
    out = capsys.readouterr().out
    assert f"ERROR   {root}: synthetic images (synth_*.png) but no synth.json: a render cut short" in out, out
    assert "Fix: rerun the `dapm-lightning synth` command that rendered it" in out and "1 problem(s)" in out


def test_the_report_names_each_depth_files_container(synthetic, tmp_path, capsys):
    root = tmp_path / "d"
    shutil.copytree(synthetic, root)
    name = sorted(p.name for p in (root / "val" / "depth").iterdir())[0]
    path = root / "val" / "depth" / name
    grey = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), np.dstack([grey] * 3 + [np.full_like(grey, 255)]))  # RGBA, equal colours
    assert doctor_main([str(root), "--splits", "[val]", "--json", str(tmp_path / "r.json")]) == 0
    (report,) = json.loads((tmp_path / "r.json").read_text())
    assert report["depth_container"][name] == "RGBA"
    assert report["depth_containers"] == {"RGBA": 1, "grey": 3}
    assert sum(kind == "grey" for kind in report["depth_container"].values()) == 3
    assert "depth PNGs: 1 RGBA, 3 grey" in capsys.readouterr().out


def test_every_unreadable_file_is_listed_rgb_and_depth_alike(synthetic, tmp_path, capsys):
    """A damaged chunk fails the scan; damage under a valid CRC (a broken writer) fails the decoding the doctor
    does for every RGB and depth file. Each is named, and the exit status is 1."""
    root = shutil.copytree(synthetic, tmp_path / "copy")
    names = sorted(p.name for p in (root / "train" / "rgb").iterdir())
    bad = [root / "train" / "rgb" / names[0], root / "train" / "rgb" / names[1], root / "train" / "depth" / names[2]]
    damage(bad[0])                  # the CRC of its IDAT no longer matches: the scan finds it
    damage(bad[1], fix_crc=True)    # only decoding finds these two
    damage(bad[2], fix_crc=True)
    assert doctor_main([str(root), "--json", str(tmp_path / "r.json")]) == 1
    out = capsys.readouterr().out
    train = json.loads((tmp_path / "r.json").read_text())[0]
    assert train["count"] == 15 and len(train["errors"]) == 3
    assert train["errors"][0].startswith(f"{bad[0]}: damaged PNG (the CRC of its 'IDAT' chunk")
    assert sorted(train["errors"][1:]) == sorted(f"{path}: cannot be decoded as an image" for path in bad[1:])
    for error in train["errors"]:
        assert f"ERROR   {error}" in out
    assert "3 problem(s)" in out and "no problems found" not in out


def test_an_impossible_pose_is_a_problem_not_only_outside_the_range(synthetic, tmp_path, capsys):
    """fov_0, fov_180 and a negative height were counted "outside" the UAPD range, then "no problems found"."""
    root = shutil.copytree(synthetic, tmp_path / "copy")
    names = sorted(p.name for p in (root / "train" / "rgb").iterdir())[:3]
    wrong = [re.sub(r"fov_\d+(\.\d+)?", "fov_0", names[0]), re.sub(r"fov_\d+(\.\d+)?", "fov_180", names[1]),
             re.sub(r"_z_\d+(\.\d+)?", "_z_-50.43", names[2])]
    for name, new in zip(names, wrong):
        assert new != name
        rename(root, "train", name, new)
    assert doctor_main([str(root), "--json", str(tmp_path / "r.json")]) == 1
    out = capsys.readouterr().out
    train = json.loads((tmp_path / "r.json").read_text())[0]
    assert train["count"] == 13 and len(train["errors"]) == 3
    fov = "fov must be within (0, 180) degrees (horizontal field of view)"
    height = "height must be > 0 m (metres above the ground under the camera)"
    why = [f"fov_0: {fov}", f"fov_180: {fov}", f"z_-50.43: {height}"]
    expected = [f"{root / 'train' / 'rgb' / new}: {new}: a pose no camera can have ({reason}); the file name is wrong "
                "(a sign, a unit or a column swapped where it was written)" for new, reason in zip(wrong, why)]
    assert sorted(train["errors"]) == sorted(expected)
    for error in expected:
        assert f"ERROR   {error}" in out
    assert "3 problem(s)" in out and "no problems found" not in out


def test_splits_as_users_type_them(synthetic, capsys):
    """`--splits val`, `--splits train val`, `--splits train,val`, `--splits=val` all work, as `[val]` does."""
    for argv, checked in ((["--splits", "val"], ["val"]), (["--splits", "train", "val"], ["train", "val"]),
                          (["--splits", "train,val"], ["train", "val"]), (["--splits=val"], ["val"]),
                          (["--splits", "[val]"], ["val"]), (["--splits+", "val"], ["val"])):
        assert doctor_main([str(synthetic), *argv]) in (0, 1), argv
        said = capsys.readouterr().out
        assert re.findall(r"^== (\w+):", said, re.MULTILINE) == checked, (argv, said[-500:])


def test_list_options_rewrites_only_plain_lists():
    assert list_options(["R", "--splits", "a", "b", "--json", "x"], ["--splits"]) == ["R", "--splits=[a,b]", "--json",
                                                                                       "x"]
    assert list_options(["--splits=a,b"], ["--splits"]) == ["--splits=[a,b]"]
    assert list_options(["--splits", "[a]", "--other", "c"], ["--splits"]) == ["--splits", "[a]", "--other", "c"]
    assert list_options(["--splits+", "a", "--other", "a,b"], ["--splits"]) == ["--splits+", "a", "--other", "a,b"]


def test_whole_numbers_take_their_least_value_itself():
    import argparse

    assert whole_number(1)("1") == 1 and whole_number(0)("0") == 0
    for least, text, match in ((1, "0", "must be at least 1, got 0"), (2, "1", "must be 2 or more, got 1"),
                               (1, "1.5", "'1.5' is not a whole number")):
        with pytest.raises(argparse.ArgumentTypeError, match=match):
            whole_number(least)(text)


def test_flag_options_take_bare_booleans():
    assert flag_options(["R", "--quiet"], ["--quiet"]) == ["R", "--quiet=true"]
    assert flag_options(["--quiet", "--json", "x"], ["--quiet"]) == ["--quiet=true", "--json", "x"]
    assert flag_options(["--quiet", "false"], ["--quiet"]) == ["--quiet", "false"]
    assert flag_options(["--no_quiet", "--other"], ["--quiet"]) == ["--quiet=false", "--other"]
    assert flag_options(["--no_other"], ["--quiet"]) == ["--no_other"]


def planar_copy(source, target):
    """A copy of a synthetic (range) set with its depth rewritten as planar, as CARLA's depth camera gives it."""
    import torch

    from dapm_lightning.geometry.camera import _plane_coords
    from dapm_lightning.geometry.constants import SKY_GREY
    from dapm_lightning.geometry.depth_codec import depth_to_grey, grey_to_depth

    root = shutil.copytree(source, target)
    for path in root.glob("*/depth/*.png"):
        grey = read_depth_grey(path)
        a, b = _plane_coords(torch.tensor([pose_of(path.name)[3]]), grey.shape)
        planar = grey_to_depth(grey) / np.sqrt(1.0 + a[0].numpy() ** 2 + b[0].numpy() ** 2)
        cv2.imwrite(str(path), np.where(grey == SKY_GREY, grey, depth_to_grey(planar)).astype(np.uint8))
    return root


def test_depth_of_the_other_kind_is_named_with_the_fix(synthetic, tmp_path, capsys):
    """The synthetic range depth rewritten as planar: checked as range, the doctor names the kind and the two
    settings to change; checked as planar, it finds nothing."""
    root = planar_copy(synthetic, tmp_path / "planar")
    assert doctor_main([str(root), "--quiet", "--json", str(tmp_path / "r.json")]) == 1
    out = capsys.readouterr().out
    assert "depth kind: the depth maps agree with the planar IGD" in out and "they look planar" in out
    assert "Set data.init_args.depth_kind and model.net.igd.depth_kind to planar" in out
    report = json.loads((tmp_path / "r.json").read_text())
    assert all(r["ground_agreement"]["median_other_kind"] > 0.5 > 0.25 > r["ground_agreement"]["median"]
               for r in report)
    assert doctor_main([str(root), "--quiet", "--depth_kind", "planar"]) == 0
    assert "depth kind" not in capsys.readouterr().out


def test_a_pixel_is_on_the_flat_ground_within_two_grey_levels_and_never_in_the_sky():
    from dapm_lightning.data.depth_kind import AGREE_LEVELS, on_flat_ground

    igd = np.array([[100, 100, 100, 100, 100, 253, 254, 255]], np.int16)
    depth = np.array([[100, 98, 102, 97, 103, 255, 255, 255]], np.uint8)
    assert AGREE_LEVELS == 2
    np.testing.assert_array_equal(on_flat_ground(depth, igd), [[True, True, True, False, False, False, False, False]])


def test_the_other_kind_is_named_only_when_it_agrees_twice_as_well_and_by_0_3_more():
    from dapm_lightning.data.depth_kind import depth_kind_mismatch

    assert depth_kind_mismatch("range", 0.5, 0.85) is None  # 0.3 more, but not twice
    assert depth_kind_mismatch("range", 0.1, 0.35) is None  # twice, but not 0.3 more
    assert "they look planar" in depth_kind_mismatch("range", 0.3, 0.95)
    assert "they look range" in depth_kind_mismatch("planar", 0.0, 0.3)


def test_depth_maps_are_checked_at_128_pixels_wide_keeping_their_aspect_and_grey_levels():
    from dapm_lightning.data.depth_kind import CHECK_WIDTH, at_check_width

    wide = np.random.default_rng(0).integers(0, 256, (100, 256), dtype=np.uint8)
    narrowed = at_check_width(wide)
    assert CHECK_WIDTH == 128 and narrowed.shape == (50, 128)
    np.testing.assert_array_equal(narrowed, wide[1::2, 1::2])  # the pixel at each new pixel's centre
    small = wide[:60, :100]
    assert at_check_width(small) is small


def test_the_sampled_depth_kind_check_reads_each_file_against_its_own_pose():
    import torch

    from dapm_lightning.data.depth_kind import sampled_mismatch
    from dapm_lightning.geometry import ideal_ground_depth
    from dapm_lightning.geometry.depth_codec import depth_to_grey

    def flat_ground(poses):  # range depth, each of its own pose
        return [depth_to_grey(ideal_ground_depth(torch.from_numpy(pose), (48, 64))[0, 0].numpy(), 1000.0).round()
                .astype(np.uint8) for pose in poses]

    poses = np.array([[40, -30, 0, 70], [60, -50, 10, 90], [25, -70, -15, 60], [80, -85, 5, 100], [50, -40, 20, 80]],
                     np.float64)
    greys = flat_ground(poses)
    assert "they look range" in sampled_mismatch(lambda index: greys[index], poses, "planar")
    assert sampled_mismatch(lambda index: greys[index], poses, "range") is None
    nadir = np.array([[height, -88, 0, 35] for height in (20, 40, 80, 160, 300)], np.float64)  # both kinds agree
    greys = flat_ground(nadir)
    assert sampled_mismatch(lambda index: greys[index], nadir, "range") is None
    assert sampled_mismatch(lambda index: greys[index], nadir, "planar") is None


def test_a_set_without_val_is_a_problem_naming_the_missing_folder_and_the_fix(synthetic, tmp_path, capsys):
    """Checked whole, a train/ without val/ (which fit refuses to start without) is a problem (before: a note, 'no
    problems found', exit 0); with --splits naming train only, a note."""
    root = shutil.copytree(synthetic, tmp_path / "noval")
    shutil.rmtree(root / "val")
    assert doctor_main([str(root), "--quiet", "--json", str(tmp_path / "r.json")]) == 1
    out = capsys.readouterr().out
    assert f"ERROR   {root / 'val'}: missing folder (expected ROOT/val/{{rgb,depth}}/NAME.png" in out, out
    assert "Fix: put a val split in ROOT/val/{rgb,depth}/NAME.png" in out and "1 problem(s)" in out
    assert [r["split"] for r in json.loads((tmp_path / "r.json").read_text())] == ["train", "val"]
    assert doctor_main([str(root), "--quiet", "--splits", "[train]"]) == 0
    assert "has no val/ split: `dapm-lightning fit` validates on ROOT/val" in capsys.readouterr().out


def test_fitting_on_depth_of_the_other_kind_warns_with_the_fix(synthetic, tmp_path):
    """Training on planar depth as range (the default) warns at start-up, naming the folder and the settings; the
    range set itself, and the planar set declared planar, do not."""
    from dapm_lightning.data.datamodules import UAPDDataModule

    root = planar_copy(synthetic, tmp_path / "planar")
    with pytest.warns(UserWarning, match="they look planar. Set data.init_args.depth_kind and model.net.igd"):
        UAPDDataModule(root=str(root), batch_size=2).setup("fit")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        UAPDDataModule(root=str(synthetic), batch_size=2).setup("fit")
        UAPDDataModule(root=str(root), batch_size=2, depth_kind="planar").setup("fit")


def test_a_report_the_disk_cannot_hold_is_not_left_half_written(synthetic, tmp_path):
    """--json on a disk that fills up (here: a file size limit, EFBIG) names the file and the fix, exits 2, and leaves
    the earlier report whole (before: a truncated JSON file and 'OSError: [Errno 27] File too large')."""
    import os
    import resource
    import signal
    import subprocess
    import sys

    report = tmp_path / "report.json"
    report.write_text('{"earlier": true}\n')

    def small_files():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (1000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))

    done = subprocess.run([sys.executable, "-B", "-m", "dapm_lightning", "doctor", str(synthetic), "--json",
                           str(report), "--quiet"], capture_output=True, text=True, preexec_fn=small_files,
                          env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}, timeout=300)
    assert done.returncode == 2, done.stderr
    assert f"error: {report}: cannot be written (File too large)" in done.stderr and "Fix:" in done.stderr
    assert "Traceback" not in done.stderr
    assert json.loads(report.read_text()) == {"earlier": True}
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]


def test_a_set_rendered_with_another_depth_limit_is_checked_with_it(tmp_path, capsys):
    """A 500 m synth set: the doctor reads its limit from synth.json and finds it as healthy as a 1000 m set (before:
    grey read as 1000 m everywhere, agreement 0.003, a false 'pitch and roll swapped', exit 1); with 1000 m forced
    the same set is refused as read with the wrong limit, and a limit that cannot be one is refused with the fix."""
    near = generate_uapd(tmp_path / "s500", train=6, val=3, size=32, max_depth=500, workers=1)
    usual = generate_uapd(tmp_path / "s1000", train=6, val=3, size=32, workers=1)
    assert doctor_main([str(usual), "--quiet", "--json", str(tmp_path / "usual.json")]) == 0
    assert doctor_main([str(near), "--quiet", "--json", str(tmp_path / "near.json")]) == 0
    assert f"grey 255 = 500 m, recorded in {near / 'synth.json'}" in capsys.readouterr().out
    medians = [[r["ground_agreement"]["median"] for r in json.loads((tmp_path / f"{n}.json").read_text())]
               for n in ("usual", "near")]
    assert min(medians[1]) > 0.5 and np.allclose(medians[0], medians[1], atol=0.15)
    assert all(r["max_depth"] == 500 for r in json.loads((tmp_path / "near.json").read_text()))
    assert doctor_main([str(near), "--quiet", "--max_depth", "1000"]) == 1
    out = capsys.readouterr().out
    assert "grey 255 = 1000 m, given by --max_depth" in out  # the set's own record contradicts it: named
    assert "rendered with a depth limit of 500 m (grey 255), but it would be read with 1000 m" in out
    for bad in ("0", ".nan", ".inf"):
        assert doctor_main([str(near), "--quiet", "--max_depth", bad]) == 2
        err = capsys.readouterr().err
        assert "max_depth: " in err and "but a depth limit must be a number of metres above 1" in err
        assert "Fix: --max_depth 1000" in err
    for bad in ('"far"', "0"):  # the set's record naming no usable limit: refused as the dataset refuses it
        (near / "synth.json").write_text(f'{{"max_depth": {bad}}}')
        assert doctor_main([str(near), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert f"{near / 'synth.json'}: max_depth" in err and "or remove max_depth from it" in err, err
        assert ".." not in err
    (near / "synth.json").write_text('{"size": 32}')  # the fix it gives works: the limit is then --max_depth's
    assert doctor_main([str(near), "--quiet", "--max_depth", "500"]) == 0


def test_a_potsdam_root_has_its_tiles_checked(tmp_path, capsys):
    """A healthy Potsdam root, crops cut, passes (before: 'crops_32_ndsm_log/depth: missing folder', exit 1); a tile
    without its height tile is named."""
    from dapm_lightning.data import PotsdamDataset
    from tests.data.test_potsdam import isprs_download

    root = isprs_download(tmp_path / "isprs")
    PotsdamDataset(root, "train", crop_size=32)
    assert doctor_main([str(root), "--json", str(tmp_path / "r.json")]) == 0
    out = capsys.readouterr().out
    assert "Potsdam tiles (ISPRS download)" in out and "missing folder" not in out and "no problems found" in out
    assert [(r["product"], r["pairs"], r["errors"]) for r in json.loads((tmp_path / "r.json").read_text())] == [
        ("ndsm", 2, []), ("dsm", 2, [])]
    (root / "1_DSM_normalisation" / "dsm_potsdam_03_11_normalized_lastools.jpg").unlink()
    assert doctor_main([str(root)]) == 1
    assert f"ERROR   {root / '2_Ortho_RGB' / 'top_potsdam_3_11_RGB.tif'}: no height tile" in capsys.readouterr().out
