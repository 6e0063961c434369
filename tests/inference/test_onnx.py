from pathlib import Path

import numpy as np
import onnxruntime
import pytest
import torch
import yaml

from dapm_lightning.cli import main
from dapm_lightning.inference.onnx import CHECK_DRAW, DEPTH_SHARE_OFF, export_mismatches, export_onnx
from dapm_lightning.models import DAPMConfig, DAPMNet
from dapm_lightning.models.blocks import adaptive_avg_pool2d_symbolic

TINY = {"backbone": "resnet18", "decoder_channels": 16, "head_channels": 8, "igd_channels": 4, "pose_hidden": 16,
        "depth_bins": (2, 4), "pose_bins": (4,)}


def tiny_net(**overrides):
    torch.manual_seed(0)
    net = DAPMNet(DAPMConfig(**{**TINY, **overrides})).eval()
    if net.config.use_depth:
        net.depth_pqb.blocks[0].body[-1].bias.data.fill_(-4.0)  # mostly ground, so depth is not all sky
    return net


def test_size_symbolic_pooling_equals_pytorch():
    for shape, n in (((2, 1, 8, 12), 8), ((1, 3, 20, 7), 8), ((1, 1, 64, 64), 8), ((2, 2, 9, 31), (4, 5))):
        x = torch.rand(*shape, dtype=torch.float64)
        torch.testing.assert_close(adaptive_avg_pool2d_symbolic(x, n), torch.nn.functional.adaptive_avg_pool2d(x, n))


@pytest.mark.slow
def test_dynamic_onnx_matches_pytorch_at_other_sizes(tmp_path):
    net = tiny_net()
    rows = export_onnx(net, tmp_path / "m.onnx", (64, 96), checks=1)
    assert [r["shape"] for r in rows] == [(1, 64, 96), (2, 51, 117)]  # batch, height and width all changed
    for row in rows:  # at ~21 m: to 1e-2 m at the export size and at any other (odd sides: ceil divisions exported)
        assert row["depth_m"] < 1e-2 and row["sky_prob"] < 1e-4 and row["pose"] < 1e-3, row
        assert row[DEPTH_SHARE_OFF] == 0.0
    assert export_mismatches(rows) == []
    session = onnxruntime.InferenceSession(str(tmp_path / "m.onnx"))
    assert [o.name for o in session.get_outputs()] == ["depth_m", "sky_prob", "pose", "pose_network", "pose_spread"]
    assert [i.name for i in session.get_inputs()] == ["image", "prior", "prior_known", "prior_sigma"]
    batch, _, height, width = session.get_inputs()[0].shape
    assert all(isinstance(d, str) for d in (batch, height, width))  # symbolic: dynamic
    nothing_known = {"prior": torch.zeros(3, 4).numpy(), "prior_known": torch.zeros(3, 4, dtype=torch.bool).numpy(),
                     "prior_sigma": torch.zeros(3, 4).numpy()}
    depth = session.run(["depth_m"], {"image": torch.rand(3, 3, 90, 161).numpy(), **nothing_known})[0]
    assert depth.shape == (3, 1, 90, 161) and (depth < 1000).any()  # any size, not only multiples of 32


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["depth_only", "pose_only", "fp16", "fixed", "told", "pooled"])
def test_every_variant_exports(kind, tmp_path):
    overrides = {"depth_only": {"use_pose": False, "use_igd_feature": False},
                 "pose_only": {"use_depth": False, "use_igd_feature": False},
                 "told": {"pose_prior_input": True, "depth_prior_input": True},
                 "pooled": {"pose_pool_grid": 3}}.get(kind, {})  # uneven cells at the other sizes checked
    rows = export_onnx(tiny_net(**overrides), tmp_path / "m.onnx", (64, 64), checks=1, fp16=kind == "fp16",
                       dynamic=kind != "fixed")
    with_prior = ["pose", "pose_network", "pose_spread"]
    names = {"depth_only": ["depth_m", "sky_prob"], "pose_only": with_prior}.get(kind, ["depth_m", "sky_prob",
                                                                                        *with_prior])
    assert [k for k in rows[0] if k not in ("shape", CHECK_DRAW, DEPTH_SHARE_OFF)] == names
    depth_tol, pose_tol = (2.0, 0.2) if kind == "fp16" else (1e-2, 1e-3)  # metres at ~21 m / degrees
    for row in rows[:1]:  # the export size
        assert row.get("depth_m", 0) < depth_tol and row.get("pose", 0) < pose_tol
    for row in rows[1:]:  # another aspect, odd sides: resizing rounds differently in onnxruntime, within 1 %
        assert row.get("depth_m", 0) < max(depth_tol, 0.2) and row.get("pose", 0) < max(pose_tol, 0.05)
    if kind == "fp16":
        import onnx

        model = onnx.load(str(tmp_path / "m.onnx"))
        assert {i.data_type for i in model.graph.initializer if len(i.dims) == 4} == {onnx.TensorProto.FLOAT16}
        assert model.graph.input[0].type.tensor_type.elem_type == onnx.TensorProto.FLOAT


