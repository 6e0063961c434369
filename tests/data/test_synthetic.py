import hashlib
import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from dapm_lightning.data import UAPDDataset
from dapm_lightning.data.synthetic import GROUND, generate_uapd, render_scene, sample_scene
from dapm_lightning.geometry import depth_to_grey, ideal_ground_depth


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
    assert json.loads((a / "synth.json").read_text())["depth_kind"] == "range"
    assert len(UAPDDataset(a, "train")) == 4 and len(UAPDDataset(a, "val")) == 2


@pytest.mark.parametrize("pose", [(35.0, -70.0, 12.0, 60.0), (80.0, -20.0, -25.0, 110.0), (12.0, 2.0, 5.0, 40.0)])
def test_ground_pixels_match_ideal_ground_depth(pose):
    size = (48, 64)
    rgb, range_m, hit = render_scene(np.array(pose), size, sample_scene(np.random.default_rng(5)))
    ground = hit == GROUND
    assert ground.mean() > 0.05
    igd = ideal_ground_depth(torch.tensor([pose], dtype=torch.float64), size, max_depth=1e9)[0, 0].numpy()
    np.testing.assert_allclose(range_m[ground], igd[ground], rtol=1e-6)
    # and in the written 8-bit encoding
    np.testing.assert_array_equal(depth_to_grey(range_m)[ground], depth_to_grey(igd)[ground])
    # buildings and trees stand above the ground: never farther than the ground behind them
    assert (range_m[~ground & np.isfinite(range_m)] <= igd[~ground & np.isfinite(range_m)] + 1e-6).all()


def test_horizon_tilt_follows_roll():
    scene = sample_scene(np.random.default_rng(0))
    _, left_tilt, _ = render_scene(np.array([50.0, 0.0, 20.0, 90.0]), (64, 64), scene)
    sky_left, sky_right = np.isinf(left_tilt[:, 0]).sum(), np.isinf(left_tilt[:, -1]).sum()
    assert sky_right < sky_left  # positive roll: right end of the horizon up


def test_cli_synth(tmp_path):
    out = tmp_path / "s"
    subprocess.run([sys.executable, "-m", "dapm_lightning", "synth", "--out", str(out), "--train", "2",
                    "--val", "1", "--size", "16", "--seed", "1", "--workers", "1"], check=True)
    assert len(UAPDDataset(out, "train")) == 2
