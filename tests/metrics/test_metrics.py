import math

import numpy as np
import pytest
import torch

from dapm_lightning.geometry import encode_log_depth
from dapm_lightning.metrics import DepthMetrics, PoseMetrics, auc_of_recall


def reference_depth(pred, gt, min_d=1e-3, max_d=1000.0):
    """Plain per-image loop, numpy."""
    per_image = []
    for p, g in zip(pred.reshape(pred.shape[0], -1).numpy(), gt.reshape(gt.shape[0], -1).numpy()):
        m = (g > min_d) & (g < max_d)
        if not m.any():
            continue
        p, g = np.clip(p[m].astype(np.float64), min_d, max_d), g[m].astype(np.float64)
        t = np.maximum(g / p, p / g)
        e = np.log(p) - np.log(g)
        per_image.append(dict(d1=(t < 1.25).mean(), d2=(t < 1.25 ** 2).mean(), d3=(t < 1.25 ** 3).mean(),
                              abs_rel=np.mean(np.abs(g - p) / g), sq_rel=np.mean((g - p) ** 2 / g),
                              rmse=np.sqrt(np.mean((g - p) ** 2)), rmse_log=np.sqrt(np.mean(e ** 2)),
                              log10=np.mean(np.abs(np.log10(g) - np.log10(p))),
                              silog=100 * np.sqrt(max(np.mean(e ** 2) - np.mean(e) ** 2, 0))))
    return {k: np.mean([r[k] for r in per_image]) for k in per_image[0]}


def random_batch(seed=0, b=4):
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(b, 1, 6, 7, generator=g) * 300 + 0.5
    pred = gt * (0.6 + 0.8 * torch.rand(b, 1, 6, 7, generator=g))
    gt[0, 0, 0, :] = 1000.0  # sky: excluded (strict < max_depth)
    gt[1, 0, 1, :] = 0.0  # invalid
    pred[2, 0, 0, 0] = 5000.0  # clamped to max_depth
    return pred, gt


def test_depth_metrics_match_loop_reference():
    pred, gt = random_batch()
    m = DepthMetrics()
    m.update(pred, gt)
    got = m.compute()
    for k, v in reference_depth(pred, gt).items():
        assert got[k].item() == pytest.approx(v, rel=1e-5), k


def test_two_half_updates_equal_one_full():
    pred, gt = random_batch(1, 6)
    full, halves = DepthMetrics(), DepthMetrics()
    full.update(pred, gt)
    halves.update(pred[:3], gt[:3])
    halves.update(pred[3:], gt[3:])
    for k, v in full.compute().items():
        assert halves.compute()[k].item() == pytest.approx(v.item(), rel=1e-6)


def test_two_processes_merged_equal_one():
    """The states are sums: two "processes" of unequal shares merged (what DDP's reduction does) give the figures of
    one; a mean reduction of the image count would weigh the processes wrongly."""
    pred, gt = random_batch(1, 6)
    full, a, b = DepthMetrics(), DepthMetrics(), DepthMetrics()
    full.update(pred, gt)
    a.update(pred[:1], gt[:1])
    b.update(pred[1:], gt[1:])
    a.merge_state(b)
    for k, v in full.compute().items():
        assert a.compute()[k].item() == pytest.approx(v.item(), rel=1e-6), k


def test_image_without_valid_pixels_is_skipped_and_all_empty_is_nan():
    pred, gt = random_batch()
    gt_empty = gt.clone()
    gt_empty[3] = 1000.0
    m = DepthMetrics()
    m.update(pred, gt_empty)
    ref = reference_depth(pred[:3], gt[:3])
    assert m.compute()["abs_rel"].item() == pytest.approx(ref["abs_rel"], rel=1e-5)
    empty = DepthMetrics()
    empty.update(pred, torch.zeros_like(gt))
    assert all(math.isnan(v.item()) for v in empty.compute().values())


def test_log_space_uses_the_8bit_scale():
    pred, gt = random_batch()
    m = DepthMetrics(space="uapd_log")
    m.update(pred, gt)
    mask = (gt > 1e-3) & (gt < 1000)
    p = 255 * encode_log_depth(pred.double().clamp(1e-3, 1000))
    g = 255 * encode_log_depth(gt.double())
    per = [((p[i][mask[i]] - g[i][mask[i]]).abs() / g[i][mask[i]]).mean() for i in range(4)]
    assert m.compute()["abs_rel"].item() == pytest.approx(float(torch.stack(per).mean()), rel=1e-5)