@pytest.mark.slow
def test_the_largest_side_allowed_exports(tmp_path):
    """--height 8192 is allowed (32 to 8192): the export traced it at 8193, outside the graph's range of sides
    (torch.export's ConstraintViolationError '8193 not in range [32, 8192]')."""
    from dapm_lightning.inference.onnx import MAX_EXPORT_SIDE

    net = tiny_net(use_pose=False, use_igd_feature=False)
    rows = export_onnx(net, tmp_path / "m.onnx", (MAX_EXPORT_SIDE, 32), checks=1)
    assert [r["shape"] for r in rows] == [(1, MAX_EXPORT_SIDE, 32), (2, MAX_EXPORT_SIDE - 13, 53)]
    assert export_mismatches(rows) == []


def test_cli_export_settings_from_a_config_file(tmp_path, capsys):
    config = tmp_path / "export.yaml"
    config.write_text(yaml.safe_dump({"ckpt_path": str(tmp_path / "model.ckpt"), "height": 64, "fp16": True}))
    with pytest.raises(SystemExit) as info:
        main(["export", "--config", str(config), "--width", "96", "--print_config"])
    assert info.value.code == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["height"] == 64 and printed["width"] == 96 and printed["fp16"] is True
    for argv in (["CKPT", "--fp16"], ["--ckpt_path", "CKPT", "--fp16", "true"], ["CKPT", "--int8", "--no_dynamic"]):
        with pytest.raises(SystemExit) as info:  # the checkpoint positional, booleans as flags
            main(["export", *[str(tmp_path / "x.ckpt") if a == "CKPT" else a for a in argv], "--print_config"])
        printed = yaml.safe_load(capsys.readouterr().out)
        assert info.value.code == 0 and printed["ckpt_path"] == str(tmp_path / "x.ckpt"), argv
        assert printed["fp16"] is ("--fp16" in argv) and printed["int8"] is ("--int8" in argv), argv
        assert printed["dynamic"] is ("--no_dynamic" not in argv), argv
    with pytest.raises(SystemExit) as info:  # a missing checkpoint: a short message, exit 1
        main(["export", "--config", str(config)])
    assert info.value.code == 1 and "model.ckpt: no such checkpoint file" in capsys.readouterr().err


SHIPPED = Path(__file__).resolve().parents[2] / "models" / "dapm-synthetic-r18-256"


def test_export_refuses_an_out_it_would_wrongly_replace_and_sizes_it_cannot_export(tmp_path, capsys):
    """Checked before the checkpoint is read: a user's checkpoint given as --out stays whole."""
    ckpt = tmp_path / "model.ckpt"
    ckpt.write_bytes(b"precious")
    for argv, message in ((["--out", str(ckpt)], "model.ckpt: an exported model is written to a file ending in .onnx"),
                          (["--out", str(tmp_path / "notes.txt")], "Fix: --out " + str(tmp_path / "notes.onnx")),
                          (["--out", str(tmp_path)], "is a folder.\nFix: give the file to write"),
                          (["--out", str(ckpt / "m.onnx")],
                           f"{ckpt}: cannot be written (it is a file, not a folder)\nFix: give another output folder"),
                          (["--height", "16"], "--height 16: an exported model takes sides of 32 to 8192"),
                          (["--width", "9000"], "--width 9000: an exported model takes sides of 32 to 8192"),
                          (["--checks", "0"], "--checks 0: at least 1"),  # once: IndexError, the file unchecked
                          (["--int8", "--verdict_images", "0"], "--verdict_images 0: at least 1")):
        with pytest.raises(SystemExit) as info:
            main(["export", "--ckpt_path", str(ckpt), *argv])
        err = capsys.readouterr().err
        assert info.value.code == 1 and message in err and "Traceback" not in err, (argv, err)
    assert ckpt.read_bytes() == b"precious" and sorted(p.name for p in tmp_path.iterdir()) == ["model.ckpt"]


