"""ViewpointBreakdown and EvaluationOutputWriter: per-image depth figures with the model's depth limit."""

import types

import torch

from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.metrics import DepthMetrics
from dapm_lightning.models import DAPMConfig, DAPMNet
from dapm_lightning.training.evaluation_outputs import EvaluationOutputWriter
from dapm_lightning.training.viewpoints import ViewpointBreakdown, viewpoint_table

LIMIT = 500.0


def sky_and_ground(limit=LIMIT):
    """Two images whose top 12 of 32 rows are sky (``limit``, predicted exactly) and the rest 50 % too far."""
    torch.manual_seed(0)
    config = DAPMConfig(backbone="resnet18", pretrained=False, decoder_channels=16, head_channels=8, igd_channels=4,
                        pose_hidden=16, igd=IGDSpec(max_depth=limit))
    with torch.no_grad():
        out = DAPMNet(config).eval()(torch.rand(2, 3, 32, 48))
    out.depth.depth_m[:] = 150.0
    out.depth.depth_m[:, :, :12] = limit
    depth = torch.full_like(out.depth_m, 100.0)
    depth[:, :, :12] = limit
    batch = {"image": torch.rand(2, 3, 32, 48), "depth": depth, "pose": torch.tensor([[50.0, -60.0, 0.0, 80.0]] * 2),
             "has_pose": torch.tensor([True, True]), "name": ["a", "b"]}
    return types.SimpleNamespace(net_config=config), out, batch


def test_viewpoint_d1_leaves_out_the_sky_of_a_500_m_limit_as_test_depth_d1_does():
    module, out, batch = sky_and_ground()
    logged = DepthMetrics(max_depth=LIMIT)  # what the module logs as test_depth_d1
    logged.update(out.depth_m, batch["depth"])
    breakdown = ViewpointBreakdown()
    breakdown.on_test_batch_end(None, module, out, batch, 0)
    # with UAPD's 1000 m the sky at 500 m counted as valid and exact: 12 / 32 = 0.375 instead of 0
    assert logged.compute()["d1"].item() == 0.0
    assert breakdown.records[0][:, 4].tolist() == [0.0, 0.0]


def test_per_image_csv_uses_the_model_limit_unless_given_one(tmp_path):
    module, out, batch = sky_and_ground()
    for given, d1 in ((None, 0.0), (1000.0, 0.375)):
        limit = {} if given is None else {"max_depth": given}
        writer = EvaluationOutputWriter(dirpath=str(tmp_path / str(given)), write_maps=False, **limit)
        writer.on_test_start(None, module)
        writer.on_test_batch_end(None, module, out, batch, 0)
        assert [row["depth_d1"] for row in writer._rows] == [d1, d1], given


def test_viewpoint_median_error_of_an_even_count_is_numpy_s():
    # two images in the same bins, roll errors 1 and 3 degrees: median 2 (torch.median gave 1)
    records = torch.tensor([[50.0, -60.0, 0.0, 80.0, 1.0, 0.5, 0.5, 1.0, 0.5],
                            [51.0, -61.0, 1.0, 81.0, 1.0, 1.5, 1.5, 3.0, 1.5]])
    rows = [r for r in viewpoint_table(records) if r["count"] == 2]
    assert {r["component"]: r["error"] for r in rows} == {"height": 1.0, "pitch": 1.0, "roll": 2.0, "fov": 1.0}


def test_viewpoint_bins_are_half_open_and_the_range_ends_count_in_the_end_bins():
    """Bins [low, high): a pose on an inner edge is in the bin it starts; the range's ends (and beyond) in the end
    bins, so that every image is counted once per component."""
    from dapm_lightning.geometry.constants import POSE_KEYS, POSE_RANGES

    lows, highs = ([POSE_RANGES[key][end] for key in POSE_KEYS] for end in (0, 1))
    edge = [lo + (hi - lo) / 5 for lo, hi in zip(lows, highs)]  # the first inner edge of 5 bins
    beyond = [hi + 1 for hi in highs]
    records = torch.tensor([[*pose, 1.0, 0.0, 0.0, 0.0, 0.0] for pose in (lows, highs, edge, beyond)])
    rows = viewpoint_table(records, bins=5)
    for key in POSE_KEYS:
        counts = [r["count"] for r in rows if r["component"] == key]
        assert counts == [1, 1, 0, 0, 2], key


def test_viewpoint_d1_is_the_mean_of_the_bins_images():
    records = torch.tensor([[50.0, -60.0, 0.0, 80.0, d1, 0.0, 0.0, 0.0, 0.0] for d1 in (0.0, 0.0, 0.9)])
    assert {round(r["d1"], 6) for r in viewpoint_table(records) if r["count"] == 3} == {0.3}


def test_igd_maps_give_the_true_pose_s_only_when_every_image_has_one():
    from dapm_lightning.training.evaluation_outputs import igd_maps

    module, out, batch = sky_and_ground()
    assert set(igd_maps(out, batch, module.net_config.igd)) == {"igd_pred", "igd_true"}
    mixed = {**batch, "has_pose": torch.tensor([True, False]),
             "pose": torch.tensor([[50.0, -60.0, 0.0, 80.0], [float("nan")] * 4])}
    assert set(igd_maps(out, mixed, module.net_config.igd)) == {"igd_pred"}

