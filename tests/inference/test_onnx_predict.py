"""An exported model runs on its own: predict from the .onnx file, the same network size and numbers as PyTorch."""

import json

import cv2
import numpy as np
import onnx
import pytest
import torch

from dapm_lightning.cli import main
from dapm_lightning.inference.predictor import DAPMPredictor
from dapm_lightning.models import DAPMConfig
from dapm_lightning.training.module import DAPMModule
from tests.inference.test_onnx import TINY

SIZES = [(128, 128), (180, 320), (240, 120), (750, 1000), (8, 10)]
"""(H, W) of the test images: square, wide, tall, large, tiny."""


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A tiny module (mostly ground, trained at 48 x 80) and its export."""
    torch.manual_seed(0)
    module = DAPMModule(net=DAPMConfig(**TINY)).eval()
    module.net.depth_pqb.blocks[0].body[-1].bias.data.fill_(-4.0)
    module.train_image_size = (48, 80)
    path = tmp_path_factory.mktemp("onnx") / "model.onnx"
    DAPMPredictor(module, onnx_path=path)  # exports: the file does not exist yet
    return module, path


@pytest.mark.parametrize("ending", ["interrupted", "mismatch", "passes"])
def test_the_api_export_is_moved_into_place_only_once_checked(tmp_path, monkeypatch, ending):
    """DAPMPredictor(module, onnx_path=...) exports when the file is missing: one interrupted during its check
    (Ctrl-C) or refused by it once left the file there, which the next call then ran as exported and checked."""
    import dapm_lightning.inference.onnx as onnx_module
    from tests.inference.test_onnx import tiny_net

    def fake_export(net, path, size, **kwargs):
        path.write_bytes(b"graph")
        (path.parent / (path.name + ".data")).write_bytes(b"weights")
        if ending == "interrupted":
            raise KeyboardInterrupt
        return [{"shape": (1, *size), "sky_prob": 0.5 if ending == "mismatch" else 0.0}]

    monkeypatch.setattr(onnx_module, "export_onnx", fake_export)
    path = tmp_path / "m.onnx"
    if ending == "passes":
        assert onnx_module.ensure_exported(tiny_net(), path) == path
        assert sorted(p.name for p in path.parent.iterdir()) == ["m.onnx", "m.onnx.data"]
        return
    with pytest.raises(KeyboardInterrupt if ending == "interrupted" else RuntimeError):
        onnx_module.ensure_exported(tiny_net(), path)
    assert list(path.parent.iterdir()) == []  # nothing at the path, no staging folder left


@pytest.mark.parametrize("content", ["cut short", "empty", "no digest"])
def test_the_api_export_names_a_file_there_it_cannot_compare(tmp_path, content):
    """A file at onnx_path that is not an ONNX model stopped with protobuf's bare DecodeError (no path, no fix); an
    export that records no weights digest (an older version's) was called 'of other weights than this
    checkpoint's', which nothing said."""
    from dapm_lightning.inference.onnx import METADATA_NET, ensure_exported
    from tests.inference.test_onnx import tiny_net

    path = tmp_path / "m.onnx"
    if content == "no digest":
        graph = onnx.helper.make_graph([onnx.helper.make_node("Identity", ["x"], ["y"])], "g",
                                       [onnx.helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, [1])],
                                       [onnx.helper.make_tensor_value_info("y", onnx.TensorProto.FLOAT, [1])])
        model = onnx.helper.make_model(graph)
        model.metadata_props.add(key=METADATA_NET, value="{}")
        onnx.save(model, str(path))
    else:
        path.write_bytes(b"" if content == "empty" else b"\x08\x07\x12\x07pytorch\x1a\xff\xff")
    before = path.read_bytes()
    expected = "records no weights digest" if content == "no digest" else "not a dapm-lightning export"
    with pytest.raises(FileExistsError, match=expected) as caught:
        ensure_exported(tiny_net(), path)
    assert str(path) in str(caught.value) and "Fix:" in str(caught.value)
    assert path.read_bytes() == before  # never overwritten


@pytest.mark.slow
def test_the_api_export_follows_the_weights_and_never_replaces_another_tools_file(exported, tmp_path):
    """``onnx_path`` kept running a file already there: after retraining, the old model, silently."""
    from dapm_lightning.inference.onnx import METADATA_NET, METADATA_ON_FIRST_USE, read_metadata, write_metadata

    module, first = exported
    path = tmp_path / "m.onnx"
    DAPMPredictor(module, onnx_path=path)
    written = path.stat().st_mtime_ns
    DAPMPredictor(module, onnx_path=path)  # the same weights: run as it is
    assert path.stat().st_mtime_ns == written
    retrained = DAPMModule(net=DAPMConfig(**TINY)).eval()
    retrained.load_state_dict(module.state_dict())
    retrained.train_image_size = module.train_image_size
    with torch.no_grad():
        for weights in retrained.parameters():
            weights.mul_(1.5)  # depth 40x and pitch 23 degrees apart from the first model's
    rgb = np.random.default_rng(0).integers(0, 255, (48, 80, 3), np.uint8)
    got, eager = DAPMPredictor(retrained, onnx_path=path)(rgb), DAPMPredictor(retrained)(rgb)  # exported again
    assert relative_depth_gap(got.depth_m, eager.depth_m) < 1e-3 and pose_gap(got.pose, eager.pose) < 0.05
    settings = json.loads(read_metadata(path)[METADATA_NET])
    other = {**settings, "igd": {**settings["igd"], "max_depth": 500.0}}  # as if exported with another depth limit
    write_metadata(path, {METADATA_NET: json.dumps(other, sort_keys=True)})
    DAPMPredictor(retrained, onnx_path=path)  # the same weights, other settings: exported again
    assert json.loads(read_metadata(path)[METADATA_NET]) == settings
    write_metadata(path, {METADATA_ON_FIRST_USE: "false"})  # as from dapm-lightning export: never overwritten
    with pytest.raises(FileExistsError, match="other weights or settings than this checkpoint's"):
        DAPMPredictor(module, onnx_path=path)
    assert read_metadata(path)[METADATA_ON_FIRST_USE] == "false"


def relative_depth_gap(got, expected):
    return float(np.median(np.abs(got - expected) / expected))


def pose_gap(got, expected):
    return max(abs(got[k] - expected[k]) for k in expected)


@pytest.mark.slow
@pytest.mark.parametrize("telemetry", [False, True])
def test_onnx_equals_eager_at_every_size_with_and_without_telemetry(exported, telemetry):
    module, path = exported
    eager = DAPMPredictor(module)
    alone = DAPMPredictor.from_checkpoint(path)  # the .onnx file only: settings and size from its metadata
    assert alone.module is None and alone.target == eager.target == (48, 80) and alone.spec == eager.spec
    rng = np.random.default_rng(1)
    prior = {"height_m": 35.0, "pitch_deg": -50.0} if telemetry else None
    for size in SIZES:
        rgb = rng.integers(0, 255, (*size, 3), np.uint8)
        want, got = eager(rgb, prior=prior), alone(rgb, prior=prior)
        assert got.depth_m.shape == size
        assert relative_depth_gap(got.depth_m, want.depth_m) < 1e-3, size
        assert pose_gap(got.pose, want.pose) < 0.05 and pose_gap(got.pose_network, want.pose_network) < 0.05
        assert got.pose_source == want.pose_source
        if telemetry:  # conditioning: the known components are the telemetry's, and the depth saw them
            assert got.pose["height"] == pytest.approx(35.0, abs=1e-3)
            assert pose_gap(got.pose_network, got.pose) > 0.1


@pytest.mark.slow
def test_the_file_says_what_it_is_and_a_foreign_file_is_refused(exported, tmp_path, capsys):
    _, path = exported
    metadata = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
    net = json.loads(metadata["dapm.net"])
    assert net["igd"]["max_depth"] == 1000.0 and json.loads(metadata["dapm.train_image_size"]) == [48, 80]
    assert metadata["dapm.pose_order"] == "height,pitch,roll,fov" and metadata["dapm.pose_units"] == "m,deg,deg,deg"
    assert metadata["dapm.depth_kind"] == "range" and metadata["dapm.sky_threshold"] == "0.5"
    foreign = tmp_path / "foreign.onnx"
    model = onnx.load(str(path))
    del model.metadata_props[:]
    onnx.save(model, str(foreign))
    images = tmp_path / "images"
    images.mkdir()
    cv2.imwrite(str(images / "a.png"), np.zeros((40, 60, 3), np.uint8))
    with pytest.raises(SystemExit) as info:
        main(["predict", str(images), "--ckpt_path", str(foreign), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert info.value.code == 1 and "foreign.onnx: not a dapm-lightning export" in err and "Traceback" not in err


@pytest.mark.slow
def test_cli_exports_then_predicts_from_the_onnx_file_alone(checkpoint, tmp_path, capsys):
    model = tmp_path / "model.onnx"
    main(["export", "--ckpt_path", str(checkpoint), "--out", str(model), "--checks", "1"])
    images = tmp_path / "images"
    images.mkdir()
    rng = np.random.default_rng(2)
    for name, size in (("wide", (30, 70)), ("tall", (64, 36))):
        cv2.imwrite(str(images / f"{name}.png"), rng.integers(0, 255, (*size, 3), np.uint8))
    table = tmp_path / "flight.csv"
    table.write_text("name,height_m,pitch_deg,roll_deg,fov_deg\nwide,40,-30,,\n")
    for ckpt, out in ((checkpoint, tmp_path / "eager"), (model, tmp_path / "onnx")):
        main(["predict", str(images), "--ckpt_path", str(ckpt), "--out", str(out), "--device", "cpu",
              "--telemetry", str(table), "--outputs", "depth_npy", "camera"])
    capsys.readouterr()
    for name in ("wide", "tall"):
        eager, onnx_depth = (np.load(tmp_path / kind / f"{name}_depth.npy") for kind in ("eager", "onnx"))
        assert eager.shape == onnx_depth.shape and relative_depth_gap(onnx_depth, eager) < 1e-3
        cameras = [json.loads((tmp_path / kind / f"{name}_camera.json").read_text()) for kind in ("eager", "onnx")]
        for key, entry in cameras[0]["pose"].items():
            assert entry["source"] == cameras[1]["pose"][key]["source"]
            assert abs(entry["value"] - cameras[1]["pose"][key]["value"]) < 0.05


@pytest.mark.slow
def test_a_fixed_size_export_predicts_batches_and_refuses_another_size_in_one_line(exported, tmp_path, capsys):
    """--dynamic false gives [1, 3, H, W]: a batch of several images once failed in onnxruntime (prior_known: 'Got 2
    Expected: 1'), and an image of another aspect with onnxruntime's INVALID_ARGUMENT, named as an unexpected error."""
    from dapm_lightning.inference.onnx import export_metadata, export_onnx

    module, dynamic = exported
    fixed = tmp_path / "fixed.onnx"
    export_onnx(module.net, fixed, (48, 80), checks=1, dynamic=False, metadata=export_metadata(module.net, (48, 80)))
    rng = np.random.default_rng(3)
    frames = [rng.integers(0, 255, (96, 160, 3), np.uint8) for _ in range(3)]  # the training aspect: 48 x 80
    prior = {"height_m": 35.0}
    want = DAPMPredictor.from_checkpoint(dynamic)(frames, prior=[prior, None, prior])
    got = DAPMPredictor.from_checkpoint(fixed, batch_size=3)(frames, prior=[prior, None, prior])
    for a, b in zip(got, want):
        assert relative_depth_gap(a.depth_m, b.depth_m) < 1e-4 and pose_gap(a.pose, b.pose) < 1e-3
    images = tmp_path / "images"
    images.mkdir()
    cv2.imwrite(str(images / "square.png"), frames[0][:, :96])
    with pytest.raises(SystemExit) as info:
        main(["predict", str(images), "--ckpt_path", str(fixed), "--out", str(tmp_path / "out"), "--device", "cpu"])
    err = capsys.readouterr().err
    assert info.value.code == 1 and "Traceback" not in err and "possibly a bug" not in err, err
    assert f"{fixed}: exported at the fixed size 48x80 (--dynamic false); this image's network size is" in err
    assert "Fix: export it again with dynamic sizes" in err


@pytest.mark.parametrize("takes_prior", [False, True])
def test_a_model_that_takes_no_prior_applies_the_known_pose_afterwards(tmp_path, monkeypatch, takes_prior):
    """An exported model without the prior inputs cannot be conditioned: the telemetry is fitted to its depth
    afterwards (``scale``), whatever mode was asked for; one that takes them keeps the mode asked for."""
    import dapm_lightning.inference.predictor as predictor_module

    class Exported:  # an OnnxRuntime, as far as the predictor looks at one
        def __init__(self, path):
            self.takes_prior, self.train_image_size, self.config = takes_prior, (32, 32), DAPMConfig()

    monkeypatch.setattr(predictor_module, "OnnxRuntime", Exported)
    predictor = DAPMPredictor(None, onnx_path=tmp_path / "model.onnx", telemetry_mode="both", igd_bound=0.3)
    assert predictor.prior_settings.mode == ("both" if takes_prior else "scale")
    assert predictor.prior_settings.igd_bound == 0.3


def test_the_onnx_feed_puts_no_nan_in_the_graph_and_each_image_keeps_its_own_prior():
    """Unknown components enter as 0 with prior_known false (a NaN would spread through the fused pose); a model
    exported for one image at a time is given each image's own row of the batch's prior."""
    from dapm_lightning.inference.onnx import PRIOR_INPUTS, onnx_feed
    from dapm_lightning.inference.prior import as_prior
    from dapm_lightning.inference.runtime import _prior_row

    nan = float("nan")
    prior = as_prior([[50.0, nan, nan, 70.0], [nan, -40.0, 1.0, nan]], sigma=(2.0, 0.0, 0.0, 1.0))
    feed = onnx_feed(np.zeros((2, 3, 8, 8), np.float32), ["image", *PRIOR_INPUTS], prior)
    assert feed["prior"].tolist() == [[50.0, 0.0, 0.0, 70.0], [0.0, -40.0, 1.0, 0.0]]
    assert feed["prior_known"].tolist() == [[True, False, False, True], [False, True, True, False]]
    assert feed["prior_sigma"].tolist() == [[2.0, 0.0, 0.0, 1.0]] * 2
    second = _prior_row(prior, 1)
    assert second.value.shape == (1, 4) and second.known.tolist() == [[False, True, True, False]]
    assert second.value[0, 1:3].tolist() == [-40.0, 1.0]


def test_the_onnx_runtime_reports_the_network_s_own_pose_only_when_it_was_given_a_prior():
    """Without a prior the pose used is the network's own, as PyTorch reports it: no `pose_network` output (the
    graph always has one). With a prior it is kept, and a one-image-at-a-time model is run image by image."""
    from dapm_lightning.inference.onnx import PRIOR_INPUTS
    from dapm_lightning.inference.prior import as_prior
    from dapm_lightning.inference.runtime import OnnxRuntime

    class Session:  # an exported model's outputs, one image a row; what it was fed is kept
        def __init__(self):
            self.feeds = []

        def run(self, _names, feed):
            self.feeds.append(feed)
            batch = feed["image"].shape[0]
            pose = np.tile(np.float32([[40.0, -45.0, 1.0, 70.0]]), (batch, 1))
            return [np.ones((batch, 1, 4, 4), np.float32), pose, pose + 1]

    runtime = object.__new__(OnnxRuntime)
    runtime.path, runtime.session = "model.onnx", Session()
    runtime.input_names, runtime.names = ["image", *PRIOR_INPUTS], ["depth_m", "pose", "pose_network"]
    runtime.takes_prior, runtime.fixed_batch, runtime.fixed_size = True, None, None
    images = torch.rand(2, 3, 4, 4)
    alone = runtime(images)
    assert alone.pose_network is None and alone.pose.shape == (2, 4)
    given = runtime(images, as_prior([[50.0, float("nan"), float("nan"), 60.0]] * 2, sigma=(2.0, 0.0, 0.0, 1.0)))
    assert given.pose_network is not None and given.pose_network[0].tolist() == [41.0, -44.0, 2.0, 71.0]
    runtime.fixed_batch = 1
    assert runtime(images).pose_network is None and [f["image"].shape[0] for f in runtime.session.feeds[-2:]] == [1, 1]
