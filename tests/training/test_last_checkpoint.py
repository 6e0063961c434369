"""last.ckpt is always the latest training state (saved on SIGTERM and Ctrl-C too), and `--ckpt_path last` finds it
in an earlier log version."""

import os
import signal
import time
from pathlib import Path

import lightning as L
import pytest
import torch
import yaml

from dapm_lightning.tools.errors import run_reporting_errors
from dapm_lightning.training.checkpointing import (
    EXIT_SIGINT,
    CheckpointOnSigterm,
    LastCheckpoint,
    find_last_checkpoint,
)
from dapm_lightning.training.lightning_cli import run_lightning_cli
from tests.conftest import QUICKSTART


class Linear(L.LightningModule):
    def __init__(self):
        super().__init__()
        self.layer = torch.nn.Linear(2, 1)

    def training_step(self, batch, batch_idx):
        return self.layer(batch[0]).square().mean()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


class TermedAt(Linear):
    """Marks SIGTERM as received at a training or validation step (what Lightning's signal handler does)."""

    def __init__(self, train_step=None):
        super().__init__()
        self.train_step = train_step

    def training_step(self, batch, batch_idx):
        if self.global_step == self.train_step:
            self.trainer._signal_connector.received_sigterm = True
        return super().training_step(batch, batch_idx)

    def validation_step(self, batch, batch_idx):
        self.trainer._signal_connector.received_sigterm = True


def test_sigterm_saves_last_in_training_only_and_exits_143(tmp_path):
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(12, 2)), batch_size=2)
    kwargs = dict(logger=False, enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)
    trainer = L.Trainer(max_steps=5, callbacks=[CheckpointOnSigterm(), LastCheckpoint(dirpath=tmp_path / "fit")],
                        **kwargs)
    with pytest.raises(SystemExit) as info:
        trainer.fit(TermedAt(train_step=2), loader)
    assert info.value.code == 143  # Lightning's own exit status would be 0, as for a finished run
    assert torch.load(tmp_path / "fit" / "last.ckpt", weights_only=True)["global_step"] == 3
    trainer = L.Trainer(callbacks=[CheckpointOnSigterm(), LastCheckpoint(dirpath=tmp_path / "val")], **kwargs)
    with pytest.raises(SystemExit) as info:
        trainer.validate(TermedAt(), loader)
    assert info.value.code == 143 and not (tmp_path / "val").exists()  # no training state to save


def test_the_project_s_saves_say_they_keep_the_full_state(tmp_path, monkeypatch):
    """Lightning logs "`weights_only` was not set, defaulting to `False`" at every save that does not say: the last
    step's save between two intervals and the SIGTERM save said nothing, and printed it at each."""
    from lightning.pytorch.trainer.connectors import checkpoint_connector

    logged: list[str] = []
    monkeypatch.setattr(checkpoint_connector.log, "info", lambda message, *args, **kwargs: logged.append(message))
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(12, 2)), batch_size=2)
    kwargs = dict(logger=False, enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)
    last = LastCheckpoint(dirpath=tmp_path / "fit", every_n_train_steps=2)
    L.Trainer(max_steps=3, callbacks=[last], **kwargs).fit(Linear(), loader)
    assert torch.load(tmp_path / "fit" / "last.ckpt", weights_only=True)["global_step"] == 3
    trainer = L.Trainer(max_steps=5, callbacks=[CheckpointOnSigterm(), LastCheckpoint(dirpath=tmp_path / "term")],
                        **kwargs)
    with pytest.raises(SystemExit):
        trainer.fit(TermedAt(train_step=2), loader)
    assert (tmp_path / "term" / "last.ckpt").is_file()
    assert not [message for message in logged if "weights_only" in message]


class InterruptedAt(Linear):
    """Presses Ctrl-C (SIGINT to its own process) ``times`` times at a training step, or when fit starts."""

    def __init__(self, train_step=None, times=1):
        super().__init__()
        self.train_step, self.times = train_step, times

    def ctrl_c(self):
        for _ in range(self.times):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.05)  # Python runs the handler between two bytecodes of the main thread

    def on_fit_start(self):
        if self.train_step is None:
            self.ctrl_c()

    def training_step(self, batch, batch_idx):
        if self.global_step == self.train_step:
            self.ctrl_c()
        return super().training_step(batch, batch_idx)


