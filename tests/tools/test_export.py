import onnxruntime
import pytest
import torch

from dapm_lightning.cli import main
from dapm_lightning.models import DAPMConfig, DAPMNet
from dapm_lightning.tools.export import export_onnx


def test_onnx_matches_pytorch(tmp_path):
    torch.manual_seed(0)
    net = DAPMNet(DAPMConfig(backbone="resnet18")).eval()
    net.depth_pqb.blocks[0].body[-1].bias.data.fill_(-4.0)  # mostly ground, so depth is not all sky
    diffs = export_onnx(net, str(tmp_path / "m.onnx"), (64, 96), checks=2)
    for diff in diffs:
        assert diff["depth_m"] < 1e-2 and diff["sky_prob"] < 1e-4 and diff["pose"] < 1e-3
    session = onnxruntime.InferenceSession(str(tmp_path / "m.onnx"))
    assert [o.name for o in session.get_outputs()] == ["depth_m", "sky_prob", "pose"]
    assert session.get_outputs()[0].shape == [1, 1, 64, 96]


def test_cli_export(checkpoint, tmp_path, capsys):
    out = tmp_path / "model.onnx"
    main(["export", "--ckpt_path", str(checkpoint), "--out", str(out), "--height", "32", "--width", "64",
          "--checks", "1"])
    printed = capsys.readouterr().out
    assert out.is_file() and "max |onnxruntime - PyTorch|" in printed


def test_depth_only_model_is_refused(tmp_path):
    with pytest.raises(ValueError, match="full DAPM"):
        export_onnx(DAPMNet(DAPMConfig(backbone="resnet18", use_pose=False, use_igd_feature=False)).eval(),
                    tmp_path / "m.onnx", (32, 32))
