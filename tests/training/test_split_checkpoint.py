"""A checkpoint stored as a folder of parts (a Git host's file limit): read like a file by every loader, and a missing
or damaged part named with the fix, never loaded half."""

import json
import shutil

import lightning as L
import pytest
import torch

from dapm_lightning.data.datamodules import UAPDDataModule
from dapm_lightning.models.config import DAPMConfig
from dapm_lightning.training.checkpoint_files import (
    SPLIT_MANIFEST,
    CheckpointReadError,
    inference_checkpoint,
    read_checkpoint,
    split_checkpoint,
    split_checkpoint_card,
)
from dapm_lightning.training.checkpointing import load_dapm_module
from dapm_lightning.training.lightning_cli import run_lightning_cli
from dapm_lightning.training.module import DAPMModule
from tests.conftest import QUICKSTART

UAPD = ["--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.batch_size", "2",
        "--data.init_args.num_workers", "0", "--trainer.enable_progress_bar", "false", "--trainer.logger", "false"]


@pytest.fixture()
def split(checkpoint, tmp_path):
    """The one-step quickstart checkpoint in parts of 1 MB."""
    folder = tmp_path / "model"
    files = split_checkpoint(checkpoint, folder, part_bytes=1 << 20, card={"image_size": 32, "note": "test"})
    return folder, files


def test_parts_join_to_the_same_checkpoint_and_load_as_a_module(checkpoint, split):
    folder, files = split
    parts, manifest = files[:-1], files[-1]
    assert manifest.name == SPLIT_MANIFEST and len(parts) == -(-checkpoint.stat().st_size // (1 << 20)) > 1
    assert all(p.stat().st_size <= 1 << 20 for p in parts)
    assert b"".join(p.read_bytes() for p in parts) == checkpoint.read_bytes()
    assert split_checkpoint_card(folder) == {"image_size": 32, "note": "test"}
    assert split_checkpoint_card(checkpoint) == {}
    whole, joined = read_checkpoint(checkpoint), read_checkpoint(folder)
    assert whole["global_step"] == joined["global_step"]
    assert all(torch.equal(whole["state_dict"][k], v) for k, v in joined["state_dict"].items())
    module, original = load_dapm_module(folder).eval(), load_dapm_module(checkpoint).eval()
    image = torch.rand(1, 3, 32, 32)
    with torch.no_grad():
        assert torch.equal(module(image).depth_m, original(image).depth_m)


def test_a_missing_or_damaged_part_is_named_with_the_fix(split):
    folder, files = split
    first = files[0]
    data = first.read_bytes()
    first.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))  # one bit flipped
    with pytest.raises(CheckpointReadError, match=f"{first}: damaged") as damaged:
        read_checkpoint(folder)
    assert damaged.value.fix.startswith(f"Fix: restore the folder as it was published (e.g. `git checkout -- {folder}`")
    first.unlink()
    with pytest.raises(FileNotFoundError, match=f"{first}: a part of the split checkpoint {folder} is missing"):
        load_dapm_module(folder)
    (folder / SPLIT_MANIFEST).write_text("{not json")
    with pytest.raises(CheckpointReadError, match="not a split checkpoint manifest"):
        read_checkpoint(folder)