@pytest.mark.parametrize("mismatch", [False, True])
def test_export_replaces_an_earlier_one_only_once_checked(tmp_path, capsys, monkeypatch, mismatch):
    """The export is written beside the target and moved there once it passes: one that fails leaves the earlier
    file and its weights as they were; one that passes replaces both (and drops weights its graph does not use)."""
    import dapm_lightning.tools.export as export_tool

    def fake_export(net, path, size, **kwargs):
        path.write_bytes(b"new graph")
        if not mismatch:
            (path.parent / (path.name + ".data")).write_bytes(b"new weights")
        row = {"shape": (1, *size), "depth_m": 1e-4, "sky_prob": 0.5 if mismatch else 1e-6, "pose": 1e-4}
        return [row]
    monkeypatch.setattr(export_tool, "export_onnx", fake_export)
    out = tmp_path / "shipped.onnx"
    out.write_bytes(b"earlier graph")
    (tmp_path / "shipped.onnx.data").write_bytes(b"earlier weights")
    if mismatch:
        with pytest.raises(export_tool.ExportMismatch, match="so it was not written .the earlier shipped.onnx there "
                                                             "is left as it was"):
            export_tool.export(SHIPPED, out, height=64, width=64)
        assert "exported, not written:" in capsys.readouterr().out
        assert out.read_bytes() == b"earlier graph"
        assert (tmp_path / "shipped.onnx.data").read_bytes() == b"earlier weights"
    else:
        assert export_tool.export(SHIPPED, out, height=64, width=64) == out
        assert out.read_bytes() == b"new graph" and (tmp_path / "shipped.onnx.data").read_bytes() == b"new weights"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["shipped.onnx", "shipped.onnx.data"]  # no staging left


def test_an_export_stopped_or_refused_leaves_no_folder_it_made(tmp_path, monkeypatch):
    """Ctrl-C during the export (or a refused one) left the new, empty --out folder behind."""
    import dapm_lightning.tools.export as export_tool

    def interrupted(net, path, size, **kwargs):
        path.write_bytes(b"half a graph")
        raise KeyboardInterrupt

    monkeypatch.setattr(export_tool, "export_onnx", interrupted)
    with pytest.raises(KeyboardInterrupt):
        export_tool.export(SHIPPED, tmp_path / "new" / "models" / "m.onnx", height=64, width=64)
    assert list(tmp_path.iterdir()) == []