def test_ctrl_c_saves_last_like_sigterm_and_exits_130(tmp_path):
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(12, 2)), batch_size=2)
    kwargs = dict(logger=False, enable_progress_bar=False, enable_model_summary=False, default_root_dir=tmp_path)
    before = signal.getsignal(signal.SIGINT)
    try:
        trainer = L.Trainer(max_steps=5, callbacks=[CheckpointOnSigterm(), LastCheckpoint(dirpath=tmp_path / "once")],
                            **kwargs)
        with pytest.raises(SystemExit) as info:
            trainer.fit(InterruptedAt(train_step=2), loader)
        assert info.value.code == EXIT_SIGINT == 130  # Lightning alone: 1, and no last.ckpt
        assert torch.load(tmp_path / "once" / "last.ckpt", weights_only=True)["global_step"] == 3  # the batch ended
        assert signal.getsignal(signal.SIGINT) is before  # handed back after fit

        for name, model in (("twice", InterruptedAt(train_step=2, times=2)), ("setup", InterruptedAt())):
            trainer = L.Trainer(max_steps=5, callbacks=[CheckpointOnSigterm(), LastCheckpoint(
                dirpath=tmp_path / name, every_n_train_steps=100)], **kwargs)
            with pytest.raises(SystemExit) as info:  # at once, without saving; 130 from the command line too
                run_reporting_errors(lambda: trainer.fit(model, loader), debug=False)  # noqa: B023
            assert info.value.code == 130 and not (tmp_path / name).exists(), name
    finally:
        signal.signal(signal.SIGINT, before)  # Lightning ignores SIGINT after a KeyboardInterrupt


def test_the_final_step_is_saved_between_two_periodic_saves(tmp_path):
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(12, 2)), batch_size=2)
    trainer = L.Trainer(max_steps=5, logger=False, enable_progress_bar=False, enable_model_summary=False,
                        callbacks=[LastCheckpoint(dirpath=tmp_path, every_n_train_steps=4)])
    trainer.fit(Linear(), loader)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]  # overwritten, never last-v1.ckpt
    assert torch.load(tmp_path / "last.ckpt", weights_only=True)["global_step"] == 5


def test_find_last_checkpoint_takes_the_newest_of_every_version(tmp_path):
    assert find_last_checkpoint([tmp_path, tmp_path / "missing"]) is None
    for i, name in enumerate(["tb/version_0/checkpoints/last.ckpt", "tb/version_1/checkpoints/last-v1.ckpt",
                              "tb/version_1/checkpoints/best-step=3.ckpt", "tb/version_1/checkpoints/last_good.ckpt"]):
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"x")
        os.utime(path, ns=(time.time_ns(), 1_000_000_000 * (i + 1)))
    assert find_last_checkpoint([tmp_path]) == tmp_path / "tb/version_1/checkpoints/last-v1.ckpt"


def test_quickstart_resumes_from_the_latest_state_when_validation_stopped_improving(tmp_path, monkeypatch):
    """The best model stays at epoch 0 (its metric, the step, is minimal there); last.ckpt follows every epoch,
    and `fit --ckpt_path last` continues from it although the resumed run logs into a new version folder, keeping
    epoch 0's model as the best (the resumed run used to save its first validation's model as the best)."""
    monkeypatch.chdir(tmp_path)
    config = yaml.safe_load(QUICKSTART.read_text())
    best = next(c for c in config["trainer"]["callbacks"] if c["class_path"].endswith(".ModelCheckpoint"))
    best["init_args"].update(monitor="step", mode="min")
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    common = ["--config", str(tmp_path / "run.yaml"), "--data.init_args.root", str(tmp_path / "data"),
              "--data.init_args.train_size", "4", "--data.init_args.val_size", "2",
              "--data.init_args.image_size", "32", "--data.init_args.render_workers", "1",
              "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
              "--trainer.enable_progress_bar", "false"]
    first = run_lightning_cli(["fit", *common, "--trainer.max_epochs", "3"])
    assert torch.load(first.trainer.checkpoint_callback.best_model_path, weights_only=True)["global_step"] == 2
    last = find_last_checkpoint([tmp_path / "outputs"])
    assert torch.load(last, weights_only=True)["global_step"] == 6
    resumed = run_lightning_cli(["fit", *common, "--trainer.max_epochs", "4", "--ckpt_path", "last"])
    assert Path(resumed.trainer.ckpt_path).resolve() == last.resolve() and resumed.trainer.global_step == 8
    assert resumed.trainer.log_dir != first.trainer.log_dir
    # the best model is still epoch 0's: the resumed run knows its score, though it writes into another folder
    best_path = resumed.trainer.checkpoint_callback.best_model_path
    assert torch.load(best_path, weights_only=True)["global_step"] == 2, best_path
    assert float(resumed.trainer.checkpoint_callback.best_model_score) == 2.0


class Validated(Linear):
    """Logs ``val_loss`` = 10 / (validation number) and records the step of every validation."""

    def __init__(self):
        super().__init__()
        self.validated_at = []

    def validation_step(self, batch, batch_idx):
        self.log("val_loss", 10.0 / (len(self.validated_at) + 1))

    def on_validation_end(self):
        self.validated_at.append(self.global_step)


