"""Checkpoints are read safely and written atomically, tested as the failures happen to a user: a malicious checkpoint
by address with a trainer plugin set, two addresses ending in the same name, a full checkpoint folder, a SIGKILL
during a save into a folder on another filesystem than $TMPDIR, a damaged last.ckpt, leftovers of killed saves."""

import errno
import functools
import http.server
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import lightning as L
import pytest
import torch
import yaml
from lightning.fabric.plugins.environments import LightningEnvironment
from lightning.fabric.plugins.io.checkpoint_io import CheckpointIO
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.plugins.io.async_plugin import AsyncCheckpointIO

from dapm_lightning.training.checkpoint_files import (
    CheckpointFetchError,
    CheckpointReadError,
    CheckpointSaveError,
    UnsafeCheckpointError,
    UnsafeCheckpointIOError,
    fetch_checkpoint,
    read_checkpoint,
    remove_unfinished_saves,
    save_atomically,
)
from dapm_lightning.training.checkpointing import (
    LastCheckpoint,
    SafeCheckpointIO,
    SafeLoadingCheckpointIO,
    resolve_last_checkpoint,
    safe_checkpoint_io,
)
from dapm_lightning.training.lightning_cli import NoWeightsError, run_lightning_cli
from tests.conftest import QUICKSTART, run_main

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
PLUGIN = "lightning.fabric.plugins.environments.LightningEnvironment"  # any plugin replaces the default list
UAPD = ["--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.batch_size", "2",
        "--data.init_args.num_workers", "0", "--trainer.enable_progress_bar", "false"]
TINY = ["--model.net.backbone", "mobilenetv3_small_050", "--model.net.decoder_channels", "16",
        "--model.net.head_channels", "8", "--model.net.pose_hidden", "32", "--trainer.limit_val_batches", "0"]


class Payload:
    """Pickled into a checkpoint, it runs code when the file is loaded with ``weights_only=False``: a marker file."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return exec, (f"open({self.marker!r}, 'w').write('the payload ran')",)


def malicious(path, marker):
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"state_dict": {"net.w": torch.zeros(2)}, "hyper_parameters": {"net": {}}, "payload": Payload(marker)},
               path)
    return path


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.fixture()
def served(tmp_path):
    """``(folder, address)``: an HTTP server on 127.0.0.1 serving the folder, in a thread."""
    folder = tmp_path / "www"
    folder.mkdir()
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0),
                                             functools.partial(QuietHandler, directory=str(folder)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield folder, f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def mount_tmpfs(folder, size):
    """A tmpfs of ``size`` at ``folder`` (another filesystem than $TMPDIR's); False when mounting is not allowed."""
    folder.mkdir(parents=True, exist_ok=True)
    if shutil.which("mount") is None:
        return False
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], capture_output=True)
    return done.returncode == 0


@pytest.fixture()
def small_folder(tmp_path, monkeypatch):
    """A checkpoint folder with 1 MB of space: a tmpfs when this user may mount one, else a monkeypatched disk
    (``torch.save`` fails with ENOSPC past 1 MB, as a full disk makes it)."""
    folder = tmp_path / "small"
    mounted = mount_tmpfs(folder, "1m")
    if not mounted:
        real = torch.save

        def full_disk(obj, f, *args, **kwargs):
            if isinstance(f, (str, os.PathLike)) or not str(getattr(f, "name", "")).startswith(str(folder)):
                return real(obj, f, *args, **kwargs)
            buffer = __import__("io").BytesIO()
            real(obj, buffer, *args, **kwargs)
            data = buffer.getvalue()
            f.write(data[:1 << 20])
            if len(data) > 1 << 20:
                raise RuntimeError("file write failed") from OSError(errno.ENOSPC, "No space left on device")
            return None

        monkeypatch.setattr(torch, "save", full_disk)
    yield folder
    if mounted:
        subprocess.run(["umount", "-l", str(folder)], check=False)


# --- reading: addresses, plugins, refused pickles -------------------------------------------------------------------