def test_a_manifest_that_lies_about_the_whole_is_refused(split):
    folder, _ = split
    manifest = json.loads((folder / SPLIT_MANIFEST).read_text())
    manifest["sha256"] = "0" * 64
    (folder / SPLIT_MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(CheckpointReadError, match="joined parts do not match"):
        read_checkpoint(folder)


def test_the_cli_tests_a_split_folder(split, tiny_uapd, tmp_path, monkeypatch):
    folder, _ = split
    shutil.copytree(folder, tmp_path / "copy")
    monkeypatch.chdir(tmp_path)
    cli = run_lightning_cli(["test", "--config", str(QUICKSTART), *UAPD, "--data.init_args.root", str(tiny_uapd),
                             "--trainer.default_root_dir", str(tmp_path / "run"), "--ckpt_path", "copy"])
    joined = tmp_path / "run" / "fetched"
    assert [p.name for p in joined.iterdir()][0].startswith("copy-")  # joined once, beside the run
    assert cli.trainer.ckpt_path.startswith(str(joined))
    assert "test_depth_d1" in cli.trainer.callback_metrics


def test_fit_refuses_to_resume_from_weights_only(checkpoint, tiny_uapd, tmp_path, monkeypatch):
    from dapm_lightning.training.checkpoint_files import read_checkpoint as read
    from dapm_lightning.training.lightning_cli import WeightsOnlyCheckpointError

    full = read(checkpoint)
    torch.save({k: full[k] for k in ("state_dict", "hyper_parameters", "epoch", "global_step")},
               tmp_path / "weights.pt")
    split_checkpoint(tmp_path / "weights.pt", tmp_path / "shipped")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(WeightsOnlyCheckpointError, match="^shipped: holds the model's weights only"):
        run_lightning_cli(["fit", "--config", str(QUICKSTART), *UAPD, "--data.init_args.root", str(tiny_uapd),
                           "--trainer.default_root_dir", str(tmp_path / "run"), "--trainer.max_steps", "1",
                           "--ckpt_path", "shipped"])


def _fit_from(init, tiny_uapd, work, *extra):
    """One step at learning rate 0 from ``init``'s weights: the parameters stay those the run started from."""
    return run_lightning_cli(["fit", "--config", str(QUICKSTART), *UAPD, "--data.init_args.root", str(tiny_uapd),
                              "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0",
                              "--trainer.callbacks", "[]", "--trainer.enable_checkpointing", "false",
                              "--trainer.default_root_dir", str(work), "--model.optimizer.lr", "0",
                              "--model.init_weights", str(init), *extra])


@pytest.fixture()
def shipped(checkpoint, tmp_path):
    """The one-step checkpoint as a shipped model: float16 weights in parts (scripts/ship_model.py's form)."""
    whole = tmp_path / "shipped.ckpt"
    torch.save(inference_checkpoint(read_checkpoint(checkpoint)), whole)
    return split_checkpoint(whole, tmp_path / "shipped", part_bytes=1 << 20)[-1].parent


def test_fit_starts_from_a_shipped_models_float16_weights(checkpoint, shipped, tiny_uapd, tmp_path):
    cli = _fit_from(shipped, tiny_uapd, tmp_path / "run")
    saved = read_checkpoint(checkpoint)["state_dict"]
    parameters = dict(cli.model.named_parameters())
    assert parameters and all(p.dtype == torch.float32 for p in parameters.values())
    assert all(torch.equal(p.detach(), saved[name].half().float()) for name, p in parameters.items())
    assert cli.trainer.global_step == 1  # a fresh start: step, optimizer and schedule are this run's
    # the checkpoints it writes load without the file it started from, and never read it again
    tuned = tmp_path / "tuned.ckpt"
    cli.trainer.save_checkpoint(tuned)
    assert read_checkpoint(tuned)["hyper_parameters"]["init_weights"] == str(shipped)
    assert "init_weights" not in read_checkpoint(shipped)["hyper_parameters"]
    shutil.rmtree(shipped)
    assert load_dapm_module(tuned).init_weights is None
    again = DAPMModule.load_from_checkpoint(tuned, weights_only=True)  # init_weights set, its file gone
    assert again.init_weights == str(shipped) and again.weights_are_final
    trainer = L.Trainer(max_steps=1, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                        limit_val_batches=0)
    trainer.fit(again, datamodule=UAPDDataModule(root=tiny_uapd, batch_size=2, num_workers=0))
    assert trainer.global_step == 1


def test_init_weights_build_the_backbone_without_imagenet_weights():
    module = DAPMModule(net=DAPMConfig(backbone="resnet18", pretrained=True), init_weights="any.ckpt")
    assert module.net_config.pretrained is False and module.hparams["net"]["pretrained"] is False


def test_init_weights_of_another_network_list_the_differences(checkpoint, tiny_uapd, tmp_path):
    with pytest.raises(ValueError, match=r"model.init_weights.*\n  model.net.decoder_channels: checkpoint 64"):
        _fit_from(checkpoint, tiny_uapd, tmp_path / "run", "--model.net.decoder_channels", "32")


def test_a_resumed_run_does_not_read_init_weights(checkpoint, tiny_uapd, tmp_path):
    """Its checkpoint names the file it started from, which may be gone by the resume."""
    run, init = tmp_path / "run", tmp_path / "init.ckpt"
    shutil.copy(checkpoint, init)
    first = _fit_from(init, tiny_uapd, run)
    last = tmp_path / "last.ckpt"
    first.trainer.save_checkpoint(last)
    init.unlink()
    resumed = _fit_from(init, tiny_uapd, run, "--trainer.max_steps", "2", "--ckpt_path", str(last))
    assert resumed.trainer.global_step == 2


def test_a_weight_beyond_float16_is_refused_not_shipped_as_inf():
    """Before, it was converted to inf and the shipped model was then refused as one of a diverged training."""
    state = {"net.a": torch.tensor([1.0, 7e4]), "net.b": torch.ones(2), "net.steps": torch.tensor(3)}
    with pytest.raises(ValueError, match=r"1 weight tensor\(s\) hold values beyond torch.float16's range \('net.a'\)"):
        inference_checkpoint({"state_dict": state})
    assert inference_checkpoint({"state_dict": state}, torch.float32)["state_dict"]["net.a"][1] == 7e4
