"""Tall structures outside downtown: in the share of scenes each family is given, off the roads, nothing standing in
them, and the rest of the scene unchanged by them."""

import math

import numpy as np
import pytest

from dapm_lightning.data.synthetic import landmarks, sample_scene
from dapm_lightning.data.synthetic.landmarks import LANDMARKS
from dapm_lightning.data.synthetic.objects import BUILDING
from dapm_lightning.data.synthetic.rural import road_distance
from dapm_lightning.data.synthetic.urban import on_road


def _scene_pair(family: str, seed: int, monkeypatch):
    """The same scene with the landmarks and without them (their share set to 0)."""
    with_them = sample_scene(np.random.default_rng(seed), family)
    with monkeypatch.context() as patch:
        patch.setattr(landmarks, "LANDMARKS", {})
        without = sample_scene(np.random.default_rng(seed), family)
    return with_them, without


def _added(with_them, without) -> np.ndarray:
    """Rows of ``with_them`` that ``without`` lacks (the landmarks are appended last)."""
    kept = len(with_them.objects) - _count_added(with_them, without)
    return np.arange(kept, len(with_them.objects))


def _count_added(with_them, without) -> int:
    rows = {tuple(np.round(np.r_[lo, hi], 6)) for lo, hi in zip(without.objects.lo, without.objects.hi)}
    objects = with_them.objects
    return sum(tuple(np.round(np.r_[lo, hi], 6)) not in rows for lo, hi in zip(objects.lo, objects.hi))


@pytest.mark.parametrize("family", ["suburb", "industrial", "farmland", "forest", "downtown"])
def test_landmarks_appear_in_their_share_of_scenes_with_real_sizes(family, monkeypatch):
    share = LANDMARKS.get(family, (0.0, {}))[0]
    counts, heights = [], []
    for seed in range(40):
        with_them, without = _scene_pair(family, seed, monkeypatch)
        rows = _added(with_them, without)
        counts.append(len(rows))
        heights += list(with_them.objects.hi[rows, 2])
        assert (with_them.objects.cls[rows] == BUILDING).all() and (with_them.objects.lo[rows, 2] == 0).all()
    seen = np.mean(np.array(counts) > 0)
    if family == "downtown":  # towers of its own
        assert seen == 0
        return
    assert abs(seen - share) < 0.25 and max(counts) <= 8
    assert 15 <= min(heights) and max(heights) <= 120
    # the share is followed, not only nearly always met: at half, about half the scenes hold landmarks
    monkeypatch.setitem(LANDMARKS, family, (0.5, LANDMARKS[family][1]))
    halved = [len(_added(*_scene_pair(family, seed, monkeypatch))) > 0 for seed in range(30)]
    assert 0.25 <= np.mean(halved) <= 0.75


@pytest.mark.parametrize("family", ["suburb", "industrial", "farmland", "forest"])
def test_landmarks_stand_off_roads_and_nothing_stands_in_them(family, monkeypatch):
    checked = 0
    for seed in range(25):
        with_them, without = _scene_pair(family, seed, monkeypatch)
        rows = _added(with_them, without)
        objects, layout = with_them.objects, with_them.layout
        others = np.setdiff1d(np.arange(len(objects)), rows)
        for i in rows:
            (x0, y0, _), (x1, y1, _) = objects.lo[i], objects.hi[i]
            xs, ys = (v.ravel() for v in np.meshgrid(np.linspace(x0, x1, 25), np.linspace(y0, y1, 25)))
            if "grid" in layout:
                assert not np.any(on_road(xs, ys, layout["grid"])[2:]), (seed, i)
            if layout.get("road") is not None:
                assert (np.abs(road_distance(xs, ys, layout["road"])[0]) > layout["road"]["width"] / 2).all()
            overlap = ((objects.lo[others, 0] < x1) & (objects.hi[others, 0] > x0)
                       & (objects.lo[others, 1] < y1) & (objects.hi[others, 1] > y0))
            assert not overlap.any(), (seed, i)
            distance = math.hypot((x0 + x1) / 2 - with_them.camera_xy[0], (y0 + y1) / 2 - with_them.camera_xy[1])
            assert 30 < distance < 450
            checked += 1
    assert checked >= 5


def test_the_rest_of_the_scene_is_unchanged_by_the_landmarks(monkeypatch):
    changed = 0
    for seed in range(30):
        with_them, without = _scene_pair("suburb", seed, monkeypatch)
        assert np.array_equal(with_them.sun, without.sun) and with_them.texture_seed == without.texture_seed
        assert with_them.layout["grid"] == without.layout["grid"]
        added = _count_added(with_them, without)
        changed += added > 0
        # the rows kept are rows of the scene without landmarks, in order; only those under a landmark are gone
        kept_lo = with_them.objects.lo[:len(with_them.objects) - added]
        before = {tuple(v) for v in without.objects.lo}
        assert all(tuple(v) in before for v in kept_lo)
    assert changed >= 8