@pytest.mark.parametrize("how", ["command line", "config file"])
def test_a_malicious_checkpoint_by_address_with_a_plugin_set_is_refused_and_never_run(how, served, tiny_uapd,
                                                                                     tmp_path, capsys, monkeypatch):
    folder, address = served
    marker = tmp_path / "PWNED"
    evil = malicious(folder / "EVIL.ckpt", marker)
    torch.load(evil, weights_only=False)  # what unsafe loading does: the payload runs
    assert marker.read_text() == "the payload ran"
    marker.unlink()
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))  # torch hub's cache, keyed by file name
    if how == "command line":
        plugins = ["--trainer.plugins", PLUGIN]
    else:
        (tmp_path / "plugins.yaml").write_text(yaml.safe_dump({"trainer": {"plugins": [{"class_path": PLUGIN}]}}))
        plugins = ["--config", str(tmp_path / "plugins.yaml")]
    code, err = run_main(["validate", "--config", str(QUICKSTART), *plugins, "--ckpt_path", f"{address}/EVIL.ckpt",
                          "--trainer.default_root_dir", str(tmp_path / "run")], capsys)
    assert code == 1 and not marker.exists(), err
    assert f"{address}/EVIL.ckpt (fetched into" in err and "refused" in err and "builtins.exec" in err, err
    assert "nothing in it was run" in err and "\nFix: use a checkpoint written by `dapm-lightning fit`" in err, err
    assert "copy the checkpoint again" not in err  # the advice for a file cut short, not for a refused pickle
    assert not list((tmp_path / "run" / "fetched").iterdir())  # a refused download is not kept
    assert not (tmp_path / "torch_home").exists()

    # past the command line's own check: Lightning's loading of ckpt_path, on the trainer the CLI built
    cli = run_lightning_cli(["--config", str(QUICKSTART), *plugins, *UAPD, "--data.init_args.root", str(tiny_uapd),
                             "--trainer.logger", "false"], run=False)
    assert isinstance(cli.trainer._accelerator_connector.cluster_environment, LightningEnvironment)  # the plugin
    assert isinstance(cli.trainer.strategy.checkpoint_io, SafeCheckpointIO)
    for path in (f"{address}/EVIL.ckpt", str(evil), f"file://{evil}"):
        with pytest.raises(UnsafeCheckpointError, match="nothing in it was run"):
            cli.trainer.validate(cli.model, datamodule=cli.datamodule, ckpt_path=path)
        assert not marker.exists(), path
    assert not (tmp_path / "torch_home").exists()


def test_two_addresses_ending_in_the_same_name_are_two_files_fetched_every_time(served, tmp_path, monkeypatch):
    folder, address = served
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch_home"))
    for name, value in (("a", 1.0), ("b", 2.0)):
        (folder / name).mkdir()
        torch.save({"x": torch.tensor(value)}, folder / name / "model.ckpt")
    first, second = f"{address}/a/model.ckpt", f"{address}/b/model.ckpt"
    assert read_checkpoint(first)["x"] == 1.0 and read_checkpoint(second)["x"] == 2.0
    assert SafeCheckpointIO().load_checkpoint(second)["x"] == 2.0  # Lightning's path: no torch hub cache either
    a, b = fetch_checkpoint(first, tmp_path / "run"), fetch_checkpoint(second, tmp_path / "run")
    assert a != b and a.name.endswith("-model.ckpt") and torch.load(b, weights_only=True)["x"] == 2.0
    torch.save({"x": torch.tensor(3.0)}, folder / "a" / "model.ckpt")  # the same address, new content
    assert torch.load(fetch_checkpoint(first, tmp_path / "run"), weights_only=True)["x"] == 3.0
    assert read_checkpoint(first)["x"] == 3.0
    assert not (tmp_path / "torch_home").exists()
    with pytest.raises(CheckpointFetchError, match=rf"{address}/c/model.ckpt: could not fetch the checkpoint "
                                                   r"\(.*\)\.\nFix:"):
        read_checkpoint(f"{address}/c/model.ckpt")
    with pytest.raises(CheckpointFetchError, match=r"nosuch://x/y.ckpt: cannot read a checkpoint from a nosuch://"):
        read_checkpoint("nosuch://x/y.ckpt")


class SavesItsOwnWay(TorchCheckpointIO):
    """A user's plugin that changes only how checkpoints are written."""

    saved = 0

    def save_checkpoint(self, checkpoint, path, storage_options=None):
        type(self).saved += 1
        super().save_checkpoint(checkpoint, path, storage_options)


class LoadsItsOwnWay(CheckpointIO):
    """A user's plugin that reads checkpoints its own way (here, unsafely)."""

    def save_checkpoint(self, checkpoint, path, storage_options=None):
        torch.save(checkpoint, path)

    def load_checkpoint(self, path, map_location=None, weights_only=None):
        return torch.load(path, weights_only=False)

    def remove_checkpoint(self, path):
        os.remove(path)


