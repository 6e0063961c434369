"""int8 ONNX (onnxruntime static QDQ quantisation calibrated on rendered images) runs wherever float ONNX runs."""

import numpy as np
import onnx
import pytest
import torch

from dapm_lightning.cli import main
from dapm_lightning.inference.onnx import export_onnx
from dapm_lightning.inference.predictor import DAPMPredictor
from dapm_lightning.inference.quantize import quantize_int8, synthetic_calibration
from dapm_lightning.models import DAPMConfig
from dapm_lightning.training.module import DAPMModule
from tests.inference.test_onnx import TINY


def test_int8_model_quantises_and_the_predictor_takes_it_like_any_onnx_file(tmp_path):
    torch.manual_seed(0)
    module = DAPMModule(net=DAPMConfig(**TINY))
    module.net.depth_pqb.blocks[0].body[-1].bias.data.fill_(-4.0)  # mostly ground, so depth is not all sky
    float_path, int8_path = tmp_path / "model.onnx", tmp_path / "model_int8.onnx"
    export_onnx(module.net.eval(), float_path, (64, 64), checks=1)
    calibration = synthetic_calibration((64, 64), 4)
    assert calibration[0].shape == (1, 3, 64, 64) and calibration[0].dtype == np.float32
    assert 0.0 <= calibration[0].min() and calibration[0].max() <= 1.0 and calibration[0].std() > 0.01
    quantize_int8(float_path, int8_path, calibration)
    graph = onnx.load(str(int8_path)).graph
    assert sum(n.op_type == "QuantizeLinear" for n in graph.node) > 10  # QDQ format
    assert any(t.data_type == onnx.TensorProto.INT8 for t in graph.initializer)  # int8 weights
    rgb = (synthetic_calibration((50, 80), 1, seed=3)[0][0].transpose(1, 2, 0) * 255).astype(np.uint8)
    eager = DAPMPredictor(module, image_width=64)(rgb)
    float_onnx = DAPMPredictor(module, image_width=64, onnx_path=float_path)(rgb)
    int8 = DAPMPredictor(module, image_width=64, onnx_path=int8_path)(rgb)
    assert int8.depth_m.shape == eager.depth_m.shape == (50, 80) and np.isfinite(int8.depth_m).all()
    assert not np.array_equal(int8.depth_m, float_onnx.depth_m)  # the int8 model ran, not the float one
    ground = eager.depth_m < 900
    assert ground.mean() > 0.5
    np.testing.assert_allclose(int8.depth_m[ground], eager.depth_m[ground], rtol=0.5)
    assert int8.pose.keys() == eager.pose.keys()
    np.testing.assert_allclose([int8.pose[k] for k in eager.pose], list(eager.pose.values()), atol=10.0)


@pytest.mark.slow
def test_cli_export_int8(checkpoint, tmp_path, capsys):
    out = tmp_path / "model_int8.onnx"
    main(["export", "--ckpt_path", str(checkpoint), "--out", str(out), "--height", "64", "--width", "64",
          "--checks", "1", "--int8", "true", "--calibration_images", "4"])
    printed = capsys.readouterr().out
    assert out.is_file() and (tmp_path / "model.onnx").is_file()
    assert "int8 (QDQ), calibrated on 4 synthetic images" in printed and "max |int8 - float32|" in printed
    with pytest.raises(SystemExit):
        main(["export", "--ckpt_path", str(checkpoint), "--int8", "true", "--fp16", "true"])
    assert "leave --fp16 out" in capsys.readouterr().err


@pytest.mark.slow
def test_int8_benchmark_compares_the_three_side_by_side():
    from benchmarks.bench_predict import format_int8, int8_compare

    rows = int8_compare(backbone="resnet18", size=64, images=2, calibration_images=2, threads=1)
    assert [r["variant"] for r in rows] == ["eager", "onnx float32", "onnx int8"]
    assert rows[0]["speedup"] == 1.0 and rows[0]["d1_change"] == 0.0 and rows[0]["worst_median_growth"] == 0.0
    assert rows[1]["d1_change"] == pytest.approx(0.0, abs=1e-6)  # float ONNX = eager
    assert all(r["median_ms"] > 0 and 0 <= r["d1"] <= 1 for r in rows)
    assert "onnx int8" in format_int8(rows, "title")