def test_a_folder_that_refuses_the_export_is_named_as_out_not_the_hidden_staging(tmp_path, capsys, monkeypatch):
    """/sys passes the writable check (root) yet refuses a folder: the message names --out, as does a disk that
    fills while exporting; the hidden staging folder beside it is not named and not left."""
    import errno

    import dapm_lightning.tools.export as export_tool

    out = tmp_path / "dapm.onnx"

    def refuse(*args, **kwargs):
        raise PermissionError(errno.EPERM, "Operation not permitted", str(tmp_path / ".dapm.onnx.x1y2z3"))

    from types import SimpleNamespace

    monkeypatch.setattr(export_tool, "tempfile", SimpleNamespace(mkdtemp=refuse))  # the staging only, not the check
    with pytest.raises(SystemExit) as info:
        main(["export", str(SHIPPED), "--out", str(out)])
    err = capsys.readouterr().err
    assert info.value.code == 1 and err.splitlines()[:2] == [
        f"error: {out}: cannot be written (Operation not permitted)",
        "Fix: write to a folder you may write to (this one is read-only or not yours) (--out)"], err
    monkeypatch.undo()

    def fill(net, path, size, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(export_tool, "export_onnx", fill)
    with pytest.raises(SystemExit) as info:
        main(["export", str(SHIPPED), "--out", str(out), "--height", "64", "--width", "64"])
    err = capsys.readouterr().err
    assert info.value.code == 1 and err.splitlines()[0] == f"error: {out}: cannot be written (No space left on device)"
    assert list(tmp_path.iterdir()) == []  # no staging folder left


def test_a_disk_that_fills_while_the_onnx_writer_writes_is_named_a_full_disk(tmp_path, capsys, monkeypatch):
    """The ONNX writer's short write carries no errno and no file name: `export` names --out (not its hidden staging
    folder) and says the disk is full (it read ``OSError: 147456 requested and 138048 written``)."""
    import dapm_lightning.inference.onnx as onnx_module

    def short_write(*args, **kwargs):
        raise OSError("147456 requested and 138048 written")

    monkeypatch.setattr(onnx_module.torch.onnx, "export", short_write)
    out = tmp_path / "dapm.onnx"
    with pytest.raises(SystemExit) as info:
        main(["export", str(SHIPPED), "--out", str(out), "--height", "64", "--width", "64"])
    err = capsys.readouterr().err.splitlines()
    assert info.value.code == 1 and err[:2] == [
        f"error: {out}: cannot be written (No space left on device: 147456 requested and 138048 written)",
        "Fix: free space on that disk, or write to another folder (--out)"], err
    assert list(tmp_path.iterdir()) == []  # no staging folder left


def test_a_renamed_model_names_the_weights_file_its_graph_records(tmp_path, capsys):
    """x.onnx and x.onnx.data copied to model.onnx and model.onnx.data: the graph still names x.onnx.data (recorded
    inside the .onnx), so the message names that file and the real fixes, not NAME.onnx.data."""
    import shutil

    import cv2
    import numpy as np
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    from dapm_lightning.inference.runtime import OnnxRuntime

    graph = helper.make_graph([helper.make_node("MatMul", ["x", "w"], ["y"])], "g",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 64])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 64])],
                              [numpy_helper.from_array(np.ones((64, 64), np.float32), "w")])
    (tmp_path / "export").mkdir()
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9),
              str(tmp_path / "export" / "x.onnx"), save_as_external_data=True, location="x.onnx.data",
              size_threshold=0)
    folder = tmp_path / "models"
    folder.mkdir()
    model = folder / "model.onnx"
    shutil.copy(tmp_path / "export" / "x.onnx", model)
    shutil.copy(tmp_path / "export" / "x.onnx.data", folder / "model.onnx.data")
    with pytest.raises(ValueError) as info:
        OnnxRuntime(model)
    assert str(info.value) == (
        f"{model}: its weights file {folder / 'x.onnx.data'} is missing. An exported model records its weights "
        "file's name inside the .onnx (x.onnx.data): renaming the .onnx and its .data file does not change it "
        "(model.onnx.data beside it is not read).\n"
        f"Fix: keep the weights file beside it under its original name, {folder / 'x.onnx.data'}, or export again "
        f"under the new name: dapm-lightning export CKPT --out {model} (writes model.onnx and model.onnx.data)")
    image = tmp_path / "a.png"
    assert cv2.imwrite(str(image), np.zeros((40, 60, 3), np.uint8))
    with pytest.raises(SystemExit) as stop:
        main(["predict", str(image), "--ckpt_path", str(model), "--out", str(tmp_path / "out"), "--device", "cpu"])
    err = capsys.readouterr().err
    assert stop.value.code == 1 and "Traceback" not in err and f"its weights file {folder / 'x.onnx.data'}" in err
    shutil.copy(folder / "model.onnx.data", folder / "x.onnx.data")  # the fix: it loads (then is not a DAPM export)
    with pytest.raises(ValueError, match="not a dapm-lightning export"):
        OnnxRuntime(model)
    (folder / "broken.onnx").write_bytes(b"not a model")
    with pytest.raises(ValueError, match=r"broken.onnx: onnxruntime cannot load it .*\nFix: export the checkpoint "
                                         r"again \(dapm-lightning export CKPT --out .*broken.onnx\)"):
        OnnxRuntime(folder / "broken.onnx")


