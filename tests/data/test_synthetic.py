import hashlib
import json
import subprocess
import sys
from collections import Counter

import numpy as np
import pytest
import torch

from dapm_lightning.data import UAPDDataset, parse_uapd_filename
from dapm_lightning.data.synthetic import (
    FAMILIES,
    GROUND,
    PERSON,
    SKY,
    VEHICLE,
    WATER,
    SynthFolderError,
    generate_uapd,
    image_seed,
    is_cache,
    is_current,
    normalize_families,
    render_scene,
    sample_pose,
    sample_scene,
    shard_range,
)
from dapm_lightning.data.synthetic.scene import BUILDING, M_CAR, draw_family
from dapm_lightning.geometry import MAX_DEPTH_M, depth_to_grey, ideal_ground_depth
from dapm_lightning.tools.doctor import diagnose_split
from dapm_lightning.tools.synth import synth_main
from tests.conftest import run_main


def digest(root):
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.png")):
        h.update(p.relative_to(root).as_posix().encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def test_same_seed_same_bytes_any_worker_count(tmp_path):
    a = generate_uapd(tmp_path / "a", train=4, val=2, size=(20, 28), seed=3, workers=1)
    b = generate_uapd(tmp_path / "b", train=4, val=2, size=(20, 28), seed=3, workers=2)
    c = generate_uapd(tmp_path / "c", train=4, val=2, size=(20, 28), seed=4, workers=1)
    assert digest(a) == digest(b)
    assert digest(a) != digest(c)
    info = json.loads((a / "synth.json").read_text())
    assert info["depth_kind"] == "range" and {"train", "val", "size", "seed", "families"} <= set(info)
    assert len(UAPDDataset(a, "train")) == 4 and len(UAPDDataset(a, "val")) == 2


def test_two_shards_equal_one_run(tmp_path):
    whole = generate_uapd(tmp_path / "whole", train=5, val=2, size=(24, 32), seed=8, workers=1)
    for k in range(2):
        synth_main(["--out", str(tmp_path / "parts"), "--train", "5", "--val", "2", "--size", "24", "32",
                    "--seed", "8", "--workers", "1", "--shard", f"{k}/2"])
    assert len(list((tmp_path / "parts").rglob("*.png"))) == 14
    assert digest(whole) == digest(tmp_path / "parts")
    assert (whole / "synth.json").read_bytes() == (tmp_path / "parts" / "synth.json").read_bytes()
    assert [list(shard_range(7, (k, 3))) for k in range(3)] == [[0, 1], [2, 3], [4, 5, 6]]


def test_changed_settings_rerender_and_are_recorded(tmp_path):
    out = generate_uapd(tmp_path / "d", train=3, val=1, size=16, seed=1, workers=1)
    assert is_current(out, train=3, val=1, size=16, seed=1)
    assert not is_current(out, train=3, val=1, size=16, seed=1, families="forest")
    generate_uapd(out, train=2, val=1, size=16, seed=1, workers=1, families="forest=1")
    names = sorted(p.name for p in (out / "train" / "rgb").iterdir())
    assert len(names) == 2 and all("_forest_" in n for n in names)  # the stale third image is gone
    info = json.loads((out / "synth.json").read_text())
    assert info["families"] == {"forest": 1.0} and info["train"] == 2
    with pytest.raises(ValueError, match="other settings"):  # shards never delete another run's files
        generate_uapd(out, train=2, val=1, size=16, seed=2, workers=1, shard=(0, 2))


def test_the_depth_limit_is_recorded_and_a_set_of_another_limit_is_not_current(tmp_path):
    """Rendered at 500 m: synth.json says so (the data set refuses a 1000 m read) and a 1000 m render replaces it."""
    from dapm_lightning.data import DatasetError

    out = generate_uapd(tmp_path / "d", train=1, val=1, size=16, seed=1, workers=1, max_depth=500.0)
    assert json.loads((out / "synth.json").read_text())["max_depth"] == 500.0
    assert is_current(out, train=1, val=1, size=16, seed=1, max_depth=500.0)
    assert not is_current(out, train=1, val=1, size=16, seed=1)
    with pytest.raises(DatasetError, match="rendered with a depth limit of 500 m"):
        UAPDDataset(out, "train")


def test_train_and_val_images_are_drawn_apart():
    """The same index in another split is another image: its generator depends on the split too."""
    for index in range(3):
        train, val = (sample_pose(image_seed(5, split, index)) for split in ("train", "val"))
        assert not np.array_equal(train, val)


def test_the_rendered_pose_is_the_one_its_file_name_reads_back():
    """Poses are drawn to the 2 decimals the name holds: the depth is rendered for the pose a reader parses."""
    for index in range(10):
        pose = sample_pose(image_seed(0, "train", index))
        assert [float(f"{value:.2f}") for value in pose] == pose.tolist()


def test_a_folder_of_other_images_is_not_rendered_into(tmp_path, capsys):
    """A real UAPD set (images, no synth.json) given as --out: refused, nothing added, no usage text."""
    real = tmp_path / "uapd"
    (real / "val" / "depth").mkdir(parents=True)
    photo = real / "val" / "depth" / "h100_p-45_r0_f60.png"
    photo.write_bytes(b"a real frame")
    code, err = run_main(["synth", "--out", str(real), "--train", "1", "--val", "1", "--size", "16"], capsys)
    assert code == 1 and f"{real}: holds images not rendered by the generator (e.g. {photo})" in err, err
    assert "Fix: render into an empty folder" in err and "UAPDDataModule" in err and "usage" not in err
    assert [p for p in real.rglob("*") if p.is_file()] == [photo] and photo.read_bytes() == b"a real frame"
    photo.rename(photo.with_suffix(".PNG"))  # the reader pairs NAME.PNG too
    with pytest.raises(SynthFolderError, match="h100_p-45_r0_f60.PNG"):
        generate_uapd(real, train=1, val=1, size=16, seed=1, workers=1)
    (real / "val" / "depth" / "h100_p-45_r0_f60.PNG").unlink()
    (real / "val" / "depth" / "._h100_p-45_r0_f60.png").write_bytes(b"macOS metadata")  # hidden: not an image
    generate_uapd(real, train=1, val=1, size=16, seed=1, workers=1)
    out = generate_uapd(tmp_path / "crashed", train=3, val=1, size=16, seed=1, workers=1)
    (out / "synth.json").unlink()  # a render cut short: its images replaced, even of other settings
    generate_uapd(out, train=1, val=1, size=16, seed=1, workers=1)
    assert len(list(out.rglob("*.png"))) == 4 and (out / "synth.json").is_file()


def test_two_renders_replacing_one_stale_set_at_once_both_succeed(tmp_path, monkeypatch):
    """The nodes of a multi-node run render a shared folder each (Lightning prepares data once a node): where both
    replace a stale set, an image the other deleted between this one's listing and its deletion is no error."""
    from pathlib import Path

    out = generate_uapd(tmp_path / "shared", train=3, val=1, size=16, seed=1, workers=1)
    (out / "synth.json").unlink()  # a render cut short: both nodes replace its images
    unlink = Path.unlink

    def deleted_by_the_other_node_first(path, missing_ok=False):
        if path.name.startswith("synth_") and path.exists():
            unlink(path)
        unlink(path, missing_ok=missing_ok)

    monkeypatch.setattr(Path, "unlink", deleted_by_the_other_node_first)
    generate_uapd(out, train=2, val=1, size=16, seed=1, workers=1)
    assert len(list(out.rglob("*.png"))) == 6 and (out / "synth.json").is_file()


def test_a_new_folder_renders_each_image_once(tmp_path, monkeypatch):
    """Only a set being replaced renders its first image ahead (to fail before deleting); a new folder does not."""
    from dapm_lightning.data.synthetic import generate

    rendered = []
    render = generate.render_sample
    monkeypatch.setattr(generate, "render_sample", lambda *args: rendered.append(args[1:3]) or render(*args))
    generate_uapd(tmp_path / "new", train=2, val=1, size=16, seed=1, workers=1)
    assert rendered == [("train", 0), ("train", 1), ("val", 0)]


def test_settings_that_cannot_render_leave_the_old_set_whole(tmp_path, monkeypatch):
    from dapm_lightning.data.synthetic import generate

    out = generate_uapd(tmp_path / "d", train=2, val=1, size=16, seed=1, workers=1)
    before = {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    with pytest.raises(ValueError, match="size 100000x100000: each side must be 1 to 8192 pixels"):
        generate_uapd(out, train=1, val=0, size=100000, seed=1, workers=1)

    def out_of_memory(*args, **kwargs):
        raise MemoryError("can't allocate memory")

    monkeypatch.setattr(generate, "render_sample", out_of_memory)  # e.g. a size this machine cannot hold
    with pytest.raises(MemoryError):
        generate_uapd(out, train=1, val=0, size=4096, seed=1, workers=1)
    assert {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()} == before


def test_family_weights_are_followed():
    assert normalize_families("downtown=3,forest=1") == {"downtown": 0.75, "forest": 0.25}
    assert set(normalize_families(None)) == set(FAMILIES)
    with pytest.raises(ValueError, match="unknown"):
        normalize_families("moon=1")
    with pytest.raises(ValueError):
        normalize_families({"forest": 0.0})
    rng = np.random.default_rng(0)
    counts = Counter(draw_family(rng, {"downtown": 3, "water": 1, "forest": 0}) for _ in range(4000))
    assert set(counts) == {"downtown", "water"}
    assert abs(counts["downtown"] / 4000 - 0.75) < 0.03


@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_passes_the_doctor(family, tmp_path):
    root = generate_uapd(tmp_path / family, train=5, val=0, size=(40, 56), seed=11, workers=1, families={family: 1})
    report = diagnose_split(root, "train", "range")
    assert report["count"] == 5 and not report["errors"] and not report["flagged"]
    assert all(parse_uapd_filename(n)["tokens"][-1] == family for n in UAPDDataset(root, "train").names)


@pytest.mark.parametrize("family", FAMILIES)
def test_ground_and_water_pixels_are_the_ideal_ground_depth(family):
    size = (40, 56)
    checked = 0
    for index in range(4):
        rng = image_seed(5, "train", index)
        pose = sample_pose(rng)
        rgb, range_m, hit = render_scene(pose, size, sample_scene(rng, family))
        assert rgb.shape == (*size, 3) and rgb.dtype == np.uint8 and hit.shape == size
        flat = (hit == GROUND) | (hit == WATER)
        igd = ideal_ground_depth(torch.from_numpy(np.array([pose], np.float64)), size, max_depth=1e9)[0, 0].numpy()
        np.testing.assert_allclose(range_m[flat], igd[flat], rtol=1e-6)
        np.testing.assert_array_equal(depth_to_grey(range_m)[flat], depth_to_grey(igd)[flat])
        seen = np.isfinite(range_m)
        assert (seen == (hit != SKY)).all()
        # objects stand on the ground: never farther than the ground behind them
        assert (range_m[seen & ~flat] <= igd[seen & ~flat] * (1 + 1e-5)).all()
        checked += int(flat.sum())
    assert checked > 0


def test_ground_reaches_the_horizon_beyond_max_depth():
    pose = np.array([60.0, -2.0, 0.0, 90.0])
    rng = np.random.default_rng(3)
    rgb, range_m, hit = render_scene(pose, (64, 64), sample_scene(rng, "farmland"))
    far_ground = (hit == GROUND) & (range_m > MAX_DEPTH_M)
    assert far_ground.sum() > 20  # ground, not sky, beyond 1000 m ...
    assert (depth_to_grey(range_m)[far_ground] == 255).all()  # ... written as grey 255
    sky_rows = np.flatnonzero((hit == SKY).all(1))
    assert len(sky_rows) and sky_rows.max() < np.flatnonzero((hit == GROUND).any(1)).min()


def test_objects_have_real_sizes():
    rng = np.random.default_rng(0)
    downtown = sample_scene(rng, "downtown").objects
    size = downtown.hi - downtown.lo
    towers = (downtown.cls == BUILDING) & (downtown.lo[:, 2] == 0) & (size[:, :2].min(1) > 8)
    assert downtown.hi[towers, 2].min() >= 20 * 0.45 and downtown.hi[:, 2].max() <= 150 + 4.01
    cars = downtown.mat == M_CAR
    length = size[cars, :2].max(1)
    assert cars.sum() > 20 and length.min() >= 4.2 and np.median(length) < 5.0 and length.max() <= 12.0
    people = downtown.cls == PERSON
    assert people.sum() > 5 and ((size[people, 2] >= 1.6) & (size[people, 2] <= 1.9)).all()
    assert (downtown.cls == VEHICLE).sum() >= cars.sum()


def test_horizon_tilt_follows_roll():
    scene = sample_scene(np.random.default_rng(0), "farmland")
    _, left_tilt, _ = render_scene(np.array([50.0, 0.0, 20.0, 90.0]), (64, 64), scene)
    sky_left, sky_right = np.isinf(left_tilt[:, 0]).sum(), np.isinf(left_tilt[:, -1]).sum()
    assert sky_right < sky_left  # positive roll: right end of the horizon up


def test_512_pixels():
    rng = image_seed(0, "train", 1)
    pose = sample_pose(rng)
    rgb, range_m, hit = render_scene(pose, (512, 512), sample_scene(rng, "suburb"))
    assert rgb.shape == (512, 512, 3) and range_m.shape == hit.shape == (512, 512)


def test_cli_synth(tmp_path, capsys):
    out = tmp_path / "s"
    synth_main(["--out", str(out), "--train", "2", "--val", "1", "--size", "16", "--seed", "1", "--workers", "1",
                "--families", "suburb,water=2"])
    assert "wrote 2 train + 1 val images" in capsys.readouterr().out
    assert len(UAPDDataset(out, "train")) == 2
    assert json.loads((out / "synth.json").read_text())["families"] == {"suburb": 1 / 3, "water": 2 / 3}
    for bad, message in ((["--shard", "2/2"], "0 <= K < N"), (["--families", "moon=1"], "unknown scene family"),
                         (["--train", "0", "--val", "0"], "nothing to render"),
                         (["--workers", "0"], "--workers must be at least 1")):
        with pytest.raises(SystemExit) as info:
            synth_main(["--out", str(out), *bad])
        assert info.value.code == 2 and message in capsys.readouterr().err


def test_slurm_array_script_renders_the_shards(tmp_path):
    import os
    from pathlib import Path

    script = Path(__file__).resolve().parents[2] / "scripts" / "synth_slurm.sh"
    env = {**os.environ, "OUT": str(tmp_path / "array"), "TRAIN": "3", "VAL": "1", "SIZE": "12", "SEED": "5",
           "FAMILIES": "suburb=1,forest=1", "PYTHON": sys.executable, "SLURM_ARRAY_TASK_COUNT": "2",
           "SLURM_ARRAY_TASK_MIN": "0", "SLURM_CPUS_PER_TASK": "1"}
    synth_main(["--out", env["OUT"], "--train", "3", "--val", "1", "--size", "12", "--seed", "5", "--families",
                "suburb=1,forest=1", "--workers", "1", "--shard", "0/2"])  # task 0 in-process, task 1 by the script
    subprocess.run(["bash", str(script)], env={**env, "SLURM_ARRAY_TASK_ID": "1"}, check=True)
    whole = generate_uapd(tmp_path / "whole", train=3, val=1, size=12, seed=5, workers=1,
                          families="suburb=1,forest=1")
    assert digest(whole) == digest(tmp_path / "array") and len(list(whole.rglob("*.png"))) == 8


def test_lens_distortion_warps_image_and_depth_alike(tmp_path):
    from dapm_lightning.data.synthetic.lens import distort, distortion_maps

    rng = image_seed(2, "train", 0)
    pose = sample_pose(rng)
    rgb, range_m, hit = render_scene(pose, (33, 47), sample_scene(rng, "suburb"), effects=False)
    same = distort(rgb, range_m, hit, 0.0, 0.0)
    assert (same[0] == rgb).all() and np.array_equal(same[1], range_m) and (same[2] == hit).all()
    warped_rgb, warped_m, warped_hit = distort(rgb, range_m, hit, 0.4, -0.1)
    map_x, map_y = distortion_maps((33, 47), 0.4, -0.1)
    src = (np.clip(np.round(map_y), 0, 32).astype(int), np.clip(np.round(map_x), 0, 46).astype(int))
    np.testing.assert_array_equal(warped_m, range_m[src])  # every depth is the range of the pixel it shows
    np.testing.assert_array_equal(warped_hit, hit[src])
    assert warped_m[16, 23] == range_m[16, 23] and not np.array_equal(warped_m, range_m)
    root = generate_uapd(tmp_path / "lens", train=2, val=0, size=16, seed=1, workers=1, distortion=True)
    names = UAPDDataset(root, "train").names
    assert all("lensk" in parse_uapd_filename(n) for n in names)
    assert json.loads((root / "synth.json").read_text())["distortion"] is True


def test_the_synthetic_module_says_what_it_renders_and_what_it_replaces(tmp_path, capsys):
    """A set rendered with other settings is re-rendered with a warning naming what changed, not silently."""
    import warnings

    from dapm_lightning.data.datamodules import SyntheticDataModule

    def prepare(train: int) -> list[str]:
        dm = SyntheticDataModule(root=str(tmp_path / "s"), train_size=train, val_size=1, image_size=16,
                                 render_workers=1, num_workers=0)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            dm.prepare_data()
        return [str(w.message) for w in caught]

    assert prepare(1) == [] and "s: rendering 1 + 1 synthetic images at 16 px" in capsys.readouterr().out
    assert prepare(1) == [] and capsys.readouterr().out == ""  # current: nothing rendered, nothing said
    replaced = prepare(2)
    assert len(replaced) == 1 and "rendering it again (2 + 1 synthetic images at 16 px)" in replaced[0]
    assert "(train 1 -> 2)" in replaced[0] and "another data.init_args.root" in replaced[0]
    assert len(list((tmp_path / "s" / "train" / "rgb").iterdir())) == 2


def test_a_set_the_synth_command_rendered_is_never_replaced_unasked(tmp_path, capsys):
    """Before, the module pointed at a set `synth` rendered, or `synth` over a set of other settings, deleted its images
    with a warning at most: the module replaces only its own caches, and `synth` only with --replace."""
    from dapm_lightning.data.datamodules import SyntheticDataModule

    out = tmp_path / "s"
    synth_main(["--out", str(out), "--train", "2", "--val", "1", "--size", "16", "--workers", "1", "--quiet"])
    kept = sorted(p.name for p in (out / "train" / "rgb").iterdir())
    dm = SyntheticDataModule(root=str(out), train_size=3, val_size=1, image_size=16, render_workers=1, num_workers=0)
    with pytest.raises(SynthFolderError, match=r"other settings \(train 2 -> 3\), not one this module rendered"):
        dm.prepare_data()
    with pytest.raises(SynthFolderError, match="Fix: add --replace"):
        synth_main(["--out", str(out), "--train", "3", "--val", "1", "--size", "16", "--workers", "1", "--quiet"])
    assert sorted(p.name for p in (out / "train" / "rgb").iterdir()) == kept
    SyntheticDataModule(root=str(out), train_size=2, val_size=1, image_size=16, num_workers=0).prepare_data()  # same
    synth_main(["--out", str(out), "--train", "3", "--val", "1", "--size", "16", "--workers", "1", "--quiet",
                "--replace"])
    assert len(list((out / "train" / "rgb").iterdir())) == 3 and not is_cache(out)


def test_an_image_that_cannot_be_written_stops_the_render_naming_it(tmp_path, monkeypatch):
    """OpenCV reports a failed write by returning False: the generator raises instead, and is not left 'current'."""
    import cv2

    from dapm_lightning.data.files import WriteError

    monkeypatch.setattr(cv2, "imencode", lambda *args, **kwargs: (False, None))
    with pytest.raises(WriteError, match=r"synth_000000.*\.png"):
        generate_uapd(tmp_path / "d", train=1, val=0, size=16, workers=1)
    assert not (tmp_path / "d" / "synth.json").exists()
    assert not list((tmp_path / "d").rglob("*.png"))


VERSION_3_SCENES = "3a2022feda9533725ed34fda35a7ae4072bbc25e416d2e61e900e2f43728cb08"
"""``scene_fingerprint(range(6))`` computed with generator version 3's code (commit 5dbf64c)."""


def scene_fingerprint(seeds) -> str:
    """Everything of a scene but the sky's colours and glare, rounded (floats may differ in the last bit between
    machines)."""
    digest = hashlib.sha256()
    for seed in seeds:
        scene = sample_scene(np.random.default_rng(seed))
        look = {k: np.round(np.asarray(v, float), 6).tolist() for k, v in sorted(scene.look.items())
                if k not in ("haze", "zenith", "bloom")}
        digest.update(json.dumps([scene.family, scene.texture_seed, round(scene.yaw_deg, 6),
                                  np.round(scene.camera_xy, 6).tolist(), np.round(scene.sun, 6).tolist(), look,
                                  np.round(scene.objects.lo, 3).tolist(),
                                  np.round(scene.objects.hi, 3).tolist()]).encode())
    return digest.hexdigest()


def test_skies_are_blue_pale_or_white_with_the_rest_of_the_scene_unchanged():
    """Generator version 4: the sky's kind and the sun's glare come from their own stream after the rest, so every
    object, texture, camera and sun of a scene is version 3's."""
    from dapm_lightning.data.synthetic.shading import sky_color

    looks = [sample_scene(np.random.default_rng(i)).look for i in range(400)]
    zeniths = np.array([look["zenith"] for look in looks])
    deep_blue = (zeniths[:, 2] - zeniths[:, 0] > 0.45).mean()  # version 3's zenith: blue - red = 0.60 +- 0.16
    grey_white = ((zeniths.max(1) - zeniths.min(1) < 0.1) & (zeniths.mean(1) > 0.6)).mean()
    assert 0.3 < deep_blue < 0.6 and 0.12 < grey_white < 0.3, (deep_blue, grey_white)
    assert 0.3 < np.mean([look["bloom"] > 0 for look in looks]) < 0.5
    assert all(0 <= look[key].min() and look[key].max() <= 1 for look in looks for key in ("haze", "zenith"))

    glaring = next(look for look in looks if look["bloom"] > 0.5)
    sun = np.array([0.0, 0.6, 0.8])
    near_sun = np.array([[0.0, 0.42, 0.907]])  # about 15 degrees from the sun
    plain = {**glaring, "bloom": 0.0, "clouds": 0.0}
    assert (sky_color(near_sun, sun, {**plain, "bloom": glaring["bloom"]}, np.zeros(3), 1e-3, 0)
            > sky_color(near_sun, sun, plain, np.zeros(3), 1e-3, 0) + 0.1).all()

    assert scene_fingerprint(range(6)) == VERSION_3_SCENES


def test_an_image_a_worker_cannot_write_ends_the_command_naming_it(tmp_path, capsys):
    """A worker's WriteError reaches the command whole (it pickles): the file and the fix, no usage, status 1.

    Before, it could not be unpickled and the render ended in 'BrokenProcessPool: ... terminated abruptly'.
    """
    import pickle

    from dapm_lightning.data.files import WriteError

    error = pickle.loads(pickle.dumps(WriteError(tmp_path / "x.png", "No space left on device", "free space")))
    assert (error.path, error.reason, error.fix) == (tmp_path / "x.png", "No space left on device", "free space")
    args = ["--out", str(tmp_path / "s"), "--train", "3", "--val", "0", "--size", "12", "--quiet"]
    synth_main([*args, "--workers", "1"])
    blocked = next((tmp_path / "s" / "train" / "rgb").glob("synth_000002_*.png"))
    blocked.unlink()
    blocked.mkdir()  # the image cannot replace a folder: the worker's write fails
    code, err = run_main(["synth", *args, "--workers", "2"], capsys)
    assert code == 1 and f"{blocked}: cannot be written" in err and "Fix:" in err
    assert "usage:" not in err and "BrokenProcessPool" not in err
    assert "stopped by the error below: no synth.json written (the set is unfinished" in err, err
    assert next(line for line in err.splitlines() if line.startswith("Fix: ")).endswith("(--out)"), err


def test_sigterm_stops_the_render_and_its_workers(tmp_path):
    """SIGTERM (scancel, a job's time limit) ends the worker processes too, with status 143 and no synth.json.

    Before, only the main process died: its workers rendered on after the command had ended, then hung for good.
    """
    import os
    import signal
    import time

    out = tmp_path / "s"
    command = [sys.executable, "-m", "dapm_lightning", "synth", "--out", str(out), "--train", "2000", "--val", "0",
               "--size", "48", "--workers", "2", "--quiet"]
    process = subprocess.Popen(command, start_new_session=True, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not list(out.glob("train/rgb/synth_*.png")) and time.monotonic() < deadline:
            time.sleep(0.2)
        process.send_signal(signal.SIGTERM)
        _, err = process.communicate(timeout=60)  # before: hung here, the orphaned workers holding stderr
        assert process.returncode == 143 and "Traceback" not in err
        assert "stopped by SIGTERM: no synth.json written; rerun the same command" in err, err[-2000:]
        deadline, left = time.monotonic() + 10, ["?"]
        while left and time.monotonic() < deadline:
            time.sleep(0.2)
            left = subprocess.run(["pgrep", "-a", "-s", str(process.pid)], capture_output=True, text=True).stdout
            left = left.splitlines()
        assert left == []
        count = len(list(out.rglob("synth_*.png")))
        time.sleep(1)
        assert len(list(out.rglob("synth_*.png"))) == count < 2000
        assert not (out / "synth.json").exists() and not list(out.rglob(".*.tmp"))
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
        subprocess.run(["pkill", "-KILL", "-s", str(process.pid)], check=False)


def test_stopping_the_render_pool_waits_for_its_manager_thread():
    """Python's exit handler wakes a process pool's manager thread through a pipe that thread closes as it ends, the
    two unlocked (CPython 3.11): a ``synth`` stopped by SIGTERM printed "OSError: Bad file descriptor" at exit, once
    in the CI. Stopped here, the thread has ended and its pipe is closed before the exit handler runs."""
    import multiprocessing
    import time
    from concurrent.futures import ProcessPoolExecutor

    from dapm_lightning.data.synthetic.generate import _stop_workers

    pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork"))
    pool.submit(time.sleep, 30)
    time.sleep(0.5)
    manager = pool._executor_manager_thread
    _stop_workers(pool)
    assert not manager.is_alive()


def test_sigterm_after_the_set_is_written_says_so(tmp_path, capsys, monkeypatch):
    """A SIGTERM that lands after synth.json was written says the set is complete (before: the handler said
    'no synth.json written', and a job script rendered it all again)."""
    import os
    import signal

    import dapm_lightning.tools.synth as synth_tool

    render = synth_tool.generate_uapd

    def render_then_sigterm(*args, **kwargs):
        out = render(*args, **kwargs)
        os.kill(os.getpid(), signal.SIGTERM)
        return out

    monkeypatch.setattr(synth_tool, "generate_uapd", render_then_sigterm)
    previous = signal.signal(signal.SIGTERM, signal.SIG_IGN)  # restored after the command (a stray one ends nothing)
    try:
        code, err = run_main(["synth", "--out", str(tmp_path / "s"), "--train", "2", "--val", "1", "--size", "16",
                              "--workers", "1", "--quiet"], capsys)
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert code == 143
    assert err.strip().splitlines()[-1] == "stopped by SIGTERM: the set was complete (synth.json written)"
    assert (tmp_path / "s" / "synth.json").is_file()



@pytest.mark.parametrize("rendered", [True, False])
def test_ctrl_c_says_what_state_the_set_is_in(tmp_path, capsys, monkeypatch, rendered):
    """As SIGTERM does (before, Ctrl-C printed only `interrupted`)."""
    import dapm_lightning.tools.synth as synth_tool

    render = synth_tool.generate_uapd

    def render_then_ctrl_c(*args, **kwargs):
        if rendered:
            render(*args, **kwargs)
        raise KeyboardInterrupt

    monkeypatch.setattr(synth_tool, "generate_uapd", render_then_ctrl_c)
    code, err = run_main(["synth", "--out", str(tmp_path / "s"), "--train", "2", "--val", "1", "--size", "16",
                          "--workers", "1", "--quiet"], capsys)
    assert code == 130
    said = "the set was complete (synth.json written)" if rendered else "no synth.json written; rerun the same " \
        "command to render the set"
    assert f"stopped by Ctrl-C: {said}" in err, err


@pytest.mark.parametrize("existed", [False, True])
def test_a_render_stopped_before_its_first_image_leaves_no_empty_folder_it_made(tmp_path, monkeypatch, existed):
    """A stop during the first image: the folders this render made are removed again (before: an empty train/rgb
    and its siblings were left); a folder that was there before is kept, and so is anything in it."""
    import dapm_lightning.data.synthetic.generate as generate

    def stopped(job):
        raise KeyboardInterrupt

    out = tmp_path / "new" / "s"  # --out's parent made by the render too, and removed with it
    if existed:
        (out / "train").mkdir(parents=True)
    monkeypatch.setattr(generate, "_render_one", stopped)
    with pytest.raises(KeyboardInterrupt):
        generate_uapd(out, train=2, val=1, size=16, workers=1)
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == (
        ["new", "new/s", "new/s/train"] if existed else [])