def test_a_step_save_that_a_validation_follows_holds_that_validation(tmp_path):
    """last.ckpt at step 2, where a validation runs: written after it (and after the best-model checkpoint, although
    listed first), so it holds that validation's best score, and the resumed run neither repeats nor skips it."""
    data = torch.utils.data.TensorDataset(torch.randn(8, 2))
    loader = torch.utils.data.DataLoader(data, batch_size=2)

    def fit(max_steps, ckpt_path=None):
        model = Validated()
        callbacks = [LastCheckpoint(dirpath=tmp_path, every_n_train_steps=1),
                     L.pytorch.callbacks.ModelCheckpoint(dirpath=tmp_path, monitor="val_loss", filename="best")]
        trainer = L.Trainer(max_steps=max_steps, val_check_interval=2, check_val_every_n_epoch=None, logger=False,
                            enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0,
                            callbacks=callbacks)
        trainer.fit(model, loader, loader, ckpt_path=ckpt_path)
        return model

    assert fit(2).validated_at == [2]
    saved = torch.load(tmp_path / "last.ckpt", weights_only=True)
    assert saved["global_step"] == 2
    best = next(state for name, state in saved["callbacks"].items() if name.startswith("ModelCheckpoint"))
    assert float(best["best_model_score"]) == 10.0  # the validation of step 2, run before the save
    assert fit(6, ckpt_path=str(tmp_path / "last.ckpt")).validated_at == [4, 6]  # step 2 not repeated


def test_only_this_runs_rankings_are_kept(tmp_path):
    """A ranking saved in this run's folders, whose best model is still there, moves to the new version folder; one
    of another run (fine-tuning from it), one whose best file is gone, and a remote one start afresh."""
    from types import SimpleNamespace

    from dapm_lightning.training.resume import keep_checkpoint_rankings

    run, other = tmp_path / "outputs" / "run", tmp_path / "elsewhere"
    for folder in (run / "version_0" / "checkpoints", other / "checkpoints"):
        folder.mkdir(parents=True)
        (folder / "best.ckpt").write_bytes(b"x")
    new = str(run / "version_1" / "checkpoints")

    def state(folder, best="best.ckpt"):
        return {"dirpath": str(folder), "best_model_path": str(Path(folder) / best), "best_model_score": 1.0}

    checkpoint = {"callbacks": {"own": state(run / "version_0" / "checkpoints"),
                                "foreign": state(other / "checkpoints"),
                                "gone": state(run / "version_0" / "checkpoints", "deleted.ckpt"),
                                "remote": {**state(run / "version_0" / "checkpoints"), "dirpath": "s3://b/run"}}}
    callbacks = [SimpleNamespace(state_key=key, dirpath=new) for key in checkpoint["callbacks"]]
    assert keep_checkpoint_rankings(checkpoint, callbacks, [str(run)]) == ["own"]
    assert checkpoint["callbacks"]["own"]["dirpath"] == new
    assert checkpoint["callbacks"]["foreign"]["dirpath"] == str(other / "checkpoints")


def test_the_fit_summary_names_best_checkpoints_before_last_whatever_the_callback_order(tmp_path):
    """best_or_last_checkpoint (what `make demo` tests) and the closing lines of `fit` prefer a best checkpoint."""
    from types import SimpleNamespace

    from lightning.pytorch.callbacks import ModelCheckpoint

    from dapm_lightning.training.checkpointing import best_or_last_checkpoint, fit_checkpoints_summary

    last_file, best_file = tmp_path / "last.ckpt", tmp_path / "best.ckpt"
    last_file.write_bytes(b"x")
    last = LastCheckpoint(dirpath=tmp_path)
    last.best_model_path = str(last_file)
    best = ModelCheckpoint(dirpath=tmp_path, monitor="val_loss")
    best.best_model_path, best.best_model_score = str(best_file), torch.tensor(0.25)
    last._last_global_step_saved = 7  # its last save; the fit went on to step 9 (a user's save_last=True)
    trainer = SimpleNamespace(checkpoint_callbacks=[last, best], global_step=9)
    assert fit_checkpoints_summary(trainer) == [("last checkpoint (step 7)", str(last_file))]  # no best file yet
    assert best_or_last_checkpoint(trainer) == str(last_file)
    best_file.write_bytes(b"x")
    assert fit_checkpoints_summary(trainer) == [("best checkpoint (val_loss 0.25)", str(best_file)),
                                                ("last checkpoint (step 7)", str(last_file))]
    assert best_or_last_checkpoint(trainer) == str(best_file)
    assert best_or_last_checkpoint(SimpleNamespace(checkpoint_callbacks=[], global_step=0)) == ""
