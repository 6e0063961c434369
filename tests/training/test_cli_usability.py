"""The command line's user errors and defaults: foreign checkpoints, unknown options, unknown backbones,
no logger, GPU configs on a CPU machine, logs under default_root_dir."""

import re
import subprocess
import sys
import warnings
from pathlib import Path

import lightning as L
import pytest
import torch
import yaml
from lightning.pytorch.callbacks import LearningRateMonitor

from dapm_lightning.training import lightning_cli
from dapm_lightning.training.callbacks import DepthPanelLogger
from dapm_lightning.training.checkpointing import NotADAPMCheckpointError, load_dapm_module
from dapm_lightning.training.lightning_cli import run_lightning_cli
from dapm_lightning.training.module import DAPMModule
from tests.conftest import CONFIGS, QUICKSTART, run_main

PAPER = CONFIGS / "paper" / "uapd_dapm.yaml"
UAPD = ["--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.batch_size", "2",
        "--data.init_args.num_workers", "0", "--trainer.enable_progress_bar", "false"]


class Linear(L.LightningModule):
    def __init__(self, width: int = 3):
        super().__init__()
        self.save_hyperparameters()
        self.layer = torch.nn.Linear(2, width)

    def training_step(self, batch, batch_idx):
        return self.layer(batch[0]).square().mean()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


@pytest.fixture(scope="module")
def foreign(tmp_path_factory):
    """Another Lightning model's checkpoint, a plain state dict and a DAPM network's bare state dict."""
    folder = tmp_path_factory.mktemp("foreign")
    trainer = L.Trainer(max_steps=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        enable_model_summary=False)
    trainer.fit(Linear(), torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(4, 2)), batch_size=2))
    trainer.save_checkpoint(folder / "other.ckpt")
    torch.save(torch.nn.Linear(2, 1).state_dict(), folder / "plain.pth")
    torch.save(DAPMModule().state_dict(), folder / "dapm_weights.pth")
    return folder


def test_load_dapm_module_builds_the_checkpoints_model(checkpoint):
    module = load_dapm_module(checkpoint).eval()
    reference = DAPMModule.load_from_checkpoint(checkpoint, weights_only=True).eval()
    assert isinstance(module, DAPMModule) and module.net_config == reference.net_config
    assert module.train_image_size == reference.train_image_size == (24, 40)
    image = torch.rand(1, 3, 24, 40)
    with torch.no_grad():
        torch.testing.assert_close(module(image).depth_m, reference(image).depth_m, rtol=0, atol=0)
    assert next(load_dapm_module(str(checkpoint), map_location=torch.device("cpu")).parameters()).device.type == "cpu"


def test_load_dapm_module_says_what_a_foreign_file_is(foreign, checkpoint, tmp_path):
    cases = {"other.ckpt": r"a Lightning checkpoint of another model: 2 weight tensor\(s\) such as 'layer.weight'",
             "plain.pth": r"a plain PyTorch state dict, another model's weights \('weight', 'bias'\)",
             "dapm_weights.pth": r"a plain PyTorch state dict, the weights of a DAPM network"}
    for name, what in cases.items():
        path = foreign / name
        with pytest.raises(NotADAPMCheckpointError, match=rf"{path}: not a dapm-lightning checkpoint \({what}"):
            load_dapm_module(path)
        with pytest.raises(ValueError, match=r"\nFix: pass a checkpoint written by `dapm-lightning fit`"):
            load_dapm_module(path)
    damaged = tmp_path / "cut.ckpt"
    damaged.write_bytes(checkpoint.read_bytes()[:4096])
    with pytest.raises(RuntimeError, match="cut.ckpt: not a readable checkpoint"):
        load_dapm_module(damaged)
    with pytest.raises(FileNotFoundError, match="missing.ckpt"):
        load_dapm_module(tmp_path / "missing.ckpt")


