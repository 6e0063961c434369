"""Fixtures of the training tests: a tiny trained checkpoint."""

from pathlib import Path

import pytest

from dapm_lightning.lightning_cli import run_lightning_cli

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.fixture(scope="session")
def checkpoint(tiny_uapd, tmp_path_factory):
    work = tmp_path_factory.mktemp("predict_ckpt")
    cli = run_lightning_cli(["fit", "--config", str(CONFIGS / "quickstart.yaml"), "--data.class_path",
                             "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(tiny_uapd),
                             "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
                             "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0",
                             "--trainer.logger", "false", "--trainer.callbacks", "[]",
                             "--trainer.enable_checkpointing", "false", "--trainer.default_root_dir", str(work)])
    path = work / "model.ckpt"
    cli.trainer.save_checkpoint(path)
    return path


