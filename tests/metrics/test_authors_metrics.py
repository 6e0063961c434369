"""The authors' depth protocol (docs/model.md): grey levels, sky included, pixels pooled, against a plain loop."""

import math

import numpy as np
import pytest
import torch

from dapm_lightning.geometry import MAX_DEPTH_M, encode_log_depth
from dapm_lightning.metrics import AUTHORS_DEPTH_METRIC_NAMES, AuthorsDepthMetrics, DepthMetrics


def reference(preds, targets):
    """The authors' formulas written plainly on all pixels of all images at once (numpy, float64)."""
    p = np.concatenate([255 * encode_log_depth(x.double()).numpy().ravel() for x in preds]).clip(1e-3)
    t = np.concatenate([255 * encode_log_depth(x.double()).numpy().ravel() for x in targets]).clip(1e-3)
    ratio = np.maximum(p / t, t / p)
    d = np.log(p) - np.log(t)
    rmse = math.sqrt(np.mean((t - p) ** 2))
    return {"d1": np.mean(ratio < 1.25), "d2": np.mean(ratio < 1.25 ** 2), "d3": np.mean(ratio < 1.25 ** 3),
            "abs_rel": np.mean(np.abs(t - p) / t), "sq_rel": np.mean((t - p) ** 2 / t), "rmse_grey": rmse,
            "rmse_unit": rmse / 255, "rmse_log": math.sqrt(np.mean(d ** 2)),
            "log10": np.mean(np.abs(np.log10(p) - np.log10(t))),
            "silog": 100 * math.sqrt(max(np.mean(d ** 2) - np.mean(d) ** 2, 0))}


def batches():
    g = torch.Generator().manual_seed(0)
    targets = [torch.rand(2, 1, 6, 8, generator=g) * 300 + 0.5 for _ in range(3)]
    for t in targets:
        t[:, :, :2] = MAX_DEPTH_M  # sky rows: counted as grey 255
    targets[2][1] = MAX_DEPTH_M  # an all-sky image
    # errors of up to 30x either way on the ground, sky predicted as sky
    preds = [torch.where(t >= MAX_DEPTH_M, t, t * 30 ** (2 * torch.rand(t.shape, generator=g) - 1)) for t in targets]
    return preds, targets


def test_matches_the_plain_pooled_loop_and_splits_exactly():
    preds, targets = batches()
    metric = AuthorsDepthMetrics()
    for p, t in zip(preds, targets):
        metric.update(p, t)
    result, expected = metric.compute(), reference(preds, targets)
    assert set(result) == set(AUTHORS_DEPTH_METRIC_NAMES)
    for name in AUTHORS_DEPTH_METRIC_NAMES:
        assert result[name].item() == pytest.approx(expected[name], rel=1e-5, abs=1e-7), name
    # the states are sums: two "processes" merged give the single-process figures (what DDP's sum reduction does)
    a, b = AuthorsDepthMetrics(), AuthorsDepthMetrics()
    a.update(preds[0], targets[0])
    for p, t in zip(preds[1:], targets[1:]):
        b.update(p, t)
    a.merge_state(b)
    for name in AUTHORS_DEPTH_METRIC_NAMES:
        assert a.compute()[name].item() == pytest.approx(result[name].item(), rel=1e-6), name


def test_differs_from_the_toolbox_protocol_where_the_design_says():
    preds, targets = batches()
    authors, toolbox = AuthorsDepthMetrics(), DepthMetrics(space="uapd_log")
    for p, t in zip(preds, targets):
        authors.update(p, t)
        toolbox.update(p, t)
    # sky pixels predicted exactly count as perfect in the authors' protocol only: more d1, lower AbsRel
    assert authors.compute()["d1"] > toolbox.compute()["d1"]
    assert authors.compute()["abs_rel"] < toolbox.compute()["abs_rel"]
    assert authors.compute()["rmse_unit"].item() == pytest.approx(authors.compute()["rmse_grey"].item() / 255, rel=1e-6)


def test_zero_metres_is_clamped_and_empty_is_nan():
    metric = AuthorsDepthMetrics()
    assert all(math.isnan(v) for v in metric.compute().values())
    metric.update(torch.zeros(1, 1, 1, 2), torch.tensor([[[[0.0, float("nan")]]]]))  # NaN targets are left out
    result = metric.compute()
    assert result["d1"] == 1.0 and result["rmse_grey"] == 0.0 and metric.pixels == 1