def test_every_checkpoint_plugin_is_made_safe_or_refused(tmp_path, capsys, monkeypatch):
    evil = malicious(tmp_path / "evil.ckpt", tmp_path / "PWNED")
    assert isinstance(safe_checkpoint_io(None), SafeCheckpointIO)
    assert isinstance(safe_checkpoint_io(TorchCheckpointIO()), SafeCheckpointIO)
    safe = SafeCheckpointIO()
    assert safe_checkpoint_io(safe) is safe
    wrapped = AsyncCheckpointIO(TorchCheckpointIO())
    assert safe_checkpoint_io(wrapped) is wrapped and isinstance(wrapped.checkpoint_io, SafeCheckpointIO)
    own = safe_checkpoint_io(SavesItsOwnWay())
    assert isinstance(own, SafeLoadingCheckpointIO)
    own.save_checkpoint({"x": torch.ones(1)}, tmp_path / "own.ckpt")
    assert SavesItsOwnWay.saved == 1 and own.load_checkpoint(tmp_path / "own.ckpt")["x"] == 1
    for plugin in (wrapped, own):
        with pytest.raises(UnsafeCheckpointError):
            plugin.load_checkpoint(evil)
    wrapped.teardown()
    with pytest.raises(UnsafeCheckpointIOError, match=r"trainer.plugins: .*LoadsItsOwnWay reads checkpoints its own "
                                                      r"way(.|\n)*Fix: derive it from .*SafeCheckpointIO"):
        safe_checkpoint_io(LoadsItsOwnWay())
    assert not (tmp_path / "PWNED").exists()

    # a trainer built without the CLI: the project's callbacks put the safe I/O on before any checkpoint is read
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(4, 2)), batch_size=2)
    trainer = L.Trainer(max_steps=1, logger=False, enable_progress_bar=False, enable_model_summary=False,
                        plugins=[LightningEnvironment()], callbacks=[LastCheckpoint(dirpath=tmp_path / "run")])
    assert type(trainer.strategy.checkpoint_io) is TorchCheckpointIO
    with pytest.raises(UnsafeCheckpointError):
        trainer.fit(Linear(), loader, ckpt_path=evil)
    assert isinstance(trainer.strategy.checkpoint_io, SafeCheckpointIO) and not (tmp_path / "PWNED").exists()

    monkeypatch.chdir(tmp_path)
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--trainer.plugins",  # refused as the trainer is built
                          f"{__name__}.LoadsItsOwnWay", "--trainer.logger", "false"], capsys)
    assert code == 1 and "LoadsItsOwnWay reads checkpoints its own way" in err and "Fix:" in err, err


class Linear(L.LightningModule):
    def __init__(self, width=1):
        super().__init__()
        self.layer = torch.nn.Linear(2, width)

    def training_step(self, batch, batch_idx):
        return self.layer(batch[0]).square().mean()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


# --- writing: full folders, $TMPDIR, leftovers ----------------------------------------------------------------------


def test_a_full_checkpoint_folder_keeps_the_previous_file_and_names_the_fix(small_folder):
    last = small_folder / "last.ckpt"
    with pytest.raises(CheckpointSaveError) as info:  # a folder too small for one checkpoint: no cut last.ckpt
        SafeCheckpointIO().save_checkpoint({"w": torch.zeros(1_000_000)}, last)
    assert not last.exists() and not list(small_folder.iterdir())
    message = str(info.value)
    assert message.startswith(f"{last}: could not save the checkpoint: no space left in {small_folder} (")
    assert f"\nFix: free space in {small_folder}, or write the run to another disk with --trainer.default_root_dir" \
        in message
    SafeCheckpointIO().save_checkpoint({"w": torch.ones(10_000), "step": 1}, last)
    with pytest.raises(CheckpointSaveError, match=r"no space left in .* MB free.*\). The previous last.ckpt is"):
        SafeCheckpointIO().save_checkpoint({"w": torch.zeros(1_000_000), "step": 2}, last)
    assert read_checkpoint(last)["step"] == 1 and [p.name for p in small_folder.iterdir()] == ["last.ckpt"]


