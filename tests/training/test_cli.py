"""End to end through the real CLI, in-process, on tiny generated data."""

import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch
import yaml

from dapm_lightning.cli import main
from dapm_lightning.data.datamodules import DAPMDataModule, PotsdamDataModule
from dapm_lightning.models import TeacherForcing
from dapm_lightning.training.checkpointing import SafeCheckpointIO, find_last_checkpoint
from dapm_lightning.training.lightning_cli import run_lightning_cli
from dapm_lightning.training.module import DAPMModule
from dapm_lightning.training.viewpoints import ViewpointBreakdown
from tests.conftest import CONFIGS, QUICKSTART

PAPER = CONFIGS / "paper" / "uapd_dapm.yaml"
CPU = ["--trainer.accelerator", "cpu", "--trainer.devices", "1", "--trainer.strategy", "auto",
       "--trainer.sync_batchnorm", "false", "--trainer.precision", "32-true", "--model.net.backbone", "resnet18",
       "--model.net.pretrained", "false", "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
       "--data.init_args.pin_memory", "false", "--data.init_args.persistent_workers", "false"]


def fast_fit(config_args, root, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return run_lightning_cli(["fit", *config_args, *CPU, "--data.init_args.root", str(root),
                              "--trainer.fast_dev_run", "1", "--trainer.default_root_dir", str(tmp_path)])


@pytest.mark.slow  # each ablation's model is built and checked in the fast tier (test_every_config_parses)
@pytest.mark.parametrize("ablation", sorted(p.name for p in (CONFIGS / "ablations").glob("*.yaml")))
def test_every_ablation_trains_a_step(ablation, tiny_uapd, tmp_path, monkeypatch):
    cli = fast_fit(["--config", str(PAPER), "--config", str(CONFIGS / "ablations" / ablation)], tiny_uapd, tmp_path,
                   monkeypatch)
    assert cli.trainer.global_step == 1
    overrides = yaml.safe_load((CONFIGS / "ablations" / ablation).read_text())["model"]

    def check(expected, got, where):
        for key, value in expected.items():
            if isinstance(value, dict):
                check(value, got[key], f"{where}.{key}")
            else:
                assert got[key] == value, f"{where}.{key}"

    check(overrides, cli.model.hparams, "model")


@pytest.mark.parametrize("config", ["uapd_dapm.yaml", "uapd_dapm_d.yaml", "uapd_dapm_p.yaml"])
def test_paper_configs_train_a_step(config, tiny_uapd, tmp_path, monkeypatch):
    cli = fast_fit(["--config", str(CONFIGS / "paper" / config)], tiny_uapd, tmp_path, monkeypatch)
    assert cli.trainer.global_step == 1
    assert "val_loss" in cli.trainer.callback_metrics


def test_potsdam_config_trains_depth_only(tiny_potsdam, tmp_path, monkeypatch):
    cli = fast_fit(["--config", str(CONFIGS / "paper" / "potsdam_dapm_d.yaml"), "--data.init_args.crop_size", "32"],
                   tiny_potsdam, tmp_path, monkeypatch)
    assert cli.trainer.global_step == 1
    assert not cli.model.hparams["net"]["use_pose"]
    dm = PotsdamDataModule(root=str(tiny_potsdam), crop_size=32)
    dm.setup("fit")
    assert len(dm.datasets["train"]) + len(dm.datasets["val"]) == 12
    assert len(dm.datasets["val"]) == 2 and not set(dm.datasets["train"].names) & set(dm.datasets["val"].names)


def test_quickstart_config_fit_test_and_outputs(tiny_uapd, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    common = ["--config", str(QUICKSTART), "--data.class_path",
              "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(tiny_uapd),
              "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0"]
    run_lightning_cli(["fit", *common, "--trainer.max_epochs", "1", "--trainer.limit_train_batches", "2"])
    last = find_last_checkpoint([tmp_path / "outputs"])
    assert last is not None and torch.load(last, weights_only=True)["global_step"] == 2
    said = capsys.readouterr().out  # the fit's closing lines name the files it saved, each there
    named = dict(line.split(": ", 1) for line in said.splitlines() if line.endswith(".ckpt"))
    best = next(path for what, path in named.items() if what.startswith("best checkpoint (val_"))
    assert Path(named["last checkpoint (step 2)"]).resolve() == last.resolve() and Path(best).is_file()
    evaluate = next(line for line in said.splitlines() if line.startswith("evaluate it: "))
    assert evaluate.endswith(f"--ckpt_path {best}")
    run_config = evaluate.split("--config ", 1)[1].split(" --ckpt_path")[0]  # the run's saved config.yaml
    assert Path(run_config).resolve() == last.resolve().parents[1] / "config.yaml"
    with warnings.catch_warnings(record=True) as said_while_testing:
        warnings.simplefilter("always")
        test = run_lightning_cli(["test", *common, "--ckpt_path", "last"])  # found in the fit's log version
    # the fit's checkpoint rankings are not restored into a test (before: "The dirpath has changed ...")
    assert not [w for w in said_while_testing if "dirpath has changed" in str(w.message)]
    assert Path(test.trainer.ckpt_path).resolve() == last.resolve()
    metrics = test.trainer.callback_metrics
    for key in ("test_depth_d1", "test_depth_abs_rel", "test_depthlog_d1", "test_pose_roll_median",
                "test_pose_fov_auc5", "test_loss_pd"):
        assert key in metrics, key
    breakdown = next(c for c in test.trainer.callbacks if isinstance(c, ViewpointBreakdown))
    table = breakdown.table
    assert {r["component"] for r in table} == {"height", "pitch", "roll", "fov"}
    assert sum(r["count"] for r in table if r["component"] == "roll") == 3  # each val image counted once per component
    csvs = [p.read_text() for p in (tmp_path / "outputs" / "quickstart" / "csv").rglob("metrics.csv")]
    assert any("test_view_pitch_bin0_d1" in text for text in csvs)
    assert breakdown.figure is not None and breakdown.figure.is_file()
    assert Path(test.trainer.log_dir) in breakdown.figure.parents  # each test run writes into its own log folder
    assert list(Path(test.trainer.log_dir).glob("panels/test_step*.png"))


def test_checkpoint_roundtrip_identical_predictions(tiny_uapd, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cli = run_lightning_cli(["fit", "--config", str(QUICKSTART), "--data.class_path",
                             "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(tiny_uapd),
                             "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
                             "--trainer.max_steps", "2", "--trainer.limit_val_batches", "0"])
    path = tmp_path / "model.ckpt"
    cli.trainer.save_checkpoint(path)
    loaded = DAPMModule.load_from_checkpoint(path, weights_only=True).eval()
    model = cli.model.eval()
    image = torch.rand(2, 3, 24, 40)
    with torch.no_grad():
        a, b = model(image), loaded(image)
    torch.testing.assert_close(a.depth_m, b.depth_m, rtol=0, atol=0)
    torch.testing.assert_close(a.pose_physical, b.pose_physical, rtol=0, atol=0)
    assert loaded.hparams["net"]["backbone"] == "resnet18" and loaded.net_config == model.net_config


CONFIG_FILES = [*sorted(str(p.relative_to(CONFIGS)) for p in CONFIGS.rglob("*.yaml")), "quickstart.yaml"]
WITHOUT_IGD_FEATURE = {"paper/uapd_dapm_d.yaml", "paper/uapd_dapm_p.yaml", "paper/potsdam_dapm_d.yaml",
                       "ablations/t9_pqb_only.yaml", "ablations/t9_no_pqb_no_igd.yaml",
                       "ablations/t11_igd_loss_only.yaml"}
"""The paper's rows without the IGD feature (Tables 2, 9, 11), written out so a config that drops it fails."""


def parse(config_args):
    """The real CLI's parser (its trainer defaults and seed), nothing run."""
    return run_lightning_cli([*config_args, "--trainer.accelerator", "cpu", "--trainer.devices", "1",
                              "--trainer.strategy", "auto", "--model.net.pretrained", "false"], run=False)


def depth_for_two_poses(net):
    """The refined depth (before the sky map overrides it) of one image, teacher-forced with two distant poses."""
    net = net.eval()
    torch.manual_seed(0)
    image = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        outs = [net(image, TeacherForcing(net.config.igd.normalize(torch.tensor([pose])), 0.0))
                for pose in ([20.0, -90.0, 0.0, 60.0], [90.0, -20.0, 10.0, 100.0])]
    return [None if o.depth is None else o.depth.depth_norm for o in outs]


@pytest.mark.parametrize("path", CONFIG_FILES)
def test_every_config_parses_and_feeds_the_igd_to_the_depth_exactly_where_it_says(path):
    if path == "quickstart.yaml":
        stack = ["--config", str(QUICKSTART)]
    else:
        alone = path.startswith("paper") or path == "predict.yaml"
        stack = [*([] if alone else ["--config", str(PAPER)]), "--config", str(CONFIGS / path)]
    cli = parse(stack)
    assert isinstance(cli.model, DAPMModule)
    assert isinstance(cli.datamodule, DAPMDataModule)
    if path.startswith(("ablations", "variants")):  # a stack runs in a folder of its own: `--ckpt_path last`
        assert cli.trainer.default_root_dir == f"outputs/uapd_dapm+{Path(path).stem}"  # resumes it, not the base's
    if path != "predict.yaml":  # the logs (and checkpoints) go where the run's folder is, wherever it is moved
        assert {logger.save_dir for logger in cli.trainer.loggers} == {cli.trainer.default_root_dir}
    assert isinstance(cli.trainer.strategy.checkpoint_io, SafeCheckpointIO)  # the real CLI's trainer defaults
    low, high = depth_for_two_poses(cli.model.net)
    if path in WITHOUT_IGD_FEATURE:
        assert not cli.model.net.config.use_igd_feature
        assert low is None or torch.equal(low, high), "the depth depends on a pose it should not see"
    else:
        assert cli.model.net.config.use_igd_feature
        assert not torch.equal(low, high), "the depth ignores the IGD it is given"


@pytest.mark.slow
def test_help_and_synth_subprocess():
    out = subprocess.run([sys.executable, "-m", "dapm_lightning", "fit", "--help"], capture_output=True, text=True,
                         check=True).stdout
    assert "--model.net.depth_bins" in out and "--trainer.devices" in out
    synth = subprocess.run([sys.executable, "-m", "dapm_lightning", "synth", "--help"], capture_output=True,
                           text=True, check=True).stdout
    assert "--out" in synth


def test_main_dispatches_synth(tmp_path):
    main(["synth", "--out", str(tmp_path / "s"), "--train", "1", "--val", "1", "--size", "12", "16", "--workers", "1"])
    assert len(list((tmp_path / "s" / "train" / "rgb").glob("*.png"))) == 1


def test_top_level_help_lists_every_subcommand_and_tools_take_settings_files(capsys):
    from dapm_lightning.cli import LIGHTNING_SUBCOMMANDS, TOOLS

    main(["--help"])
    listing = capsys.readouterr().out
    for name in [*LIGHTNING_SUBCOMMANDS, *TOOLS]:
        assert f"\n  {name} " in listing, name
    assert "--debug" in listing
    for tool in ("doctor", "export", "collect-carla"):
        with pytest.raises(SystemExit) as info:
            main([tool, "--help"])
        text = capsys.readouterr().out
        assert info.value.code == 0 and "--config" in text and "--print_config" in text, tool
        assert "``" not in text, f"{tool} --help shows raw RST markup"
        flags = [w.split("=")[0] for w in text.split() if w.startswith("--") and len(w) > 3]
        assert not [f for f in flags if "-" in f[2:]], f"{tool}: one flag style (underscores)"


def test_each_stack_of_configs_runs_in_a_folder_of_its_own(tmp_path):
    """The same overlay on two bases, two overlays, and the base alone: four folders; an explicit folder (the command
    line or a later file) is kept; predict is left alone."""
    from dapm_lightning.training.lightning_cli import stacked_run_folder

    paper, efficient = str(PAPER), str(CONFIGS / "variants" / "efficient.yaml")
    potsdam, t9 = str(CONFIGS / "paper" / "potsdam_dapm_d.yaml"), str(CONFIGS / "ablations" / "t9_pqb_only.yaml")
    planar = str(CONFIGS / "ablations" / "planar_depth.yaml")
    assert stacked_run_folder([paper, efficient], []) == "outputs/uapd_dapm+efficient"
    assert stacked_run_folder([potsdam, efficient], []) == "outputs/potsdam_dapm_d+efficient"
    assert stacked_run_folder([paper, t9, planar], []) == "outputs/uapd_dapm+t9_pqb_only+planar_depth"
    assert stacked_run_folder([paper], []) is None
    assert stacked_run_folder([paper, t9], ["--trainer.default_root_dir", "runs/x"]) is None
    assert stacked_run_folder([paper, t9], ["--trainer.default_root_dir=runs/x"]) is None
    assert stacked_run_folder([paper, t9], [], "predict") is None
    own = tmp_path / "own.yaml"
    own.write_text("trainer:\n  default_root_dir: runs/mine\n")
    assert stacked_run_folder([paper, str(own)], []) is None
    cli = parse(["--config", paper, "--config", t9])  # through the real parser: the loggers follow
    assert cli.trainer.default_root_dir == "outputs/uapd_dapm+t9_pqb_only"
    assert {logger.save_dir for logger in cli.trainer.loggers} == {"outputs/uapd_dapm+t9_pqb_only"}
    shown = subprocess.run([sys.executable, "-m", "dapm_lightning", "fit", "--config", paper, "--config", t9,
                            "--print_config"], capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert shown.returncode == 0 and "default_root_dir: outputs/uapd_dapm+t9_pqb_only" in shown.stdout
    assert "args parameter" not in shown.stderr, shown.stderr  # LightningCLI's note on args given beside sys.argv
