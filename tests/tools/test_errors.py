"""User errors end in a short message naming the file and the fix, exit status 1, and no traceback."""

import errno
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
import torch

from dapm_lightning.cli import main
from dapm_lightning.data.datamodules import SyntheticDataModule, UAPDDataModule
from dapm_lightning.data.errors import DatasetError
from dapm_lightning.tools.errors import debug_requested, describe, run_reporting_errors
from dapm_lightning.training.checkpoint_files import CheckpointSaveError, UnsafeCheckpointError
from tests.conftest import CONFIGS, QUICKSTART, run_main


def test_missing_data_folder(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--data.class_path",
                          "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root",
                          str(tmp_path / "nowhere"), "--trainer.logger", "false"], capsys)
    assert code == 1
    assert f"{tmp_path / 'nowhere'}: no such folder" in err and "Fix: give data.init_args.root" in err
    assert "--debug" in err and "on_bad_file" not in err  # no files to leave out: the root is wrong
    (tmp_path / "notes.txt").write_text("not a data set")
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--data.class_path",
                          "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root",
                          str(tmp_path / "notes.txt"), "--trainer.logger", "false"], capsys)
    assert code == 1 and f"{tmp_path / 'notes.txt'}: a file, not a folder" in err, err
    (tmp_path / "nosplit" / "val" / "rgb").mkdir(parents=True)
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--data.class_path",
                          "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root",
                          str(tmp_path / "nosplit"), "--trainer.logger", "false"], capsys)
    assert code == 1 and f"{tmp_path / 'nosplit' / 'train'}: missing folder" in err and "holds val/" in err
    assert "Fix: put the train split in ROOT/train/{rgb,depth}/NAME.png" in err and "on_bad_file" not in err


def test_data_problems_stop_a_run_before_its_log_folders_are_made(uapd_copy, checkpoint, tmp_path, capsys,
                                                                  monkeypatch):
    """An empty tensorboard/version_0 left by a run that never started would send the next run to version_1."""
    run = tmp_path / "run"
    run.mkdir()
    monkeypatch.chdir(run)
    uapd = ["--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule"]
    for subcommand in ("fit", "validate", "test"):
        weights = [] if subcommand == "fit" else ["--ckpt_path", str(checkpoint)]
        code, err = run_main([subcommand, "--config", str(QUICKSTART), *uapd, "--data.init_args.root",
                              str(tmp_path / "nowhere"), *weights], capsys)
        assert code == 1 and "no such folder" in err, err
    broken = uapd_copy
    damaged = sorted((broken / "train" / "depth").iterdir())[0]
    damaged.write_bytes(damaged.read_bytes()[:40])
    code, err = run_main(["fit", "--config", str(QUICKSTART), *uapd, "--data.init_args.root", str(broken)], capsys)
    assert code == 1 and str(damaged) in err, err
    assert list(run.iterdir()) == []


def test_validate_or_test_with_the_predict_data_module_is_refused_before_any_log(checkpoint, tmp_path, capsys,
                                                                                    monkeypatch):
    run = tmp_path / "run"
    run.mkdir()
    monkeypatch.chdir(run)
    for subcommand in ("validate", "test"):
        code, err = run_main([subcommand, "--config", str(CONFIGS / "predict.yaml"), "--ckpt_path", str(checkpoint),
                              "--data.init_args.source", str(tmp_path), "--trainer.logger", "true"], capsys)
        assert code == 1 and f"PredictDataModule serves predict only (no labels), not '{subcommand}'" in err, err
    assert list(run.iterdir()) == []


def test_data_read_early_is_what_setup_uses(tiny_uapd, tmp_path, monkeypatch):
    data = UAPDDataModule(root=str(tiny_uapd), batch_size=2)
    made = []
    make = data.make_dataset
    monkeypatch.setattr(data, "make_dataset", lambda split, train: made.append((split, train)) or make(split, train))
    data.read_early("fit")
    data.setup("fit")
    assert made == [("train", True), ("val", False)]  # scanned once, before the trainer starts
    data.setup("test")
    assert made[2:] == [("val", False)] and len(data.datasets["test"]) == len(data.datasets["val"])
    synthetic = SyntheticDataModule(root=str(tmp_path / "rendered by prepare_data"), train_size=2, val_size=1)
    synthetic.read_early("fit")  # its data does not exist before prepare_data: read in setup, after it
    assert not (tmp_path / "rendered by prepare_data").exists()