def test_a_full_folder_during_fit_is_one_message_naming_the_file(small_folder, tiny_uapd, tmp_path, capsys,
                                                                monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "job.yaml").write_text(yaml.safe_dump({"trainer": {"logger": False, "callbacks": [
        {"class_path": "dapm_lightning.training.checkpointing.LastCheckpoint",
         "init_args": {"dirpath": str(small_folder), "every_n_train_steps": 1}}]}}))
    code, err = run_main(["fit", "--config", str(QUICKSTART), "--config", str(tmp_path / "job.yaml"), *UAPD, *TINY,
                          "--data.init_args.root", str(tiny_uapd), "--trainer.max_steps", "2"], capsys)
    assert code == 1, err
    assert f"error: {small_folder / 'last.ckpt'}: could not save the checkpoint: no space left in {small_folder}" in err
    assert f"Fix: free space in {small_folder}, or write the run to another disk with --trainer.default_root_dir" in err
    assert not list(small_folder.glob("*.partial-*"))


@pytest.fixture()
def full_tmpdir(tmp_path, monkeypatch):
    """$TMPDIR on a tmpfs too small for a checkpoint (where mounting is not allowed: a $TMPDIR that does not
    exist)."""
    folder = tmp_path / "tmpdir"
    mounted = mount_tmpfs(folder, "64k")
    if not mounted:
        folder = tmp_path / "no_tmpdir"
    monkeypatch.setenv("TMPDIR", str(folder))
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    yield folder
    if mounted:
        subprocess.run(["umount", "-l", str(folder)], check=False)


def test_saves_need_no_tmpdir_and_never_rename_across_folders(full_tmpdir, tmp_path, monkeypatch):
    """$TMPDIR full, and a rename between two folders failing as it does between two filesystems."""
    with pytest.raises(OSError):  # Lightning's own writer goes through $TMPDIR (fsspec's mkstemp)
        TorchCheckpointIO().save_checkpoint({"x": torch.ones(100_000)}, tmp_path / "lightning.ckpt")
    for name in ("rename", "replace"):
        real = getattr(os, name)

        def same_folder_only(src, dst, *args, _real=real, **kwargs):
            if Path(src).resolve().parent != Path(dst).resolve().parent:
                raise OSError(errno.EXDEV, "Invalid cross-device link")
            return _real(src, dst, *args, **kwargs)

        monkeypatch.setattr(os, name, same_folder_only)
    loader = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(8, 2)), batch_size=2)
    trainer = L.Trainer(max_steps=3, logger=False, enable_progress_bar=False, enable_model_summary=False,
                        callbacks=[LastCheckpoint(dirpath=tmp_path / "run", every_n_train_steps=1)])
    trainer.fit(Linear(), loader)
    assert read_checkpoint(tmp_path / "run" / "last.ckpt")["global_step"] == 3
    assert [p.name for p in (tmp_path / "run").iterdir()] == ["last.ckpt"]


def dead_pid():
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_leftovers_of_killed_saves_are_removed_and_named_once(tmp_path):
    host = socket.gethostname()
    run = tmp_path / "run" / "version_0" / "checkpoints"
    run.mkdir(parents=True)
    killed = run / f"last.ckpt.partial-{host}-{dead_pid()}-0badc0de"
    elsewhere = run / "best.ckpt.partial-another-node-12-deadbeef"
    alive = run / f"last.ckpt.partial-{host}-{os.getppid()}-c0ffee00"  # a save still being written
    mine = run / f"last.ckpt.partial-{host}-{os.getpid()}-00000000"  # this process has not started saving
    keep = run / "notes.partial-text"
    for path in (killed, elsewhere, alive, mine, keep):
        path.write_bytes(b"x" * 10)
    with pytest.warns(UserWarning, match="removed 3 unfinished checkpoint file") as record:
        assert sorted(remove_unfinished_saves([tmp_path / "run", tmp_path / "missing"])) == sorted(
            [killed, elsewhere, mine])
    assert len(record) == 1 and all(str(p) in str(record[0].message) for p in (killed, elsewhere, mine))
    assert alive.exists() and keep.exists()
    assert remove_unfinished_saves([tmp_path / "run"]) == []


# --- --ckpt_path last: a damaged last.ckpt ----------------------------------------------------------------------------


def write_at(path, content, second):
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        torch.save(content, path)
    os.utime(path, ns=(time.time_ns(), second * 1_000_000_000))
    return path