def reference_auc(errors, t):
    """Loop version: trapezoids through (0, 0) and (e_i, i / n) up to t, then flat to t."""
    errors = np.sort(np.asarray(errors, np.float64))
    area, prev_e, prev_r = 0.0, 0.0, 0.0
    for i, e in enumerate(errors):
        if e > t:
            break
        r = (i + 1) / len(errors)
        area += 0.5 * (e - prev_e) * (prev_r + r)
        prev_e, prev_r = e, r
    return (area + (t - prev_e) * prev_r) / t


def test_auc_matches_loop_and_hand_value():
    assert auc_of_recall(torch.tensor([1.0, 2.0]), 5.0).item() == pytest.approx(0.8)
    rng = np.random.default_rng(0)
    errors = rng.exponential(4.0, size=37)
    for t in (1.0, 5.0, 10.0):
        assert auc_of_recall(torch.from_numpy(errors), t).item() == pytest.approx(reference_auc(errors, t), rel=1e-9)


def test_pose_metrics_median_numpy_semantics_and_keys():
    target = torch.zeros(4, 4)
    pred = torch.tensor([[1.0, 2.0, -3.0, 4.0], [3.0, 4.0, 5.0, 6.0], [0.5, 0.5, 0.5, 0.5], [10.0, 0, 0, 0]])
    m = PoseMetrics()
    m.update(pred[:2], target[:2])
    m.update(pred[2:], target[2:])
    got = m.compute()
    for k, key in enumerate(("height", "pitch", "roll", "fov")):
        assert got[f"{key}_median"].item() == pytest.approx(np.median(np.abs(pred[:, k].numpy())))
    assert set(got) == {f"{c}_{s}" for c in ("height", "pitch", "roll", "fov")
                        for s in ("median", "auc1", "auc5", "auc10")}


def reference_auc_min_error(errors, t, min_error):
    """Loop version of GeoCalib's option: flat at the share of errors <= min_error up to min_error, then on."""
    errors = np.sort(np.asarray(errors, np.float64))
    share = np.mean(errors <= min_error)
    points = [(0.0, share), (min_error, share)] + [(e, (i + 1) / len(errors)) for i, e in enumerate(errors)
                                                   if e > min_error]
    area, (prev_e, prev_r) = 0.0, points[0]
    for e, r in points[1:]:
        if e > t:
            break
        area += 0.5 * (e - prev_e) * (prev_r + r)
        prev_e, prev_r = e, r
    return (area + (t - prev_e) * prev_r) / t


def test_auc_counts_errors_equal_to_the_threshold():
    # recall(0.5) is 3/5 here: the curve (0, 0), (0, 1/5), (0.5, 2/5), (0.5, 3/5) gives 0.3; stopping before the
    # errors equal to 0.5, flat at 1/5, gave 0.2
    errors = np.array([0.0, 0.5, 0.5, 1.0, 2.0])
    assert auc_of_recall(torch.from_numpy(errors), 0.5).item() == pytest.approx(0.3)
    rng = np.random.default_rng(1)
    for _ in range(200):
        ties = rng.integers(0, 6, size=rng.integers(1, 12)) / 2.0  # many errors exactly on a threshold
        for t in (0.5, 1.0, 2.0):
            assert auc_of_recall(torch.from_numpy(ties), t).item() == pytest.approx(reference_auc(ties, t), abs=1e-12)


def test_min_error_counts_small_errors_as_perfect_as_geocalib():
    pred = torch.tensor([[0.8, 0.8, 0.8, 0.8], [3.0, 3.0, 3.0, 3.0]])
    plain, geocalib = PoseMetrics(), PoseMetrics(min_error=1.0)
    plain.update(pred, torch.zeros(2, 4))
    geocalib.update(pred, torch.zeros(2, 4))
    # (0, 0.5), (1, 0.5), (3, 1), (5, 1): 4 / 5 (zeroing the small errors gave (0, 0.5), (3, 1), (5, 1): 0.85);
    # without min_error (0, 0), (0.8, 0.5), (3, 1), (5, 1): 0.77
    assert geocalib.compute()["roll_auc5"].item() == pytest.approx(0.8)
    assert plain.compute()["roll_auc5"].item() == pytest.approx(0.77)
    assert geocalib.compute()["roll_median"].item() == pytest.approx(1.9)  # the errors' median, not of zeroed ones
    assert geocalib.compute()["roll_auc1"].item() == pytest.approx(0.5)
    rng = np.random.default_rng(2)
    errors = rng.exponential(3.0, size=41)
    for min_error in (0.5, 1.0, 7.0):
        for t in (1.0, 5.0, 10.0):
            assert auc_of_recall(torch.from_numpy(errors), t, min_error).item() == pytest.approx(
                reference_auc_min_error(errors, t, min_error), rel=1e-9), (min_error, t)
