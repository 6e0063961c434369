"""The authors' pose protocol (their test.py): 3-point AUC through (0, 0), (1, r1), (5, r5), (10, r10), and MAE."""

import pytest
import torch

from dapm_lightning.metrics import AuthorsPoseMetrics, PoseMetrics, authors_auc


def poses_with_errors(errors):
    """``[N, 4]`` predictions and truths whose absolute error is ``errors`` in every component."""
    errors = torch.as_tensor(errors, dtype=torch.float64)
    target = torch.tensor([50.0, -60.0, 5.0, 80.0], dtype=torch.float64).repeat(len(errors), 1)
    signs = torch.where(torch.arange(len(errors)) % 2 == 0, 1.0, -1.0).double()[:, None]
    return target + signs * errors[:, None], target


def test_three_point_auc_and_mae_by_hand():
    # recall at 1, 5, 10: 1/5, 3/5, 4/5 (an error equal to a threshold counts, as errs <= t)
    pred, target = poses_with_errors([0.5, 2.0, 5.0, 7.0, 20.0])
    metric = AuthorsPoseMetrics()
    metric.update(pred[:2], target[:2])  # two updates: sum states
    metric.update(pred[2:], target[2:])
    got = metric.compute()
    # AUC@1 = 0.5*0.2*1 / 1; AUC@5 = (0.1 + 0.5*(0.2+0.6)*4) / 5; AUC@10 = (1.7 + 0.5*(0.6+0.8)*5) / 10
    for key in ("height", "pitch", "roll", "fov"):
        assert got[f"{key}_auc1"].item() == pytest.approx(0.1, rel=1e-6)
        assert got[f"{key}_auc5"].item() == pytest.approx(0.34, rel=1e-6)
        assert got[f"{key}_auc10"].item() == pytest.approx(0.52, rel=1e-6)
        assert got[f"{key}_mae"].item() == pytest.approx(34.5 / 5, rel=1e-6)


def test_two_processes_merged_equal_one():
    """Sum states: two "processes" (1 and 4 images) merged as DDP reduces them give the by-hand figures of all 5."""
    pred, target = poses_with_errors([0.5, 2.0, 5.0, 7.0, 20.0])
    a, b = AuthorsPoseMetrics(), AuthorsPoseMetrics()
    a.update(pred[:1], target[:1])
    b.update(pred[1:], target[1:])
    a.merge_state(b)
    got = a.compute()
    assert got["roll_auc5"].item() == pytest.approx(0.34, rel=1e-6)
    assert got["height_mae"].item() == pytest.approx(34.5 / 5, rel=1e-6)


def test_differs_from_geocalib_auc_on_the_same_errors():
    # GeoCalib's AUC@5 follows every error, the authors' only the recalls at 1 and 5
    pred, target = poses_with_errors([0.5, 2.0, 3.0, 7.0, 20.0])
    geocalib, authors = PoseMetrics(), AuthorsPoseMetrics()
    geocalib.update(pred, target)
    authors.update(pred, target)
    # exact: 0.5*0.2*0.5 + 0.5*(0.2+0.4)*1.5 + 0.5*(0.4+0.6)*1 + 0.6*2 = 2.2 -> 0.44; authors: (0.1 + 1.6) / 5 = 0.34
    assert geocalib.compute()["roll_auc5"].item() == pytest.approx(0.44, rel=1e-6)
    assert authors.compute()["roll_auc5"].item() == pytest.approx(0.34, rel=1e-6)


def test_authors_auc_formula_with_other_thresholds():
    # thresholds (2, 4): curve (0,0), (2, r2), (4, r4)
    areas = authors_auc([0.5, 1.0], (2.0, 4.0))
    assert [a.item() for a in areas] == pytest.approx([0.25, (0.5 + 1.5) / 4])


def test_bad_thresholds_and_shapes_are_refused():
    with pytest.raises(ValueError, match="increasing"):
        AuthorsPoseMetrics(thresholds=(5.0, 1.0))
    with pytest.raises(ValueError, match=r"\[B, 4\]"):
        AuthorsPoseMetrics().update(torch.zeros(2, 3), torch.zeros(2, 3))