def test_ckpt_path_last_skips_a_damaged_last_checkpoint(checkpoint, tiny_uapd, tmp_path, monkeypatch):
    run = tmp_path / "run"
    older = write_at(run / "tensorboard/version_0/checkpoints/last.ckpt", {"global_step": 2}, 10)
    best = write_at(run / "tensorboard/version_1/checkpoints/best-step=3.ckpt", {"global_step": 3}, 20)
    cut = write_at(run / "tensorboard/version_1/checkpoints/last.ckpt", older.read_bytes()[:300], 30)
    with pytest.warns(UserWarning, match=f"--ckpt_path last: skipping {cut}: it cannot be loaded"):
        path, loaded = resolve_last_checkpoint([run])
    assert path == best and loaded["global_step"] == 3  # the newest complete checkpoint
    best.unlink()
    with pytest.warns(UserWarning, match="skipping"):
        assert resolve_last_checkpoint([run])[0] == older
    older.write_bytes(b"")
    with pytest.warns(UserWarning, match="none of the 2 checkpoint"):
        assert resolve_last_checkpoint([run]) is None
    assert resolve_last_checkpoint([tmp_path / "nothing"]) is None

    # through the command line, with a real checkpoint under an older log version
    shutil.copy(checkpoint, older)
    os.utime(older, ns=(time.time_ns(), 10 * 1_000_000_000))
    monkeypatch.chdir(tmp_path)
    with pytest.warns(UserWarning, match=f"skipping {cut}"):
        cli = run_lightning_cli(["validate", "--config", str(QUICKSTART), *UAPD, "--data.init_args.root",
                                 str(tiny_uapd), "--trainer.default_root_dir", str(run), "--trainer.logger", "false",
                                 "--ckpt_path", "last"])
    assert Path(cli.trainer.ckpt_path) == older
    older.write_bytes(older.read_bytes()[:4096])
    last_in = {"class_path": "dapm_lightning.training.checkpointing.LastCheckpoint",  # Lightning looks for last there
               "init_args": {"dirpath": str(cut.parent)}}
    (tmp_path / "job.yaml").write_text(yaml.safe_dump({"trainer": {"callbacks": [last_in]}}))
    # every checkpoint damaged: validate refuses (an untrained network's metrics), not Lightning's reading of the file
    with pytest.warns(UserWarning, match=f"skipping {older}") as warned, \
            pytest.raises(NoWeightsError, match=f"validate --ckpt_path last: looked for the run's newest checkpoint "
                                                f"under {run}, {cut.parent}: none of the checkpoints there can be "
                                                "loaded"):
        run_lightning_cli(["validate", "--config", str(QUICKSTART), "--config", str(tmp_path / "job.yaml"),
                           *UAPD, "--data.init_args.root", str(tiny_uapd), "--trainer.default_root_dir", str(run),
                           "--trainer.logger", "false", "--ckpt_path", "last"])
    assert not any("starting from scratch" in str(w.message) for w in warned)  # fit's wording, not validate's


def test_a_refused_pickle_and_a_damaged_file_get_their_own_messages(tmp_path):
    evil = malicious(tmp_path / "evil.ckpt", tmp_path / "PWNED")
    with pytest.raises(UnsafeCheckpointError) as refused:
        read_checkpoint(evil)
    assert not (tmp_path / "PWNED").exists()
    assert "not a readable checkpoint" not in str(refused.value)
    cut = tmp_path / "cut.ckpt"
    cut.write_bytes(evil.read_bytes()[:100])
    with pytest.raises(CheckpointReadError, match=r"cut.ckpt: not a readable checkpoint \(100 bytes"):
        read_checkpoint(cut)
    with pytest.raises(FileNotFoundError, match="missing.ckpt: no such checkpoint file"):
        read_checkpoint(tmp_path / "missing.ckpt")
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    with pytest.raises(IsADirectoryError, match="run: a folder, not a checkpoint file, and no \\*.ckpt is below it"):
        read_checkpoint(run)
    save_atomically({"x": torch.ones(2)}, run / "checkpoints" / "last.ckpt")
    with pytest.raises(IsADirectoryError, match=r"below it: .*last.ckpt.\nFix: give one of them, e.g. .*last.ckpt"):
        read_checkpoint(run)
    save_atomically({"x": torch.ones(2)}, f"file://{tmp_path / 'url.ckpt'}")
    assert read_checkpoint(f"file://{tmp_path / 'url.ckpt'}")["x"].sum() == 2


# --- in real processes ------------------------------------------------------------------------------------------------


def saves_in_progress(folder):
    return [p for p in folder.glob("last.ckpt.partial-*") if p.stat().st_size > 1_000_000]


