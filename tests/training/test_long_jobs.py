"""Long jobs: resume after SIGKILL / SIGTERM / SIGINT, checkpoints, non-finite losses, bad data, determinism."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import yaml

from dapm_lightning.data import DatasetError, UAPDDataset
from dapm_lightning.data.synthetic import generate_uapd
from dapm_lightning.training.checkpointing import EXIT_SIGINT, EXIT_SIGTERM, SafeCheckpointIO
from dapm_lightning.training.lightning_cli import run_lightning_cli

HERE = Path(__file__).resolve().parent
QUICKSTART = HERE.parents[1] / "dapm_lightning" / "configs" / "quickstart.yaml"
TINY = ["--model.net.backbone", "mobilenetv3_small_050", "--model.net.decoder_channels", "16",
        "--model.net.head_channels", "8",
        "--model.net.pose_hidden", "32", "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
        "--trainer.limit_val_batches", "0", "--trainer.deterministic", "true", "--trainer.max_steps", "8",
        "--trainer.enable_progress_bar", "false",
        # telemetry priors drawn in every step: their draws must resume exactly too (one and two processes)
        "--model.prior_training.enabled", "true", "--model.prior_training.image_fraction", "0.75"]


@pytest.fixture(scope="module")
def data8(tmp_path_factory):
    return generate_uapd(tmp_path_factory.mktemp("rel") / "d", train=8, val=2, size=(24, 32), seed=5, workers=1)


def job_config(tmp_path, name):
    """Callbacks of a resumable job: save on SIGTERM, a checkpoint every step (last.ckpt)."""
    path = tmp_path / f"{name}.yaml"
    path.write_text(yaml.safe_dump({"trainer": {"logger": False, "callbacks": [
        {"class_path": "dapm_lightning.training.checkpointing.CheckpointOnSigterm"},
        {"class_path": "dapm_lightning.training.checkpointing.LastCheckpoint",
         "init_args": {"dirpath": str(tmp_path / name), "every_n_train_steps": 1}}]}}))
    return ["--config", str(QUICKSTART), "--config", str(path)]


def start(tmp_path, name, data, extra=(), pause=None):
    env = dict(os.environ, PAUSE_AT=f"{pause},{tmp_path / (name + '.marker')}" if pause else "",
               RECORD_IMAGES=str(tmp_path / f"{name}_images_rank"))
    cmd = [sys.executable, str(HERE / "resume_run.py"), str(tmp_path / f"{name}.pt"), *job_config(tmp_path, name),
           "--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(data),
           *TINY, *extra]
    return subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def finish(process, timeout=240):
    out, _ = process.communicate(timeout=timeout)
    return process.returncode, out


def wait_for(path, process, timeout=180):
    deadline = time.time() + timeout
    while not path.exists():
        if process.poll() is not None:
            pytest.fail(f"run ended before the marker:\n{process.stdout.read()[-3000:]}")
        assert time.time() < deadline, "marker never appeared"
        time.sleep(0.1)


def weights(path):
    return torch.load(path, weights_only=True)


@pytest.mark.slow
def test_killed_and_terminated_runs_resume_to_the_uninterrupted_weights(data8, tmp_path):
    code, out = finish(start(tmp_path, "straight", data8))
    assert code == 0, out[-3000:]
    reference = weights(tmp_path / "straight.pt")
    assert reference["global_step"] == 8

    killed = start(tmp_path, "killed", data8, pause=3)  # mid-epoch 0 (4 batches per epoch)
    wait_for(tmp_path / "killed.marker", killed)
    killed.send_signal(signal.SIGKILL)
    finish(killed)
    assert (tmp_path / "killed" / "last.ckpt").is_file()  # never half-written: the last complete step's

    terminated = start(tmp_path, "termed", data8, pause=5)  # mid-epoch 1
    wait_for(tmp_path / "termed.marker", terminated)
    terminated.send_signal(signal.SIGTERM)
    code, out = finish(terminated)
    assert "Received SIGTERM" in out and (tmp_path / "termed" / "last.ckpt").is_file(), out[-2000:]
    assert code == EXIT_SIGTERM == 143, out[-2000:]  # pre-empted, not finished: a job script can requeue
    saved = torch.load(tmp_path / "termed" / "last.ckpt", weights_only=True)
    assert saved["global_step"] == 5

    interrupted = start(tmp_path, "ctrl_c", data8, pause=6)  # Ctrl-C: saved like SIGTERM, status 130
    wait_for(tmp_path / "ctrl_c.marker", interrupted)
    interrupted.send_signal(signal.SIGINT)
    code, out = finish(interrupted)
    assert code == EXIT_SIGINT == 130 and "Received SIGINT (Ctrl-C)" in out, out[-2000:]
    assert torch.load(tmp_path / "ctrl_c" / "last.ckpt", weights_only=True)["global_step"] == 6

    for name in ("killed", "termed", "ctrl_c"):
        code, out = finish(start(tmp_path, name, data8, extra=["--ckpt_path", str(tmp_path / name / "last.ckpt")]))
        assert code == 0, out[-3000:]
        resumed = weights(tmp_path / f"{name}.pt")
        assert resumed["global_step"] == 8
        for key, value in reference["state_dict"].items():
            assert torch.equal(value, resumed["state_dict"][key]), f"{name}: {key} differs"


def test_two_seeded_runs_are_bit_identical(data8, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    states = []
    for _ in range(2):
        cli = run_lightning_cli(["fit", "--config", str(QUICKSTART), "--data.class_path",
                                 "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(data8),
                                 *TINY, "--trainer.max_steps", "3", "--trainer.logger", "false",
                                 "--trainer.callbacks", "[]", "--trainer.enable_checkpointing", "false"])
        states.append({k: v.clone() for k, v in cli.model.state_dict().items()})
    assert all(torch.equal(states[0][k], states[1][k]) for k in states[0])


def test_truncated_and_foreign_checkpoints_are_clear(checkpoint, tmp_path, tiny_uapd, monkeypatch):
    truncated = tmp_path / "truncated.ckpt"
    truncated.write_bytes(checkpoint.read_bytes()[:5000])
    with pytest.raises(RuntimeError, match="truncated.ckpt: not a readable checkpoint"):
        SafeCheckpointIO().load_checkpoint(truncated)
    evil = tmp_path / "evil.ckpt"
    torch.save({"state_dict": {}, "payload": Path("x")}, evil)  # an arbitrary pickled object
    with pytest.raises(RuntimeError, match="weights_only"):
        SafeCheckpointIO().load_checkpoint(evil)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(RuntimeError, match="truncated.ckpt: not a readable checkpoint"):
        run_lightning_cli(["validate", "--config", str(QUICKSTART), "--ckpt_path", str(truncated)])
    expected = r"model.net.depth_bins: checkpoint \(2, 16, 64\), this run \(2, 16, 16\)(.|\n)*Fix:"
    with pytest.raises(ValueError, match=expected):
        run_lightning_cli(["fit", "--config", str(QUICKSTART), "--data.class_path",
                           "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(tiny_uapd),
                           "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
                           "--model.net.depth_bins", "[2, 16, 16]", "--trainer.max_steps", "1",
                           "--ckpt_path", str(checkpoint)])


def test_nonfinite_loss_skips_the_step(tiny_uapd, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cli = run_lightning_cli(["--config", str(QUICKSTART), "--data.class_path",
                             "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(tiny_uapd),
                             *TINY, "--trainer.max_steps", "1", "--trainer.logger", "false",
                             "--trainer.callbacks", "[]", "--trainer.enable_checkpointing", "false"], run=False)
    model = cli.model
    before = {k: v.clone() for k, v in model.state_dict().items()}
    real = model.criterion.forward
    monkeypatch.setattr(model.criterion, "forward",
                        lambda out, t: {**real(out, t), "total": torch.tensor(float("nan"), requires_grad=True)})
    with pytest.warns(UserWarning, match="non-finite training loss"):
        cli.trainer.fit(model, datamodule=cli.datamodule)
    assert model.nonfinite_steps >= 1
    for key, value in model.state_dict().items():
        if "running" not in key and "num_batches" not in key:  # batch-norm statistics move in any forward
            assert torch.equal(value, before[key]), key


def test_bad_files_at_scale_are_all_listed_and_skippable(tmp_path, monkeypatch):
    root = generate_uapd(tmp_path / "big", train=1000, val=2, size=(8, 12), seed=1)
    rgb, depth = root / "train" / "rgb", root / "train" / "depth"
    names = sorted(p.name for p in rgb.iterdir())
    (rgb / names[10]).write_bytes((rgb / names[10]).read_bytes()[:40])                     # truncated
    (depth / names[20]).unlink()                                                            # missing twin
    for sub in (rgb, depth):
        (sub / names[30]).rename(sub / "no_pose_here.png")                                  # unparsable name
    cv2.imwrite(str(rgb / names[40]), np.zeros((9, 12, 3), np.uint8))                       # wrong size
    cv2.imwrite(str(depth / names[50]), np.zeros((8, 12), np.uint16))                       # 16-bit depth
    with pytest.raises(DatasetError) as info:
        UAPDDataset(root, "train")
    problems = info.value.problems
    assert len(problems) == 5
    for needle in (names[10], names[20], "no_pose_here.png", names[40], names[50]):
        assert any(needle in p for p in problems), needle
    with pytest.warns(UserWarning, match="skipping 5 bad file"):
        skipped = UAPDDataset(root, "train", on_bad_file="skip")
    assert len(skipped) == 995 and len(skipped.skipped) == 5
    monkeypatch.chdir(tmp_path)
    cli = run_lightning_cli(["fit", "--config", str(QUICKSTART), "--data.class_path",
                             "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(root),
                             "--data.init_args.on_bad_file", "skip", *TINY, "--trainer.fast_dev_run", "2"])
    assert cli.trainer.global_step == 2


DDP = ["--trainer.accelerator", "cpu", "--trainer.devices", "2", "--trainer.strategy", "ddp",
       "--data.init_args.num_workers", "1", "--data.init_args.persistent_workers", "true",
       "--model.optimizer.schedule_steps", "10", "--trainer.max_steps", "10"]


@pytest.fixture(scope="module")
def data16(tmp_path_factory):
    return generate_uapd(tmp_path_factory.mktemp("rel16") / "d", train=16, val=2, size=(24, 32), seed=6, workers=1)


@pytest.mark.slow
def test_two_process_ddp_resumes_mid_epoch_exactly(data16, tmp_path):
    """2 processes, persistent workers, 4 steps per epoch: stopped by max_steps (step 6) and by SIGTERM (step 3),
    each resumed from last.ckpt to step 10, equal the uninterrupted run bit for bit; Ctrl-C (step 3) saves too."""
    code, out = finish(start(tmp_path, "straight", data16, extra=DDP), timeout=400)
    assert code == 0, out[-3000:]
    reference = weights(tmp_path / "straight.pt")
    assert reference["global_step"] == 10
    seen = {"0": {}, "1": {}}  # persistent workers under DDP: every image augmented anew in every epoch
    for rank in (0, 1):
        for epoch, images in json.loads((tmp_path / f"straight_images_rank{rank}.json").read_text()).items():
            seen.setdefault(epoch, {}).update(images)
    assert len(seen["0"]) == len(seen["1"]) == 16
    renewed = sum(seen["0"][name] != seen["1"][name] for name in seen["0"])
    assert renewed >= 12, f"{16 - renewed} of 16 images augmented identically in epochs 0 and 1"  # frozen: 0

    code, out = finish(start(tmp_path, "stopped", data16, extra=[*DDP, "--trainer.max_steps", "6"]), timeout=400)
    assert code == 0, out[-3000:]
    assert torch.load(tmp_path / "stopped" / "last.ckpt", weights_only=True)["global_step"] == 6

    terminated = start(tmp_path, "termed", data16, extra=DDP, pause=3)
    wait_for(tmp_path / "termed.marker", terminated)
    terminated.send_signal(signal.SIGTERM)
    code, out = finish(terminated, timeout=400)
    saved = torch.load(tmp_path / "termed" / "last.ckpt", weights_only=True)
    assert saved["global_step"] == 3, out[-3000:]
    assert code == EXIT_SIGTERM, out[-3000:]
    position = next(v for k, v in saved.items() if k.endswith("DataModule"))
    assert position == {"epoch": 0, "samples_seen": 3 * 2 * 2}  # global: 3 batches of 2 on each of 2 processes

    interrupted = start(tmp_path, "ctrl_c", data16, extra=DDP, pause=3)  # Ctrl-C to the main process: passed on
    wait_for(tmp_path / "ctrl_c.marker", interrupted)
    interrupted.send_signal(signal.SIGINT)
    code, out = finish(interrupted, timeout=400)
    assert code == EXIT_SIGINT, out[-3000:]
    assert torch.load(tmp_path / "ctrl_c" / "last.ckpt", weights_only=True)["global_step"] == 3, out[-3000:]

    for name in ("stopped", "termed"):
        code, out = finish(start(tmp_path, name, data16,
                                 extra=[*DDP, "--ckpt_path", str(tmp_path / name / "last.ckpt")]), timeout=400)
        assert code == 0, out[-3000:]
        resumed = weights(tmp_path / f"{name}.pt")
        assert resumed["global_step"] == 10
        for key, value in reference["state_dict"].items():
            assert torch.equal(value, resumed["state_dict"][key]), f"{name}: {key} differs"