def test_a_model_of_another_version_names_the_file_and_the_fix(tmp_path, capsys):
    """A newer export's settings (one this version does not know) once gave "unknown model.net setting(s)
    ['future_setting']; known: [...]", naming neither the .onnx file nor what to do."""
    import json

    import cv2
    import numpy as np
    import onnx
    from onnx import TensorProto, helper

    from dapm_lightning.inference.runtime import OnnxRuntime

    graph = helper.make_graph([helper.make_node("Identity", ["image"], ["depth_m"])], "g",
                              [helper.make_tensor_value_info("image", TensorProto.FLOAT, ["b", 3, "h", "w"])],
                              [helper.make_tensor_value_info("depth_m", TensorProto.FLOAT, ["b", 3, "h", "w"])])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9)
    settings = {**DAPMConfig(**TINY).to_dict(), "future_setting": 1}
    for key, value in {"dapm.net": json.dumps(settings), "dapm.version": "9.0.0"}.items():
        model.metadata_props.add(key=key, value=value)
    path = tmp_path / "newer.onnx"
    onnx.save(model, str(path))
    with pytest.raises(ValueError) as info:
        OnnxRuntime(path)
    assert str(info.value).startswith(f"{path}: its network settings (dapm.net, exported by dapm-lightning 9.0.0) "
                                      "do not load here: unknown model.net setting(s) ['future_setting']")
    assert str(info.value).endswith("\nFix: predict with the dapm-lightning version that exported it, or export "
                                    "the checkpoint again with this one")
    image = tmp_path / "a.png"
    assert cv2.imwrite(str(image), np.zeros((40, 60, 3), np.uint8))
    with pytest.raises(SystemExit) as stop:
        main(["predict", str(image), "--ckpt_path", str(path), "--out", str(tmp_path / "out"), "--device", "cpu"])
    err = capsys.readouterr().err
    assert stop.value.code == 1 and "newer.onnx: its network settings" in err and "Traceback" not in err


@pytest.mark.slow
def test_cli_export(checkpoint, tmp_path, capsys):
    out = tmp_path / "model.onnx"
    main(["export", "--ckpt_path", str(checkpoint), "--out", str(out), "--height", "32", "--width", "64",
          "--checks", "1"])
    printed = capsys.readouterr().out
    assert out.is_file() and printed.count("max |onnxruntime - PyTorch fp32|") == 2


def test_export_mismatches_name_what_exceeds_its_tolerance():
    good = {"shape": (1, 64, 64), "depth_m": 0.01, "sky_prob": 1e-5, "pose": 1e-4, DEPTH_SHARE_OFF: 0.0}
    assert export_mismatches([good]) == [] and export_mismatches([good], fp16=True) == []
    odd = {**good, "shape": (2, 51, 117), "sky_prob": 0.1, DEPTH_SHARE_OFF: 4e-4}  # a misaligned head, as once
    assert export_mismatches([good, odd]) == ["sky_prob 0.1 > 0.01 at (2, 51, 117)"]
    assert export_mismatches([good, odd], fp16=True) == []  # half precision is allowed more
    assert export_mismatches([{**good, DEPTH_SHARE_OFF: 0.02}], fp16=True) == [
        "depth_share_off_1pct 0.02 > 0.01 at (1, 64, 64)"]


def test_every_output_is_held_to_its_float32_tolerance():
    """float32 is held tighter than float16: a share of 0.2 % of depth pixels off, or the network's own pose off by
    0.06, fails it."""
    good = {"shape": (1, 64, 64), "depth_m": 0.01, "sky_prob": 1e-5, "pose": 1e-4, "pose_network": 1e-4,
            DEPTH_SHARE_OFF: 0.0}
    assert export_mismatches([{**good, DEPTH_SHARE_OFF: 2e-3}]) == ["depth_share_off_1pct 0.002 > 0.001 at (1, 64, 64)"]
    assert export_mismatches([{**good, "pose_network": 0.06}]) == ["pose_network 0.06 > 0.05 at (1, 64, 64)"]
    assert export_mismatches([{**good, DEPTH_SHARE_OFF: 2e-3, "pose_network": 0.06}], fp16=True) == []