def test_missing_and_damaged_checkpoints_and_sources(checkpoint, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    predict = ["predict", "--config", str(CONFIGS / "predict.yaml"), "--data.init_args.source", str(tmp_path)]
    code, err = run_main([*predict, "--ckpt_path", str(tmp_path / "missing.ckpt")], capsys)
    assert code == 1 and "missing.ckpt" in err and "Fix: check the path" in err
    damaged = tmp_path / "cut.ckpt"
    damaged.write_bytes(checkpoint.read_bytes()[:4096])
    code, err = run_main([*predict, "--ckpt_path", str(damaged)], capsys)
    assert code == 1 and f"{damaged}: not a readable checkpoint" in err and "Fix: copy the checkpoint again" in err
    code, err = run_main(["predict", "--config", str(CONFIGS / "predict.yaml"), "--ckpt_path", str(checkpoint),
                          "--data.init_args.source", str(tmp_path / "photos"), "--trainer.callbacks.output_dir",
                          str(tmp_path / "out")], capsys)
    assert code == 1 and f"{tmp_path / 'photos'}: no such file or folder" in err


def test_a_checkpoint_of_a_diverged_training_is_refused_before_anything_is_written(checkpoint, tiny_uapd, tmp_path,
                                                                                    capsys, monkeypatch):
    """Weights holding NaN (a training that diverged): before, the one-line predict wrote a `_camera.json` of NaN
    (not JSON) and a black picture, then stopped on `cannot convert float NaN to integer`, naming no file."""
    import torch

    monkeypatch.chdir(tmp_path)
    saved = torch.load(checkpoint, weights_only=True)
    name = next(k for k, v in saved["state_dict"].items() if v.is_floating_point() and v.numel() > 1)
    saved["state_dict"][name][0] = float("nan")
    diverged = tmp_path / "diverged.ckpt"
    torch.save(saved, diverged)
    images = tiny_uapd / "val" / "rgb"
    code, err = run_main(["predict", str(images), "--ckpt_path", str(diverged), "--out", str(tmp_path / "out"),
                          "--device", "cpu"], capsys)
    assert code == 1 and f"{diverged}: 1 of its" in err and "hold NaN or infinite values" in err, err
    assert "Fix: use an earlier checkpoint of that run" in err and not (tmp_path / "out").exists()
    data = ["--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root",
            str(tiny_uapd), "--trainer.default_root_dir", str(tmp_path / "run")]
    for subcommand in ("test", "fit"):  # a resume would train on from NaN
        code, err = run_main([subcommand, "--config", str(QUICKSTART), *data, "--ckpt_path", str(diverged)], capsys)
        assert code == 1 and "hold NaN or infinite values" in err, err
    code, err = run_main(["fit", "--config", str(QUICKSTART), *data, "--model.init_weights", str(diverged)], capsys)
    assert code == 1 and "hold NaN or infinite values" in err, err
    assert not (tmp_path / "run").exists()


def test_a_checkpoint_missing_weights_says_which(checkpoint, tiny_uapd, tmp_path, capsys):
    """Before: `its weights do not fit the network its settings describe (Error(s) in loading state_dict for
    DAPMModule:)`, the detail cut off at the colon."""
    import torch

    saved = torch.load(checkpoint, weights_only=True)
    names = sorted(saved["state_dict"])
    for name in names[::2]:
        del saved["state_dict"][name]
    first_kept = names[1]
    saved["state_dict"][first_kept] = torch.zeros(1, *saved["state_dict"][first_kept].shape[1:])
    saved["state_dict"]["net.extra.weight"] = torch.zeros(2)
    halved = tmp_path / "halved.ckpt"
    torch.save(saved, halved)
    code, err = run_main(["predict", str(tiny_uapd / "val" / "rgb"), "--ckpt_path", str(halved), "--out",
                          str(tmp_path / "out")], capsys)
    assert code == 1 and f"{halved}: its weights do not fit the network its settings describe " \
        f"({len(names[::2])} missing: '" in err and f"... ({len(names[::2])} in all); 1 not in the network: " \
        f"'net.extra.weight'; 1 of another shape: {first_kept!r} [1" in err, err


def test_data_of_another_depth_kind_or_limit_than_the_checkpoint_s_is_refused_before_the_log_folders(
        checkpoint, tiny_uapd, tmp_path, capsys, monkeypatch):
    """Before, the check ran as the trainer set the module up, after the loggers made `version_0/` (left with
    `config_test.yaml`), and its fix, `set model.net.igd.depth_kind`, cannot change a checkpoint's network."""
    monkeypatch.chdir(tmp_path)
    data = ["--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root",
            str(tiny_uapd), "--trainer.default_root_dir", str(tmp_path / "run"), "--ckpt_path", str(checkpoint)]
    code, err = run_main(["test", "--config", str(QUICKSTART), *data, "--data.init_args.depth_kind", "planar"],
                         capsys)
    assert code == 1 and "the data holds planar depth but the model's IGD computes range depth" in err, err
    assert f"the network of {checkpoint} was trained for range depth and keeps it" in err, err
    assert not (tmp_path / "run").exists()
    from types import SimpleNamespace

    from dapm_lightning.training.checkpointing import load_dapm_module

    module = load_dapm_module(checkpoint)
    with pytest.raises(ValueError, match=f"limit is 1000 m: the network of {checkpoint} keeps its 1000 m"):
        module.check_data_agrees(SimpleNamespace(depth_kind="range", max_depth=500.0), str(checkpoint))
    with pytest.raises(ValueError, match="limit is 1000 m: set model.net.igd.max_depth: 500"):
        module.check_data_agrees(SimpleNamespace(depth_kind="range", max_depth=500.0))


def test_a_wrong_ckpt_path_stops_fit_and_test_before_their_log_folders_are_made(tiny_uapd, tmp_path, capsys,
                                                                                 monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runs" / "checkpoints").mkdir(parents=True)
    data = ["--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root",
            str(tiny_uapd), "--trainer.default_root_dir", str(tmp_path / "run")]
    for subcommand in ("fit", "test"):
        code, err = run_main([subcommand, "--config", str(QUICKSTART), *data, "--ckpt_path", "nope.ckpt"], capsys)
        assert code == 1 and "nope.ckpt: no such checkpoint file" in err and "Fix: check the path" in err, err
        code, err = run_main([subcommand, "--config", str(QUICKSTART), *data, "--ckpt_path", "runs"], capsys)
        assert code == 1 and "runs: a folder, not a checkpoint file" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["runs"]  # no run folder, no logger's version_N
    from dapm_lightning.training.checkpoint_files import is_lightning_checkpoint_word
    assert all(map(is_lightning_checkpoint_word, ("best", "last", "hpc", "registry", "REGISTRY:model:1")))
    assert not any(map(is_lightning_checkpoint_word, ("registry_old.ckpt", "lastest.ckpt", "runs/last")))
    assert not any(map(is_lightning_checkpoint_word, ("nope.ckpt", "runs", "lastly.ckpt", "best.ckpt")))


def test_predict_with_ckpt_path_last_and_no_run_folder_is_refused(checkpoint, tmp_path, capsys, monkeypatch):
    """predict.yaml names no run folder: `last` was the newest last.ckpt of any run under the current directory."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "someone_else" / "checkpoints").mkdir(parents=True)
    (tmp_path / "someone_else" / "checkpoints" / "last.ckpt").write_bytes(checkpoint.read_bytes())
    code, err = run_main(["predict", "--config", str(CONFIGS / "predict.yaml"), "--ckpt_path", "last",
                          "--data.init_args.source", str(tmp_path)], capsys)
    assert code == 1 and "predict --ckpt_path last: the configuration names no run folder" in err, err
    assert "Fix: --trainer.default_root_dir set to the folder `fit` wrote its run to" in err


def test_bad_setting_and_debug_flag(capsys, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    args = ["fit", "--config", str(QUICKSTART), "--model.net.head_stride", "3", "--trainer.logger", "false"]
    code, err = run_main(args, capsys)
    assert code == 1 and "head_stride must be 1, 2, 4 or 8, got 3" in err
    with pytest.raises(ValueError, match="head_stride"):  # --debug: the exception itself, with its traceback
        main([*args, "--debug"])
    monkeypatch.setenv("DAPM_DEBUG", "1")
    with pytest.raises(ValueError, match="head_stride"):
        main(args)
    assert debug_requested(["fit", "--debug"]) == (True, ["fit"])
    for off in ("0", "false", "No", " "):  # as a shell user writes "off"
        monkeypatch.setenv("DAPM_DEBUG", off)
        assert debug_requested(["fit"]) == (False, ["fit"]), off


def test_messages_of_wrapped_and_unexpected_errors():
    wrapped = RuntimeError("Caught DatasetError in DataLoader worker process 0.\nOriginal Traceback (most recent "
                           "call last):\n  File \"x.py\", line 1, in f\ndapm_lightning.data.errors.DatasetError: "
                           "/d/train: 1 problem(s) found:\n  /d/train/rgb/a.png: cannot be decoded as an image")
    message, expected = describe(wrapped)
    assert message.startswith("/d/train: 1 problem(s)") and "a.png" in message and "Fix:" in message and expected
    message, expected = describe(DatasetError("/d", ["/d/x.png: bad"]))
    assert "/d/x.png: bad" in message and expected
    message, expected = describe(TypeError("unsupported operand"))
    assert not expected and "possibly a bug" in message and "--debug" in message


def test_batch_norm_of_a_one_pixel_batch_says_what_to_change():
    """torch's own message (training on one image whose deepest map is 1x1), explained with the fix."""
    with pytest.raises(ValueError) as info:
        torch.nn.BatchNorm2d(4).train()(torch.zeros(1, 4, 1, 1))
    message, expected = describe(info.value)
    assert expected and message.startswith(str(info.value)) and "divides each side by 32" in message
    assert "Fix: batches of at least 2 images (--data.init_args.batch_size" in message


def test_refused_checkpoints_and_failed_saves_keep_their_own_fix():
    refused = UnsafeCheckpointError("/x/evil.ckpt: refused: the file holds pickled Python objects (builtins.exec) ...\n"
                                    "Fix: use a checkpoint written by `dapm-lightning fit`")
    message, expected = describe(refused)
    assert message == str(refused) and expected and "copy the checkpoint again" not in message
    full = CheckpointSaveError("/x/last.ckpt: could not save the checkpoint: no space left in /x\nFix: free space")
    assert describe(full) == (str(full), True)


def test_ctrl_c_exits_130_also_after_lightnings_own_shutdown(capsys):
    def lightning_style():  # what Lightning does on KeyboardInterrupt: a graceful shutdown, then sys.exit(1)
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            sys.exit(1)

    for function in (lightning_style, lambda: (_ for _ in ()).throw(KeyboardInterrupt)):
        with pytest.raises(SystemExit) as info:
            run_reporting_errors(function, debug=False)
        assert info.value.code == 130 and "interrupted" in capsys.readouterr().err
    for code in (0, 1, 143):  # other exits keep their status
        with pytest.raises(SystemExit) as info:
            run_reporting_errors(lambda: sys.exit(code), debug=False)  # noqa: B023
        assert info.value.code == code


def test_unknown_subcommand(capsys):
    with pytest.raises(SystemExit) as info:
        main(["trian"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "unknown subcommand 'trian'" in err and "fit" in err
    for typed, meant in (("predikt", "predict"), ("tset", "test"), ("exprt", "export"), ("docter", "doctor")):
        with pytest.raises(SystemExit):
            main([typed])
        assert f"unknown subcommand '{typed}' (did you mean {meant}?)" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["zzz"])
    assert "did you mean" not in capsys.readouterr().err


@pytest.mark.slow
def test_real_process_exit_status_and_traceback_only_on_request(tmp_path):
    env = {k: v for k, v in os.environ.items() if k != "DAPM_DEBUG"}
    command = [sys.executable, "-m", "dapm_lightning", "export", "--ckpt_path", str(tmp_path / "gone.ckpt")]
    quiet = subprocess.run(command, capture_output=True, text=True, env=env)
    assert quiet.returncode == 1 and "gone.ckpt" in quiet.stderr and "Traceback" not in quiet.stderr
    loud = subprocess.run(command, capture_output=True, text=True, env={**env, "DAPM_DEBUG": "1"})
    assert loud.returncode == 1 and "Traceback" in loud.stderr


def test_an_error_under_a_progress_bar_starts_a_line_of_its_own():
    """A progress bar leaves its line open (it redraws it); the message after it must not run on from that line."""
    import io

    from tqdm import tqdm

    def failing():
        raise ValueError("/data/x.png: broken")

    for shown in (True, False):
        stream = io.StringIO()
        bar = tqdm(total=3, file=io.StringIO(), disable=not shown)
        bar.update()
        with pytest.raises(SystemExit):
            run_reporting_errors(failing, debug=False, stream=stream)
        bar.close()
        assert stream.getvalue().startswith("\nerror: /data/x.png" if shown else "error: /data/x.png")


def test_a_failed_weights_download_names_the_offline_settings():
    """timm's pretrained weights from the Hub, offline: an OSError, but not a path the user gave."""
    class LocalEntryNotFoundError(FileNotFoundError):  # huggingface_hub's, raised when the Hub cannot be reached
        pass

    LocalEntryNotFoundError.__module__ = "huggingface_hub.errors"
    message, expected = describe(LocalEntryNotFoundError(
        "An error happened while trying to locate the file on the Hub and we cannot find the requested files in the "
        "local cache."))
    assert expected and "--model.net.pretrained false" in message and "--model.net.weights_path FILE" in message
    assert "check the path" not in message
    message, _ = describe(FileNotFoundError("data/x.png: no such file"))
    assert "pretrained" not in message and "check the path" in message


def test_an_explained_error_about_a_hub_address_keeps_its_own_fix():
    """A checkpoint that cannot be fetched from huggingface.co says its own fix, not the pretrained weights' one."""
    class CheckpointFetchError(OSError):
        explained = True

    message, expected = describe(CheckpointFetchError(
        "https://huggingface.co/x/y/resolve/main/m.ckpt: cannot be fetched (no network?)\nFix: copy it here."))
    assert expected and "Fix: copy it here." in message and "pretrained" not in message


@pytest.mark.parametrize(("code", "fix"), [
    (errno.EROFS, "write to a folder you may write to (this one is read-only or not yours)"),
    (errno.ENOSPC, "free space on that disk, or write to another folder"),
    (errno.EACCES, "write to a folder you may write to (this one is read-only or not yours)"),
    (errno.ENOTDIR, "a part of the path is a file, not a folder: write to another folder, or move that file away"),
    (errno.EEXIST, "a part of the path is a file, not a folder: write to another folder, or move that file away"),
])
def test_os_errors_of_writing_name_the_path_what_happened_and_the_fix(code, fix):
    message, expected = describe(OSError(code, os.strerror(code), "/runs/out/model.onnx"))
    assert message == f"/runs/out/model.onnx: cannot be written ({os.strerror(code)})\nFix: {fix}" and expected, message


def test_synth_into_a_file_and_export_under_a_file_say_so(capsys, tmp_path):
    a_file = tmp_path / "notes.txt"
    a_file.write_text("kept")
    code, err = run_main(["synth", "--out", str(a_file / "data"), "--train", "1", "--val", "0", "--size", "8",
                          "--workers", "1", "--quiet"], capsys)
    assert code == 1 and f"it lies under {a_file}, which is a file, not a folder" in err, err
    assert "Fix: give another output folder (--out)" in err and a_file.read_text() == "kept"


def test_a_missing_export_extra_names_the_install(tmp_path, capsys, monkeypatch):
    """predict on an .onnx model (or export) without onnxruntime once ended in "ModuleNotFoundError: No module named
    'onnxruntime'" alone, with no word of the export extra that holds it."""
    import sys

    import cv2
    import numpy as np

    from dapm_lightning.cli import main

    monkeypatch.setitem(sys.modules, "onnxruntime", None)  # importing it raises ModuleNotFoundError
    image = tmp_path / "a.png"
    assert cv2.imwrite(str(image), np.zeros((40, 60, 3), np.uint8))
    (tmp_path / "m.onnx").write_bytes(b"graph")
    with pytest.raises(SystemExit) as stop:
        main(["predict", str(image), "--ckpt_path", str(tmp_path / "m.onnx"), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert stop.value.code == 1 and "Traceback" not in err, err
    assert "ONNX export and running an .onnx model need the export extra.\nFix: pip install " \
           '"dapm-lightning[export]" (onnx, onnxscript, onnxruntime)' in err, err
    message, _ = describe(ModuleNotFoundError("No module named 'yaml'", name="yaml"))
    assert "export extra" not in message  # another missing package is not said to be the extra's


def _onnx_bytes() -> bytes:
    """A small ONNX model (Identity), as onnx writes it."""
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    value = helper.make_tensor_value_info
    graph = helper.make_graph([helper.make_node("Identity", ["x"], ["y"])], "g", [value("x", TensorProto.FLOAT, [1])],
                              [value("y", TensorProto.FLOAT, [1])])
    return onnx.helper.make_model(graph, producer_name="pytorch").SerializeToString()


def test_export_of_an_onnx_model_says_it_is_exported_already(tmp_path, capsys):
    """`export m.onnx` said to write --out m.onnx (the same path), `export x.onnx --out y.onnx` called it corrupt."""
    exported = tmp_path / "exp" / "m.onnx"
    exported.parent.mkdir()
    exported.write_bytes(b"\x08\x07")  # by its name: an .onnx file cut short is still one
    code, err = run_main(["export", str(exported)], capsys)
    assert code == 1 and f"{exported}: an exported ONNX model already, not a checkpoint" in err, err
    assert f"predict directly: dapm-lightning predict SOURCE --ckpt_path {exported}" in err
    assert "ending in .onnx" not in err and "copy the checkpoint again" not in err
    for missing in (tmp_path / "none.onnx", tmp_path / "none.ckpt"):  # nothing there: said so, not taken for a model
        code, err = run_main(["export", str(missing)], capsys)
        assert code == 1 and f"{missing}: no such checkpoint file" in err and "already" not in err, err
        assert "--out" not in err
    code, err = run_main(["export", "https://example.com/runs/m.ckpt"], capsys)  # its address was folded to https:/
    assert code == 1 and "https://example.com/runs/m.ckpt: export reads a local checkpoint file" in err, err
    named = tmp_path / "x.onnx"
    named.write_bytes(_onnx_bytes())
    code, err = run_main(["export", str(named), "--out", str(tmp_path / "y.onnx")], capsys)
    assert code == 1 and "an exported ONNX model already" in err and "not a readable" not in err, err
    renamed = tmp_path / "model.ckpt"  # by its content
    renamed.write_bytes(_onnx_bytes())
    code, err = run_main(["export", str(renamed), "--out", str(tmp_path / "y.onnx")], capsys)
    assert code == 1 and f"{renamed}: an exported ONNX model already" in err, err
    assert f"--ckpt_path {tmp_path / 'model.onnx'} (renamed to end in .onnx" in err
    assert not (tmp_path / "y.onnx").exists()


def test_a_part_of_a_split_checkpoint_or_an_onnx_model_given_to_predict_say_what_they_are(checkpoint, tmp_path,
                                                                                            capsys, monkeypatch):
    """A split checkpoint's part was called truncated or corrupt, with the fix to copy it again."""
    from dapm_lightning.training.checkpoint_files import split_checkpoint

    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "split"
    split_checkpoint(checkpoint, folder, part_bytes=checkpoint.stat().st_size // 2 + 1)
    predict = ["predict", "--config", str(CONFIGS / "predict.yaml"), "--data.init_args.source", str(tmp_path)]
    code, err = run_main([*predict, "--ckpt_path", str(folder / "checkpoint.part00")], capsys)
    assert code == 1 and f"{folder / 'checkpoint.part00'}: one part of a split checkpoint" in err, err
    assert f"Fix: pass the folder, {folder}, instead of one of its parts" in err and "copy the checkpoint" not in err
    alone = tmp_path / "copied"
    alone.mkdir()
    (alone / "checkpoint.part01").write_bytes((folder / "checkpoint.part01").read_bytes())
    code, err = run_main([*predict, "--ckpt_path", str(alone / "checkpoint.part01")], capsys)
    assert code == 1 and f"{alone} has no parts.json" in err, err
    renamed = tmp_path / "model.ckpt"
    renamed.write_bytes(_onnx_bytes())
    code, err = run_main([*predict, "--ckpt_path", str(renamed)], capsys)
    assert code == 1 and f"{renamed}: an exported ONNX model, not a checkpoint" in err, err
    assert f"--ckpt_path {tmp_path / 'model.onnx'}` (renamed to end in .onnx" in err

def test_an_unreadable_checkpoint_is_told_apart_from_no_checkpoint_at_all(checkpoint, tmp_path, capsys,
                                                                           monkeypatch):
    """A PNG, a config or a text file given as a checkpoint ended in torch's fragments ('Weights only load failed',
    'pop from empty list', '101') and 'copy the checkpoint again'; a damaged split part leaked its class name; a
    folder suggested a 6-byte junk file beside the whole checkpoint."""
    from dapm_lightning.training.checkpoint_files import split_checkpoint

    monkeypatch.chdir(tmp_path)
    (tmp_path / "photos").mkdir()
    cv2.imwrite(str(tmp_path / "photos" / "a.png"), np.zeros((16, 16, 3), np.uint8))
    (tmp_path / "run.yaml").write_text("trainer:\n  max_steps: 3\n")
    (tmp_path / "junk.ckpt").write_text("hello\n")
    (tmp_path / "empty.ckpt").write_bytes(b"")
    (tmp_path / "cut.ckpt").write_bytes(checkpoint.read_bytes()[:4096])
    cases = {tmp_path / "photos" / "a.png": ("not a checkpoint at all: a PNG image", "an image goes to predict"),
             tmp_path / "run.yaml": ("not a checkpoint at all: a YAML file of settings",
                                     f"settings go to --config {tmp_path / 'run.yaml'}"),
             tmp_path / "junk.ckpt": ("not a checkpoint at all: a text file", "Fix: give a checkpoint written by"),
             tmp_path / "empty.ckpt": ("(0 bytes: the file is empty)", "Fix: copy the checkpoint again"),
             tmp_path / "cut.ckpt": ("(4096 bytes, a checkpoint cut short or damaged", "Fix: copy the checkpoint")}
    for path, (what, fix) in cases.items():
        code, err = run_main(["predict", str(tmp_path / "photos"), "--ckpt_path", str(path)], capsys)
        assert code == 1 and f"{path}: not a readable checkpoint (" in err and what in err and fix in err, err
        assert ("copy the checkpoint" in err) == ("copy" in fix), err
        assert "Weights only" not in err and "pop from" not in err and "EOFError" not in err, err
    folder = tmp_path / "split"
    split_checkpoint(checkpoint, folder, part_bytes=checkpoint.stat().st_size // 2 + 1)
    (folder / "checkpoint.part01").write_bytes(b"cut")
    code, err = run_main(["predict", str(tmp_path / "photos"), "--ckpt_path", str(folder)], capsys)
    assert code == 1 and err.startswith(f"error: {folder / 'checkpoint.part01'}: damaged (3 bytes"), err
    assert f"\nFix: restore the folder as it was published (e.g. `git checkout -- {folder}`" in err, err
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for name in ("a.ckpt", "z.ckpt"):
        (mixed / name).write_text("junk")
    (mixed / "model.ckpt").write_bytes(checkpoint.read_bytes())
    os.utime(mixed / "model.ckpt", (0, 0))  # the oldest, and not named last or best: still the one a run reads
    code, err = run_main(["predict", str(tmp_path / "photos"), "--ckpt_path", str(mixed)], capsys)
    assert code == 1 and f"Fix: give one of them, e.g. {mixed / 'model.ckpt'}\n" in err, err



def test_one_line_predict_given_lightning_s_word_for_a_checkpoint_says_which_form_reads_it(tmp_path, capsys,
                                                                                            monkeypatch):
    """`predict SRC --ckpt_path last` said only 'last: no such checkpoint file'; a file named `last` is read."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "photos").mkdir()
    cv2.imwrite(str(tmp_path / "photos" / "a.png"), np.zeros((16, 16, 3), np.uint8))
    for word in ("last", "best"):
        code, err = run_main(["predict", str(tmp_path / "photos"), "--ckpt_path", word], capsys)
        assert code == 1 and f"--ckpt_path {word}: no such file; this form of predict takes a checkpoint file" in err
        assert "Fix: give the checkpoint file" in err and not (tmp_path / "runs").exists(), err
    (tmp_path / "last").write_bytes(b"not a checkpoint")  # a file of that name: read as one, and named if bad
    code, err = run_main(["predict", str(tmp_path / "photos"), "--ckpt_path", "last"], capsys)
    assert code == 1 and "last: not a readable checkpoint" in err and "Lightning's words" not in err, err


def test_lightning_s_word_for_a_checkpoint_outside_the_lightning_form_says_where_it_works(tmp_path, capsys,
                                                                                         monkeypatch):
    """`export last` said only 'no such checkpoint file'; a file named so is read."""
    monkeypatch.chdir(tmp_path)
    code, err = run_main(["export", "last"], capsys)
    assert code == 1 and "last: no such checkpoint file; `last` is Lightning's word for a checkpoint" in err, err
    assert "Fix: give the checkpoint file" in err and "Traceback" not in err
    code, err = run_main(["export", "lastly.ckpt"], capsys)  # not one of the words: no hint
    assert code == 1 and "lastly.ckpt: no such checkpoint file" in err and "Lightning's word" not in err, err


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc, where no folder can be made")
def test_an_output_folder_no_one_can_make_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """os.access says root may write in /proc; mkdir says otherwise. Before, synth and fit stopped later with a raw
    `[Errno 2] No such file or directory` and the fix `check the path`."""
    from dapm_lightning.data.files import check_folder_writable

    monkeypatch.chdir(tmp_path)
    code, err = run_main(["synth", "--out", "/proc/dapm_out", "--train", "2", "--val", "1", "--size", "16"], capsys)
    refused = "nothing can be made in /proc: " if os.geteuid() == 0 else "/proc is read-only or not yours"
    assert code == 1 and f"/proc/dapm_out: cannot be written ({refused}" in err, err
    assert "Fix: give another output folder (--out)" in err
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--trainer.default_root_dir", "/proc/dapm_run",
                          "--data.init_args.root", str(tmp_path / "data")], capsys)
    assert code == 1 and f"/proc/dapm_run: cannot be written ({refused}" in err, err
    assert "Fix: give another output folder (--trainer.default_root_dir)" in err
    assert list(tmp_path.iterdir()) == []  # no data rendered
    assert check_folder_writable(tmp_path / "a" / "b") == tmp_path / "a" / "b" and list(tmp_path.iterdir()) == []
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--trainer.default_root_dir", "file:///proc/dapm_run",
                          "--data.init_args.root", str(tmp_path / "data")], capsys)
    assert code == 1 and f"/proc/dapm_run: cannot be written ({refused}" in err, err  # not ./file:/proc/dapm_run
    assert list(tmp_path.iterdir()) == []