@pytest.mark.slow
def test_sigkill_during_a_save_on_another_filesystem_keeps_last_and_the_requeued_job_resumes(tmp_path):
    """The checkpoint folder on a tmpfs, $TMPDIR on the disk (where mounting is not allowed, both on the disk: the
    save never goes through $TMPDIR either way): a SIGKILL from another process while last.ckpt is being rewritten;
    the resubmitted job (`--ckpt_path last`) removes the leftover, names it, and resumes from the previous one."""
    folder = tmp_path / "ckpt"
    mounted = mount_tmpfs(folder, "2g")
    try:
        data = tmp_path / "data"
        from dapm_lightning.data.synthetic import generate_uapd

        generate_uapd(data, train=8, val=2, size=(24, 32), seed=5, workers=1)
        (tmp_path / "job.yaml").write_text(yaml.safe_dump({"trainer": {"logger": False, "callbacks": [
            {"class_path": "dapm_lightning.training.checkpointing.CheckpointOnSigterm"},
            {"class_path": "dapm_lightning.training.checkpointing.LastCheckpoint",
             "init_args": {"dirpath": str(folder), "every_n_train_steps": 1}}]}}))
        (tmp_path / "tmpdir").mkdir()
        env = dict(os.environ, PYTHONPATH=str(REPO), TMPDIR=str(tmp_path / "tmpdir"))
        command = [sys.executable, "-m", "dapm_lightning", "fit", "--config", str(QUICKSTART), "--config",
                   str(tmp_path / "job.yaml"), *UAPD, "--data.init_args.root", str(data),
                   "--trainer.limit_val_batches", "1", "--trainer.val_check_interval", "2",  # validating, as jobs do
                   "--trainer.check_val_every_n_epoch", "null", "--trainer.default_root_dir", str(tmp_path / "run")]
        job = subprocess.Popen([*command, "--trainer.max_steps", "40"], cwd=tmp_path, env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        deadline, complete = time.time() + 240, 0
        while True:  # a save in progress after a complete one: a temporary file growing, or last.ckpt rewritten
            try:
                size = (folder / "last.ckpt").stat().st_size
            except FileNotFoundError:
                size = 0
            if complete and (size < complete or saves_in_progress(folder)):
                break
            complete = max(complete, size)
            assert job.poll() is None, job.stdout.read()[-3000:]
            assert time.time() < deadline, "no save seen in progress"
            time.sleep(0.002)
        job.send_signal(signal.SIGKILL)  # from another process, in the middle of writing the new last.ckpt
        job.communicate(timeout=60)
        left = saves_in_progress(folder)
        assert len(left) == 1
        step = read_checkpoint(folder / "last.ckpt")["global_step"]  # the previous one, complete
        assert step >= 1

        again = subprocess.run([*command, "--trainer.max_steps", str(step + 1), "--ckpt_path", "last"], cwd=tmp_path,
                               env=env, capture_output=True, text=True, timeout=300)
        out = again.stdout + again.stderr
        assert again.returncode == 0, out[-3000:]
        assert f"removed 1 unfinished checkpoint file(s) left by interrupted saves: {left[0]}" in out, out[-3000:]
        assert f"--ckpt_path last: resuming from {folder / 'last.ckpt'}" in out, out[-3000:]
        assert read_checkpoint(folder / "last.ckpt")["global_step"] == step + 1
        assert [p.name for p in folder.iterdir()] == ["last.ckpt"]
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(folder)], check=False)


@pytest.mark.slow
def test_the_reported_command_refuses_a_malicious_address_in_real_processes(tmp_path):
    """`dapm-lightning validate --ckpt_path http://127.0.0.1:PORT/EVIL.ckpt --trainer.plugins ...` with the checkpoint
    served by `python -m http.server`: exit status 1, a message, and the payload never runs."""
    marker = tmp_path / "PWNED"
    malicious(tmp_path / "www" / "EVIL.ckpt", marker)
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = subprocess.Popen([sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1", "--directory",
                               str(tmp_path / "www")], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 30
        while True:
            with socket.socket() as client:
                if client.connect_ex(("127.0.0.1", port)) == 0:
                    break
            assert time.time() < deadline, "the server did not start"
            time.sleep(0.1)
        done = subprocess.run([sys.executable, "-m", "dapm_lightning", "validate", "--config", str(QUICKSTART),
                               "--ckpt_path", f"http://127.0.0.1:{port}/EVIL.ckpt", "--trainer.plugins", PLUGIN],
                              cwd=tmp_path, env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True,
                              text=True, timeout=300)
    finally:
        server.terminate()
        server.wait(timeout=30)
    assert done.returncode == 1 and not marker.exists(), done.stderr[-3000:]
    assert "refused" in done.stderr and "nothing in it was run" in done.stderr and "Traceback" not in done.stderr
