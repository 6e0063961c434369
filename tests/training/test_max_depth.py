"""A depth limit other than UAPD's 1000 m flows from the generator through the data to the model and metrics."""

import pytest
import torch

from dapm_lightning.cli import main
from dapm_lightning.data.datamodules import UAPDDataModule
from dapm_lightning.data.synthetic import generate_uapd
from dapm_lightning.geometry.depth_codec import grey_to_depth
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.training.lightning_cli import run_lightning_cli
from tests.conftest import QUICKSTART, run_main

LIMIT = 500.0


@pytest.fixture(scope="module")
def uapd_500(tmp_path_factory):
    return generate_uapd(tmp_path_factory.mktemp("uapd500"), train=4, val=2, size=(32, 48), seed=3, workers=1,
                         max_depth=LIMIT)


def common(root, model_limit):
    return ["--config", str(QUICKSTART), "--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule",
            "--data.init_args.root", str(root), "--data.init_args.max_depth", str(LIMIT),
            "--model.net.igd.max_depth", str(model_limit), "--data.init_args.batch_size", "2",
            "--data.init_args.num_workers", "0", "--trainer.logger", "false", "--trainer.enable_checkpointing",
            "false", "--trainer.callbacks", "[]"]


def test_a_500_m_data_set_trains_and_tests_with_its_own_limit(uapd_500, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    fit = run_lightning_cli(["fit", *common(uapd_500, LIMIT), "--trainer.max_steps", "2",
                             "--trainer.limit_val_batches", "1"])
    assert fit.trainer.global_step == 2
    depths = torch.stack([fit.datamodule.datasets["val"][i]["depth"] for i in range(2)])
    assert depths.max() == LIMIT and (depths == LIMIT).any()  # grey 255 decodes to the data set's limit
    assert float(grey_to_depth(torch.tensor([254]).numpy(), LIMIT)[0]) < LIMIT
    fit.trainer.save_checkpoint(tmp_path / "fit.ckpt")
    test = run_lightning_cli(["test", *common(uapd_500, LIMIT), "--ckpt_path", str(tmp_path / "fit.ckpt")], run=True)
    metrics = test.trainer.callback_metrics
    assert torch.isfinite(metrics["test_depth_abs_rel"]) and torch.isfinite(metrics["test_pose_height_median"])
    assert test.model.metrics["test_depth"].max_depth == LIMIT
    with torch.no_grad():
        out = test.model.eval()(torch.rand(1, 3, 32, 48))
    assert out.depth_m.max() <= LIMIT


def test_a_limit_the_model_does_not_share_is_refused_before_training(uapd_500, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match=r"up to 500 m .* model.net.igd.max_depth: 500"):
        run_lightning_cli(["fit", *common(uapd_500, 1000.0), "--trainer.max_steps", "1"])


def test_the_synthetic_module_renders_and_records_its_limit(tmp_path):
    from dapm_lightning.data.datamodules import SyntheticDataModule
    from dapm_lightning.data.synthetic import is_current

    dm = SyntheticDataModule(root=str(tmp_path / "s"), train_size=1, val_size=1, image_size=16, max_depth=LIMIT,
                             render_workers=1, num_workers=0)
    dm.prepare_data()
    assert is_current(tmp_path / "s", train=1, val=1, size=16, seed=0, max_depth=LIMIT)
    assert not is_current(tmp_path / "s", train=1, val=1, size=16, seed=0)


@pytest.mark.parametrize("setting", ["data.init_args.max_depth", "model.net.igd.max_depth"])
@pytest.mark.parametrize("value", ["0", "-50", "1"])
def test_a_depth_limit_of_a_metre_or_less_is_refused_naming_its_setting(setting, value, tmp_path, capsys,
                                                                          monkeypatch):
    """0 m used to pass the data module, then every training step was non-finite and skipped, and fit exited 0."""
    monkeypatch.chdir(tmp_path)
    code, err = run_main(["fit", "--config", str(QUICKSTART), f"--{setting}", value, "--data.init_args.root",
                          str(tmp_path / "never_rendered"), "--trainer.logger", "false"], capsys)
    assert code == 1 and len(err.splitlines()) <= 3, err
    assert f"error: {setting}: {float(value)!r}, but a depth limit must be a number of metres above 1" in err, err
    assert f"Fix: --{setting} 1000, or the limit the data set was written with" in err, err
    assert list(tmp_path.iterdir()) == []  # nothing rendered, no run folder


def test_the_depth_limit_is_checked_where_it_is_set(tmp_path):
    with pytest.raises(ValueError, match=r"model.net.igd.max_depth: 0.5, but"):
        IGDSpec(max_depth=0.5)
    with pytest.raises(ValueError, match=r"data.init_args.max_depth: inf, but"):
        UAPDDataModule(root=str(tmp_path), max_depth=float("inf"))
    assert IGDSpec(max_depth=LIMIT).max_depth == UAPDDataModule(root=str(tmp_path), max_depth=LIMIT).max_depth == LIMIT
    with pytest.raises(SystemExit) as refused:
        main(["synth", "--out", str(tmp_path / "synth"), "--max_depth", "inf"])
    assert refused.value.code == 2 and not (tmp_path / "synth").exists()