@pytest.mark.parametrize("subcommand", ["fit", "validate", "test", "predict"])
def test_ckpt_path_of_another_model_is_one_short_message(subcommand, foreign, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for name, what in (("other.ckpt", "a Lightning checkpoint of another model"),
                       ("plain.pth", "a plain PyTorch state dict")):
        path = foreign / name
        code, err = run_main([subcommand, "--config", str(QUICKSTART), "--ckpt_path", str(path),
                              "--trainer.logger", "false"], capsys)
        assert code == 1 and f"{path}: not a dapm-lightning checkpoint ({what}" in err, err
        assert "Fix: pass a checkpoint written by `dapm-lightning fit`" in err
        assert len(err.splitlines()) <= 4 and "pytorch-lightning_version" not in err, err


@pytest.mark.parametrize("subcommand", ["validate", "test", "predict"])
def test_evaluating_without_trained_weights_is_refused(subcommand, tmp_path, capsys, monkeypatch):
    """No --ckpt_path, or ``last`` finding nothing: refused before anything is read or written, not a random network."""
    monkeypatch.chdir(tmp_path)
    run = tmp_path / "empty_run"
    if subcommand == "predict":
        (tmp_path / "imgs").mkdir()
        config = ["--config", str(CONFIGS / "predict.yaml"), "--data.init_args.source", str(tmp_path / "imgs"),
                  "--trainer.default_root_dir", str(run)]
    else:
        config = ["--config", str(QUICKSTART), "--trainer.logger", "false", "--trainer.default_root_dir", str(run)]
    code, err = run_main([subcommand, *config], capsys)
    assert code == 1 and len(err.splitlines()) <= 4, err
    assert f"error: {subcommand}: no weights to {subcommand} with: neither --ckpt_path nor --model.init_weights" in err
    assert "Fix: --ckpt_path CKPT" in err and ("--ckpt_path last" in err) == (subcommand != "predict"), err
    code, err = run_main([subcommand, *config, "--ckpt_path", "last"], capsys)
    assert code == 1 and len(err.splitlines()) <= 4, err
    assert f"error: {subcommand} --ckpt_path last: looked for the run's newest checkpoint under {run}: no last.ckpt" \
           in err and "Fix: --trainer.default_root_dir" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == (["imgs"] if subcommand == "predict" else [])


@pytest.mark.parametrize("setup", ["training config", "no writer"])
def test_predict_that_would_write_nothing_is_refused(setup, checkpoint, tmp_path, capsys, monkeypatch):
    """A training config's data module (labelled samples) or no prediction writer: refused, naming what works."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "imgs").mkdir()
    if setup == "training config":
        config = ["--config", str(QUICKSTART), "--trainer.logger", "false"]
        reason = "its data module is SyntheticDataModule, which serves labelled samples, not PredictDataModule"
    else:
        config = ["--config", str(CONFIGS / "predict.yaml"), "--data.init_args.source", str(tmp_path / "imgs"),
                  "--trainer.callbacks=[]"]
        reason = "no prediction writer callback (PredictionWriter) writes its outputs"
    code, err = run_main(["predict", *config, "--ckpt_path", str(checkpoint)], capsys)
    assert code == 1 and len(err.splitlines()) <= 4 and "Traceback" not in err, err
    assert "predict with this configuration would write nothing: " in err and reason in err, err
    assert "Fix: `dapm-lightning predict SOURCE --ckpt_path CKPT --out OUT`" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["imgs"]


def test_evaluating_with_init_weights_uses_them(checkpoint, tiny_uapd, tmp_path, monkeypatch):
    """``--model.init_weights`` is weights too: the same figures as ``--ckpt_path`` with the same file."""
    monkeypatch.chdir(tmp_path)
    common = ["test", "--config", str(QUICKSTART), *UAPD, "--data.init_args.root", str(tiny_uapd), "--trainer.logger",
              "false"]
    given = run_lightning_cli([*common, "--ckpt_path", str(checkpoint)]).trainer.callback_metrics
    initial = run_lightning_cli([*common, "--model.init_weights", str(checkpoint)])
    assert initial.trainer.ckpt_path is None and initial.model.weights_are_final
    assert initial.model.train_image_size == (24, 40)  # recorded in the checkpoint: predict's network size
    for key in ("test_depth_abs_rel", "test_pose_pitch_median"):
        assert torch.equal(initial.trainer.callback_metrics[key], given[key]), key


def test_unknown_options_are_a_few_lines_with_the_closest(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--trainer.max_stpes", "3"], capsys)
    assert code == 2 and len(err.splitlines()) <= 4, err
    assert "unknown option --trainer.max_stpes" in err and "did you mean --trainer.max_steps?" in err
    assert "see `dapm-lightning fit --help`" in err
    code, err = run_main(["test", "--config", str(QUICKSTART), "--data.init_args.batchsize", "3"], capsys)
    assert code == 2 and len(err.splitlines()) <= 4, err
    assert "did you mean --data.init_args.batch_size?" in err and "dapm-lightning test --help" in err
    typo = tmp_path / "typo.yaml"
    typo.write_text("trainer:\n  max_stpes: 3\n")
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--config", str(typo)], capsys)
    assert code == 2 and "trainer.max_stpes" in err and "did you mean --trainer.max_steps?" in err, err
    assert f"unknown setting trainer.max_stpes (set in {typo})" in err, err  # the file that holds it
    typo.write_text("data:\n  init_args:\n    batchsize: 3\n")
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--config", str(typo)], capsys)
    assert code == 2 and f"(--data.init_args.batchsize, set in {typo})" in err, err


@pytest.mark.parametrize(("option", "value", "expected"), [
    ("batch_size", "two", "error: --data.init_args.batch_size: expected int. Got value: two"),
    ("on_bad_file", "skipp", "error: --data.init_args.on_bad_file: Expected a typing.Literal['raise', 'skip']. Got "
                             "value: skipp"),
])
def test_a_data_setting_of_the_wrong_type_is_one_line_naming_it(option, value, expected, capsys, tmp_path,
                                                                 monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = tmp_path / "wrong.yaml"
    config.write_text(f"data:\n  init_args:\n    {option}: {value}\n")
    for args in ([f"--data.init_args.{option}", value], ["--config", str(config)]):
        code, err = run_main(["fit", "--config", str(QUICKSTART), *args], capsys)
        assert code == 2 and expected in err and len(err.splitlines()) <= 3 and "Union" not in err, err


@pytest.mark.parametrize(("option", "value", "expected"), [
    ("--trainer.max_steps", "two", "error: --trainer.max_steps: expected int. Got value: two"),
    ("--model.net.igd.max_depth", "nan", "error: --model.net.igd.max_depth: expected a finite number. Got value: nan"),
    ("--data.init_args.max_depth", "inf",
     "error: --data.init_args.max_depth: expected a finite number. Got value: inf"),
])
def test_a_value_of_the_wrong_type_is_one_line_naming_its_setting(option, value, expected, capsys, tmp_path,
                                                                  monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = run_main(["fit", "--config", str(QUICKSTART), option, value], capsys)
    assert code == 2 and expected in err and len(err.splitlines()) <= 2, err


def test_a_value_of_the_wrong_type_in_a_config_file_names_the_file(capsys, tmp_path, monkeypatch):
    """As an unknown key in a file does (before: the setting only)."""
    monkeypatch.chdir(tmp_path)
    wrong = tmp_path / "wrongtype.yaml"
    for content, expected in (("trainer:\n  max_steps: two\n", "--trainer.max_steps: expected int. Got value: two"),
                              ("data:\n  init_args:\n    batch_size: many\n",
                               "--data.init_args.batch_size: expected int. Got value: many")):
        wrong.write_text(content)
        code, err = run_main(["fit", "--config", str(QUICKSTART), "--config", str(wrong)], capsys)
        assert code == 2 and f"error: {expected} (set in {wrong})\n" in err, err
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--trainer.max_steps", "two"], capsys)
    assert code == 2 and "Got value: two\n" in err and "set in" not in err, err  # the command line's: no file


def test_a_typo_in_a_class_path_is_a_few_lines_naming_the_file_and_the_closest_class(capsys, tmp_path, monkeypatch):
    """A class_path that cannot be imported gave jsonargparse's 12-20 lines about union subtypes."""
    monkeypatch.chdir(tmp_path)
    config = tmp_path / "typo.yaml"
    for content, key, typed, meant in (
            ("data:\n  class_path: dapm_lightning.data.UAPDDataModul\n", "data", "dapm_lightning.data.UAPDDataModul",
             "dapm_lightning.data.datamodules.UAPDDataModule"),
            ("trainer:\n  callbacks:\n  - class_path: lightning.pytorch.callbacks.ModelChekpoint\n",
             "trainer.callbacks", "lightning.pytorch.callbacks.ModelChekpoint",
             "lightning.pytorch.callbacks.ModelCheckpoint")):
        config.write_text(content)
        code, err = run_main(["fit", "--config", str(QUICKSTART), "--config", str(config)], capsys)
        assert code == 2 and len(err.splitlines()) == 3 and "Union" not in err, err
        assert err.startswith(f"error: {key}: no class {typed}: ") and f"(set in {config})\n" in err, err
        assert f"  {typed}: did you mean {meant}?" in err, err


@pytest.mark.parametrize(("option", "value"), [("batch_size", "-2"), ("eval_batch_size", "0"), ("num_workers", "-1"),
                                               ("seed", "-1")])
def test_a_data_setting_out_of_range_is_refused_before_anything_is_rendered(option, value, capsys, tmp_path,
                                                                            monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = run_main(["fit", "--config", str(QUICKSTART), f"--data.init_args.{option}", value,
                          "--data.init_args.root", str(tmp_path / "never_rendered")], capsys)
    assert code == 1 and f"error: data.init_args.{option}: {value}, but it must be a whole number" in err, err
    assert f"Fix: e.g. --data.init_args.{option}" in err and "Union" not in err and "Namespace" not in err, err
    assert not (tmp_path / "never_rendered").exists()


def test_a_setting_given_twice_in_one_config_is_named_with_both_lines(capsys, tmp_path, monkeypatch):
    """YAML keeps the second of two equal keys without a word: a config edited twice ran with one of its values."""
    monkeypatch.chdir(tmp_path)
    twice = tmp_path / "twice.yaml"
    twice.write_text("trainer:\n  max_steps: 3\n  devices: 1\n  max_steps: 5\n")
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--config", str(twice)], capsys)
    assert code == 2 and f"{twice}: trainer.max_steps is set twice (lines 2 and 4)" in err, err
    assert "fix: keep one of the two lines" in err and not (tmp_path / "outputs").exists()
    from dapm_lightning.training.lightning_cli import repeated_key

    assert repeated_key("data:\n  init_args:\n    augmentation: {hflip_p: 0.5, hflip_p: 0}\n") == (
        "data.init_args.augmentation.hflip_p", 3, 3)
    assert repeated_key("a: 1\nb: {a: 2}\nc:\n- {a: 1}\n- {a: 2}\n") is None  # one key per mapping


def test_a_config_given_by_a_relative_path_in_another_folder_is_named(capsys, tmp_path, monkeypatch):
    """The parser reads a config from inside its folder: `--config in/broken.yaml` was looked for there as
    `in/in/broken.yaml`, so the YAML error lost the file's name and line, and a wrong type its `(set in FILE)`."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "broken.yaml").write_text("trainer:\n  max_steps: 3\n   devices: [1,\n")
    (tmp_path / "in" / "typed.yaml").write_text("trainer:\n  max_steps: two\n")
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--config", "in/broken.yaml"], capsys)
    assert code == 2 and f"{tmp_path / 'in' / 'broken.yaml'}: not valid YAML (line 3, column 11)" in err, err
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--config", "in/typed.yaml"], capsys)
    assert code == 2 and f"(set in {tmp_path / 'in' / 'typed.yaml'})" in err, err


@pytest.mark.parametrize(("given", "said"), [("nosuch.yaml", "no such file"),
                                             ("folder", "a folder, not a config file")])
def test_a_config_path_that_is_no_file_is_named_with_the_fix(given, said, capsys, tmp_path, monkeypatch):
    """jsonargparse's 'Parser key "config": File does not exist' gave no fix."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "folder").mkdir()
    code, err = run_main(["fit", "--config", given], capsys)
    assert code == 2 and err.splitlines()[:2] == [
        f"error: --config {tmp_path / given}: {said}",
        f"  fix: give a YAML config file (relative paths start from the current directory, {tmp_path}); the shipped "
        "ones: configs/paper/*.yaml, configs/ablations/*.yaml, dapm_lightning/configs/quickstart.yaml"], err


@pytest.mark.parametrize("subcommand", ["fit", "test"])
def test_a_config_that_is_not_yaml_is_named_with_its_line(subcommand, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    broken = tmp_path / "broken.yaml"
    broken.write_text("trainer:\n  max_steps: 3\n   devices: [1,\n")
    code, err = run_main([subcommand, "--config", str(QUICKSTART), f"--config={broken}"], capsys)
    assert code == 2 and len(err.splitlines()) <= 4, err
    assert f"{broken}: not valid YAML (line 3, column 11)" in err and "fix: correct the file" in err, err
    assert "<unicode string>" not in err and f"dapm-lightning {subcommand} --help" in err


@pytest.mark.parametrize(("name", "content", "said", "fix"), [
    ("good.ckpt", None, "not a YAML text file (byte N is not UTF-8 text: a checkpoint or other binary file)",
     "fix: a checkpoint goes to --ckpt_path"),
    ("photo.png", b"\x89PNG\r\n\x1a\n\x00\x00", "not a YAML text file (byte N is not UTF-8 text: a binary file)",
     "fix: give --config a YAML file of settings"),
    ("empty.yaml", b"", "no settings in it (the file is empty)", "fix: give --config a YAML file of settings"),
    ("notes.yaml", b"# to do\n", "no settings in it (only comments)", "or leave out --config"),
    ("list.yaml", b"- fit\n- test\n", "not a mapping of settings (the file holds a list)",
     "fix: give --config a YAML file of settings"),
])
@pytest.mark.parametrize("subcommand", ["fit", "test"])
def test_a_config_that_holds_no_settings_is_named_with_the_fix(subcommand, name, content, said, fix, checkpoint,
                                                              capsys, tmp_path, monkeypatch):
    """A checkpoint given as --config was "error: 'utf-8' codec can't decode byte 0x80...", exit 1; an empty file
    "error: Unexpected config:"."""
    monkeypatch.chdir(tmp_path)
    config = tmp_path / name
    config.write_bytes(checkpoint.read_bytes() if content is None else content)
    for words in ([f"--config={config}"], ["--config", str(QUICKSTART), "--config", str(config)]):
        code, err = run_main([subcommand, *words], capsys)
        assert code == 2 and len(err.splitlines()) <= 3, err
        first = r"byte \d+".join(map(re.escape, f"error: {config}: {said}\n  fix: ".split("byte N")))  # byte N: any
        assert re.match(first, err) and fix in err.splitlines()[1], err
        assert "codec" not in err and "Unexpected config" not in err and f"dapm-lightning {subcommand} --help" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]  # nothing rendered, no run folder


@pytest.mark.parametrize("option", [["--trainer.max_step", "3"], ["--model.net.backbon", "resnet18"]])
def test_abbreviated_options_are_refused(option, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = run_main(["fit", "--config", str(QUICKSTART), *option, "--print_config"], capsys)  # accepted: exit 0
    assert code == 2 and f"unknown option {option[0]}" in err and f"did you mean {option[0]}" in err, err


def test_unknown_backbone_names_the_setting(capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--model.net.backbone", "resnet5O",
                          "--data.init_args.root", str(tmp_path / "never_rendered")], capsys)
    assert code == 1 and "model.net.backbone: unknown timm model 'resnet5O' (closest: resnet50" in err, err
    assert "timm.list_models('resnet*')" in err and not (tmp_path / "never_rendered").exists()


def test_without_a_logger_the_callbacks_that_need_one_are_left_out(tiny_uapd, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    notes = []
    monkeypatch.setattr(lightning_cli, "rank_zero_info", notes.append)
    cli = run_lightning_cli(["fit", "--config", str(QUICKSTART), *UAPD, "--data.init_args.root", str(tiny_uapd),
                             "--trainer.logger", "false", "--trainer.max_steps", "1"])
    assert cli.trainer.global_step == 1 and not cli.trainer.loggers
    assert not [c for c in cli.trainer.callbacks if isinstance(c, (LearningRateMonitor, DepthPanelLogger))]
    assert notes == ["note: no logger (trainer.logger false): left out DepthPanelLogger, LearningRateMonitor, which "
                     "need one"]
    with_logger = run_lightning_cli(["--config", str(QUICKSTART), *UAPD, "--data.init_args.root", str(tiny_uapd)],
                                    run=False)
    kept = [type(c) for c in with_logger.trainer.callbacks]
    assert LearningRateMonitor in kept and DepthPanelLogger in kept
    assert DepthPanelLogger(output_dir="panels").needs_logger is False


def test_evaluation_of_a_gpu_config_falls_back_to_the_cpu_and_fit_refuses(checkpoint, tiny_uapd, tmp_path, capsys,
                                                                         monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    notes = []
    monkeypatch.setattr(lightning_cli, "rank_zero_info", notes.append)
    common = ["--config", str(PAPER), *UAPD, "--data.init_args.root", str(tiny_uapd), "--data.init_args.pin_memory",
              "false", "--data.init_args.persistent_workers", "false", "--trainer.logger", "false",
              "--trainer.default_root_dir", str(tmp_path)]
    cli = run_lightning_cli(["validate", *common, "--ckpt_path", str(checkpoint)])
    trainer = cli.trainer
    assert trainer.accelerator.__class__.__name__ == "CPUAccelerator" and trainer.world_size == 1
    assert trainer.num_nodes == 1 and "val_loss" in trainer.callback_metrics
    assert any(n.startswith("note: no GPU on this machine: validate runs on the CPU") and "devices 4" in n
               for n in notes), notes
    code, err = run_main(["fit", *common], capsys)
    assert code == 1 and "trainer.accelerator: gpu, but this machine has no GPU" in err and "Fix:" in err, err


def test_quickstart_logs_and_checkpoints_follow_default_root_dir(tiny_uapd, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    root = tmp_path / "D"
    cli = run_lightning_cli(["fit", "--config", str(QUICKSTART), *UAPD, "--data.init_args.root", str(tiny_uapd),
                             "--trainer.max_steps", "1", "--trainer.limit_val_batches", "1",
                             "--trainer.default_root_dir", str(root)])
    assert [Path(logger.save_dir) for logger in cli.trainer.loggers] == [root, root]
    assert list((root / "tensorboard" / "version_0").glob("events.out.tfevents.*"))
    assert (root / "csv" / "version_0" / "metrics.csv").is_file()
    assert (root / "tensorboard" / "version_0" / "checkpoints" / "last.ckpt").is_file()
    assert not (tmp_path / "outputs").exists()  # the config's own default_root_dir is not used
    explicit = run_lightning_cli(["--config", str(QUICKSTART), *UAPD, "--data.init_args.root", str(tiny_uapd),
                                  "--trainer.default_root_dir", str(root), "--trainer.logger+=CSVLogger",
                                  "--trainer.logger.save_dir", str(tmp_path / "elsewhere")], run=False)
    assert Path(explicit.trainer.loggers[-1].save_dir) == tmp_path / "elsewhere"  # an explicit save_dir is kept


def small_fit(tiny_uapd, root, *extra):
    """``fit`` of a small network for one step into ``root``, without validation."""
    return ["fit", "--config", str(QUICKSTART), *UAPD, "--data.init_args.root", str(tiny_uapd),
            "--trainer.limit_val_batches", "0", "--trainer.max_steps", "1", "--trainer.default_root_dir", str(root),
            "--model.net.backbone", "mobilenetv3_small_050", "--model.net.decoder_channels", "16",
            "--model.net.head_channels", "8", "--model.net.pose_hidden", "32", *extra]


def test_a_first_fit_with_ckpt_path_last_says_it_starts_from_scratch(tiny_uapd, tmp_path, monkeypatch):
    """A job always launched with ``--ckpt_path last``: its first run says it starts from scratch, without Lightning's
    hint to set ``ModelCheckpoint(save_last=True)`` (the project's LastCheckpoint writes last.ckpt)."""
    monkeypatch.chdir(tmp_path)
    said: list[str] = []  # what the CLI tells the user (Lightning's logger, whose handlers other tests change)
    monkeypatch.setattr(lightning_cli, "rank_zero_info", lambda message, *args, **kwargs: said.append(message))
    with warnings.catch_warnings(record=True) as warned:
        warnings.simplefilter("always")
        cli = run_lightning_cli(small_fit(tiny_uapd, tmp_path / "run", "--ckpt_path", "last"))
    assert cli.trainer.global_step == 1
    assert f"--ckpt_path last: no checkpoint of this run yet under {tmp_path / 'run'}: training starts from " \
           "scratch" in said, said
    assert not [w for w in warned if "no last checkpoint" in str(w.message) or "save_last" in str(w.message)]


def test_a_second_fit_without_a_logger_does_not_write_over_the_first(tiny_uapd, tmp_path, capsys, monkeypatch):
    """Without a logger every run writes ROOT/checkpoints/last.ckpt and ROOT/config.yaml: a second run into the same
    folder used to replace the first one's (only Lightning's "exists and is not empty" notice)."""
    monkeypatch.chdir(tmp_path)
    root = tmp_path / "run"
    fit = small_fit(tiny_uapd, root, "--trainer.logger", "false")
    run_lightning_cli(fit)
    kept = {path: path.read_bytes() for path in (root / "checkpoints" / "last.ckpt", root / "config.yaml")}
    code, err = run_main([*fit, "--trainer.max_steps", "2"], capsys)
    assert code == 1 and len(err.splitlines()) <= 3, err
    assert (f"error: fit: {root} holds an earlier run without a logger ({root / 'checkpoints' / 'last.ckpt'}, "
            f"{root / 'config.yaml'}); this run would write over it") in err, err
    assert "Fix: resume that run with --ckpt_path last, or start this one in a folder of its own: " \
           "--trainer.default_root_dir NEW_DIR" in err, err
    assert {path: path.read_bytes() for path in kept} == kept  # nothing written over
    resumed = run_lightning_cli([*fit, "--trainer.max_steps", "2", "--ckpt_path", "last"])  # the fix: resumes
    assert resumed.trainer.global_step == 2
    other = run_lightning_cli([*fit, "--trainer.default_root_dir", str(tmp_path / "other")])  # the other fix
    assert other.trainer.global_step == 1 and (tmp_path / "other" / "checkpoints" / "last.ckpt").is_file()
    # a requeued job (always --ckpt_path last) whose every checkpoint is damaged starts afresh there, not refused
    for path in (root / "checkpoints").glob("*.ckpt"):
        path.write_bytes(path.read_bytes()[:300])
    with pytest.warns(UserWarning, match="starting from scratch"):
        again = run_lightning_cli([*fit, "--ckpt_path", "last"])
    assert again.trainer.global_step == 1


def test_a_second_fit_into_a_fixed_checkpoint_folder_is_refused_on_every_rank(tiny_uapd, tmp_path, capsys,
                                                                              monkeypatch):
    """With a logger each fit logs into a new version folder, but a checkpoint callback's fixed dirpath is the same
    folder for every run: a second new fit used to replace the first one's checkpoints there (Lightning only warned).
    The check runs in every process (here as rank 1), so that no DDP process waits for one that refused."""
    monkeypatch.chdir(tmp_path)
    ckpts = tmp_path / "ckpts"
    (tmp_path / "job.yaml").write_text(yaml.safe_dump({"trainer": {"callbacks": [
        {"class_path": "dapm_lightning.training.checkpointing.LastCheckpoint",
         "init_args": {"dirpath": str(ckpts)}}]}}))
    fit = small_fit(tiny_uapd, tmp_path / "run", "--config", str(tmp_path / "job.yaml"))
    assert run_lightning_cli(fit).trainer.loggers  # the quickstart's loggers: this run logged into version_0
    kept = {path: path.read_bytes() for path in ckpts.iterdir()}
    assert list(kept) == [ckpts / "last.ckpt"]
    for rank in (0, 1):
        monkeypatch.setattr(L.Trainer, "global_rank", property(lambda trainer, rank=rank: rank))
        code, err = run_main([*fit, "--trainer.max_steps", "2", "--trainer.default_root_dir", str(tmp_path / "b")],
                             capsys)
        assert code == 1 and len(err.splitlines()) <= 3, err
        assert (f"error: fit: {ckpts} holds the checkpoints of an earlier run ({ckpts / 'last.ckpt'}); this run would "
                "write over them") in err, err
        assert "Fix: resume that run with --ckpt_path last, or give this run a folder of its own: a new dirpath" in err
    monkeypatch.undo()
    monkeypatch.chdir(tmp_path)
    assert {path: path.read_bytes() for path in ckpts.iterdir()} == kept  # nothing written over
    resumed = run_lightning_cli([*fit, "--trainer.max_steps", "2", "--ckpt_path", "last"])  # the fix: resumes
    assert resumed.trainer.global_step == 2
    (tmp_path / "job.yaml").write_text((tmp_path / "job.yaml").read_text().replace(str(ckpts), str(tmp_path / "other")))
    other = run_lightning_cli(fit)  # the other fix: a folder of its own
    assert other.trainer.global_step == 1 and (tmp_path / "other" / "last.ckpt").is_file()


def test_evaluation_without_a_logger_keeps_the_config_of_the_fit(tiny_uapd, tmp_path, monkeypatch):
    """validate and test without a logger save their config into the fit's folder as config_validate.yaml and
    config_test.yaml: they used to replace the fit's config.yaml, which the fit resumes from. predict saves none."""
    monkeypatch.chdir(tmp_path)
    root = tmp_path / "run"
    fit = small_fit(tiny_uapd, root, "--trainer.logger", "false")
    run_lightning_cli(fit)
    config = (root / "config.yaml").read_bytes()
    for subcommand in ("validate", "test"):
        run_lightning_cli([subcommand, *fit[1:], "--trainer.limit_val_batches", "1", "--ckpt_path", "last"])
        saved = yaml.safe_load((root / f"config_{subcommand}.yaml").read_text())
        assert saved["ckpt_path"] == str(root / "checkpoints" / "last.ckpt")
    assert (root / "config.yaml").read_bytes() == config
    before = sorted(root.rglob("*"))
    run_lightning_cli(["predict", "--config", str(CONFIGS / "predict.yaml"), "--ckpt_path", "last",
                       "--trainer.default_root_dir", str(root), "--data.init_args.num_workers", "0",
                       "--data.init_args.source", str(tiny_uapd / "val" / "rgb"),
                       "--trainer.callbacks.output_dir", str(tmp_path / "out")])
    assert sorted(root.rglob("*")) == before and not list(tmp_path.glob("*.yaml"))
    resumed = run_lightning_cli(["fit", "--config", str(root / "config.yaml"), "--trainer.max_steps", "2",
                                 "--ckpt_path", "last"])  # the fit's own config, as a requeued job resumes
    assert resumed.trainer.global_step == 2


@pytest.mark.parametrize("argv,shown", [(["--help"], "subcommands:"), (["predict", "--help"], "--telemetry FILE")])
def test_help_imports_no_torch(argv, shown):
    """`dapm-lightning --help` and `predict --help` answer at once: nothing heavy is imported for them (PyTorch
    alone takes seconds to import on a small machine)."""
    code = (f"import sys; from dapm_lightning.cli import main\ntry:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
            "heavy = [m for m in ('torch', 'lightning', 'cv2', 'numpy') if m in sys.modules]; assert not heavy, heavy")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr[-2000:]
    assert shown in result.stdout