def test_the_depth_check_counts_the_pixels_off_by_more_than_one_percent_of_their_depth(tmp_path, monkeypatch):
    """The share of depth pixels off is relative to each pixel's depth: onnxruntime's depth 2 % off on the first
    tenth of the pixels (and 0.5 % off elsewhere, within the limit) is that tenth, at each checked size."""
    import dapm_lightning.inference.onnx as onnx_module
    from dapm_lightning.inference.onnx import ExportWrapper

    net = tiny_net()
    reference = ExportWrapper(net)

    class Session:  # onnxruntime's outputs: PyTorch's, the depth a little off
        def __init__(self, *args, **kwargs):
            pass

        def run(self, names, feed):
            with torch.no_grad():
                outputs = [o.numpy() for o in reference(*(torch.from_numpy(feed[n]) for n in reference.input_names))]
            depth = outputs[reference.names.index("depth_m")]
            off = np.full(depth.size, 1.005, np.float32)
            off[: depth.size // 10] = 1.02
            outputs[reference.names.index("depth_m")] = depth * off.reshape(depth.shape)
            return outputs

    monkeypatch.setattr(torch.onnx, "export", lambda model, args, path, **kwargs: Path(path).write_bytes(b"graph"))
    monkeypatch.setattr(onnx_module, "write_metadata", lambda path, metadata: None)
    monkeypatch.setattr(onnxruntime, "InferenceSession", Session)
    rows = export_onnx(net, tmp_path / "m.onnx", (32, 32), checks=1)
    assert [row["shape"] for row in rows] == [(1, 32, 32), (2, 32, 53)]
    for row in rows:
        assert row[DEPTH_SHARE_OFF] == pytest.approx(0.1, abs=0.01) and row["sky_prob"] == 0.0
    (failure,) = export_mismatches(rows)
    assert failure.startswith("depth_share_off_1pct 0.0") and "> 0.001 at" in failure


def test_an_output_that_is_nan_in_onnxruntime_alone_fails_the_check():
    """A NaN (an fp16 overflow) is a difference, not a pass: NaN compares false with every limit, so it once passed
    the check and, as the first row, hid a real mismatch in the rows after it."""
    import numpy as np

    from dapm_lightning.inference.onnx import output_difference

    good = {"shape": (1, 64, 64), "depth_m": 0.01, "sky_prob": 1e-5, "pose": 1e-4, DEPTH_SHARE_OFF: 0.0}
    nan = float("nan")
    assert export_mismatches([{**good, "sky_prob": nan}]) == ["sky_prob nan > 0.01 at (1, 64, 64)"]
    assert export_mismatches([{**good, "pose": nan}, {**good, "shape": (2, 51, 117), "pose": 0.06}],
                             fp16=True) == ["pose nan > 0.5 at (1, 64, 64)"]
    assert export_mismatches([good, {**good, "shape": (2, 51, 117), "pose": 0.06}]) == [
        "pose 0.06 > 0.05 at (2, 51, 117)"]
    got = np.array([1.0, nan, nan, np.inf, 5.0], np.float32)
    expected = np.array([1.5, nan, 2.0, np.inf, nan], np.float32)
    assert output_difference(got, expected).tolist() == [0.5, 0.0, np.inf, 0.0, np.inf]  # only one NaN: inf


@pytest.mark.slow
def test_the_shipped_model_exports_exactly_at_odd_sizes(tmp_path, capsys, monkeypatch):
    """The trained model shows what a random network hides: a head a pixel off at sides not divisible by its stride
    (``-(-H // s)`` exported as a truncating division) moved its sky and depth edges; the export now refuses that."""
    shipped = Path(__file__).resolve().parents[2] / "models" / "dapm-synthetic-r18-256"
    out = tmp_path / "shipped.onnx"
    main(["export", "--ckpt_path", str(shipped), "--out", str(out), "--checks", "1"])
    printed = capsys.readouterr().out
    assert out.is_file() and "(2, 243, 277)" in printed and "depth pixels off by > 1 %: 0.00%" in printed
    exported = out.read_bytes()
    import dapm_lightning.tools.export as export_tool

    real = export_tool.export_onnx

    def misaligned(*args, **kwargs):
        rows = real(*args, **kwargs)
        return [*rows[:-1], {**rows[-1], "sky_prob": 0.1}]
    monkeypatch.setattr(export_tool, "export_onnx", misaligned)
    with pytest.raises(export_tool.ExportMismatch, match=r"(?s)shipped.onnx: onnxruntime's outputs disagree.*sky_prob "
                                                         r"0.1 > 0.01.*--force true keeps"):
        export_tool.export(shipped, out, checks=1)
    assert out.read_bytes() == exported  # the earlier, right export is left whole; the wrong one is not written
    assert export_tool.export(shipped, out, checks=1, force=True) == out and out.is_file()
    assert "kept anyway (--force true)" in capsys.readouterr().out


def test_the_docs_name_every_input_and_output_of_the_exported_model():
    """predict.md documents the ONNX file's interface: each input the export takes and each output it gives."""
    from pathlib import Path

    from dapm_lightning.inference.onnx import PRIOR_INPUTS
    from dapm_lightning.models.dapm import INFERENCE_OUTPUTS

    doc = (Path(__file__).resolve().parents[2] / "docs" / "predict.md").read_text()
    section = doc[doc.index("dapm-lightning export CKPT"):doc.index("The file carries what prediction needs")]
    assert [name for name in ("image", *PRIOR_INPUTS, *INFERENCE_OUTPUTS) if f"`{name}`" not in section] == []
    assert "NaN where unknown" not in section  # the graph takes no NaN: prior_known says what is known
    import dapm_lightning.inference.onnx as onnx_module
    import dapm_lightning.tools.export as export_tool

    for text in (export_tool.__doc__, onnx_module.__doc__):  # `export --help`, and the module's reference
        assert [name for name in PRIOR_INPUTS if name not in text] == [] and "NaN where unknown" not in text


@pytest.mark.parametrize("kept", [0, 100])
def test_a_weights_file_cut_short_is_named_with_its_size_and_the_fix(tmp_path, kept, monkeypatch):
    """Before, a .onnx.data cut short (or empty) gave onnxruntime's own message, never saying the file was short;
    then it came after onnxruntime's own error log (C++, on the process's stderr): now onnxruntime is not asked."""
    import numpy as np
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    from dapm_lightning.inference.runtime import OnnxRuntime

    graph = helper.make_graph([helper.make_node("MatMul", ["x", "w"], ["y"])], "g",
                              [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 64])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 64])],
                              [numpy_helper.from_array(np.ones((64, 64), np.float32), "w")])
    model = tmp_path / "m.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9), str(model),
              save_as_external_data=True, location="m.onnx.data", size_threshold=0)
    data = tmp_path / "m.onnx.data"
    data.write_bytes(data.read_bytes()[:kept])
    with pytest.raises(ValueError) as info:
        OnnxRuntime(model)
    assert str(info.value).startswith(f"{model}: its weights file {data} is cut short: {kept} bytes, where the graph "
                                      f"reads {64 * 64 * 4:,}")
    assert "\nFix: copy the .onnx and its weights file again together" in str(info.value)

    sessions = []
    monkeypatch.setattr(onnxruntime, "InferenceSession", lambda *args, **kwargs: sessions.append(args))
    with pytest.raises(ValueError, match="is cut short"):  # the same message, and no C++ error log before it
        OnnxRuntime(model)
    assert sessions == []


def test_a_stop_between_moving_the_weights_and_the_graph_waits_for_both(tmp_path, monkeypatch):
    """Ctrl-C (or SIGTERM) after an export's weights file was moved into place but before its graph: the stop waits
    for the graph (before: the earlier export's graph was left reading the new weights)."""
    import os
    import signal

    import dapm_lightning.inference.onnx as onnx_module

    staging, final = tmp_path / "staging", tmp_path / "m.onnx"
    staging.mkdir()
    for folder, what in ((staging, "new"), (tmp_path, "old")):
        (folder / "m.onnx").write_text(f"{what} graph")
        (folder / "m.onnx.data").write_text(f"{what} weights")
    replace, moved = os.replace, []

    def replace_then_ctrl_c(source, target):
        replace(source, target)
        moved.append(Path(target).name)
        if len(moved) == 1:
            os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(onnx_module.os, "replace", replace_then_ctrl_c)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            onnx_module.move_exported(staging / "m.onnx", final)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert moved == ["m.onnx.data", "m.onnx"]
    assert (final.read_text(), (tmp_path / "m.onnx.data").read_text()) == ("new graph", "new weights")
