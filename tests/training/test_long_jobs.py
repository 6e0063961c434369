"""Long jobs: resume after SIGKILL / SIGTERM / SIGINT, checkpoints, non-finite losses, bad data, determinism."""

import json
import os
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import cv2
import lightning as L
import numpy as np
import pytest
import torch
import yaml
from lightning.pytorch.loops.progress import _BatchProgress

from dapm_lightning.data import DatasetError, UAPDDataset
from dapm_lightning.data.synthetic import generate_uapd
from dapm_lightning.training.checkpointing import EXIT_SIGINT, EXIT_SIGTERM, SafeCheckpointIO
from dapm_lightning.training.lightning_cli import run_lightning_cli
from dapm_lightning.training.resume import count_batches_as_resumed, resume_after_last_batch

HERE = Path(__file__).resolve().parent
QUICKSTART = HERE.parents[1] / "dapm_lightning" / "configs" / "quickstart.yaml"
TINY = ["--model.net.backbone", "mobilenetv3_small_050", "--model.net.decoder_channels", "16",
        "--model.net.head_channels", "8",
        "--model.net.pose_hidden", "32", "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
        "--trainer.limit_val_batches", "0", "--trainer.deterministic", "true", "--trainer.max_steps", "8",
        "--trainer.enable_progress_bar", "false",
        # telemetry priors drawn in every step and told to both branches: their draws must resume exactly too
        # (one and two processes)
        "--model.prior_training.enabled", "true", "--model.prior_training.image_fraction", "0.75",
        "--model.net.pose_prior_input", "true", "--model.net.depth_prior_input", "true",
        "--model.net.pose_pool_grid", "2"]  # the pose branch pooled to cells


@pytest.fixture(scope="module")
def data8(tmp_path_factory):
    return generate_uapd(tmp_path_factory.mktemp("rel") / "d", train=8, val=2, size=(24, 32), seed=5, workers=1)


VALIDATE = ["--trainer.limit_val_batches", "1.0", "--trainer.val_check_interval", "2",
            "--data.init_args.eval_batch_size", "1"]
"""Every resume test validates (every 2 steps; one image a batch, so that a SIGTERM can stop a validation midway):
a resumed run must train as the uninterrupted one, which validated in between."""
SCHEDULE = ["--model.optimizer.schedule_steps", "8"]  # no step depends on where a job stopped (docs/long_jobs.md)


def job_config(tmp_path, name, every_step=True, best=False):
    """Callbacks of a resumable job: save on SIGTERM, last.ckpt every step (or as the configs: at every validation
    and when training ends); ``best``: best-model checkpoints by val_loss too, all kept, one written at each
    validation (``best-step=N.ckpt``), one as the configs' (``epoch-step=N.ckpt``: at each epoch's end when the
    validation is there)."""
    path = tmp_path / f"{name}.yaml"
    last = {"dirpath": str(tmp_path / name), **({"every_n_train_steps": 1} if every_step else {})}
    ranked = [{"class_path": "lightning.pytorch.callbacks.ModelCheckpoint", "init_args": {
        "dirpath": str(tmp_path / name), "monitor": "val_loss", "save_top_k": -1, "filename": f"{kind}-{{step}}",
        **({"save_on_train_epoch_end": False} if kind == "best" else {"mode": "max"})}}  # max: another state key
        for kind in ("best", "epoch")]
    path.write_text(yaml.safe_dump({"trainer": {"logger": False, "callbacks": [
        {"class_path": "dapm_lightning.training.checkpointing.CheckpointOnSigterm"}, *(ranked if best else []),
        {"class_path": "dapm_lightning.training.checkpointing.LastCheckpoint", "init_args": last}]}}))
    return ["--config", str(QUICKSTART), "--config", str(path)]


def start(tmp_path, name, data, extra=(), pause=None, every_step=True, slow_exit=None, best=False):
    """A run of resume_run.py in a process group of its own; ``pause``: a step, or "STEP,WHERE[,RANK]" (resume_run.py).
    """
    step, _, where = str(pause).partition(",")
    marker = f"{step},{tmp_path / (name + '.marker')}" + (f",{where}" if where else "")
    env = dict(os.environ, PAUSE_AT=marker if pause else "", RECORD_IMAGES=str(tmp_path / f"{name}_images_rank"),
               SLOW_EXIT=str(slow_exit or ""))
    cmd = [sys.executable, str(HERE / "resume_run.py"), str(tmp_path / f"{name}.pt"),
           *job_config(tmp_path, name, every_step, best),
           "--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(data),
           *TINY, *VALIDATE, *extra]
    return subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True)


def terminate_job(process):
    """SIGTERM to every process of the run, loader workers and DDP processes included, as SLURM sends it."""
    os.killpg(process.pid, signal.SIGTERM)


def _group_alive(pgid):
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def give_up(process, why):
    """Fail with every process's stacks (SIGUSR1: resume_run.py's faulthandler) and the run's output; kill the run."""
    if _group_alive(process.pid):
        os.killpg(process.pid, signal.SIGUSR1)
        time.sleep(3)
        os.killpg(process.pid, signal.SIGKILL)
    out, _ = process.communicate()
    pytest.fail(f"{why}; the run's output (stacks of its processes at the end):\n{out[-12000:]}")


def finish(process, timeout=240):
    """The run's exit status and output, once it and every process it started (DDP ranks, loader workers) ended."""
    try:
        out, _ = process.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        give_up(process, f"the run did not end in {timeout} s")
    deadline = time.time() + 30
    while _group_alive(process.pid):  # processes left behind by a run that has ended are a bug of their own
        if time.time() > deadline:
            os.killpg(process.pid, signal.SIGKILL)
            pytest.fail(f"processes of the run still alive 30 s after it ended (status {process.returncode}):\n"
                        f"{out[-3000:]}")
        time.sleep(0.1)
    return process.returncode, out


def wait_for(path, process, timeout=180):
    deadline = time.time() + timeout
    while not path.exists():
        if process.poll() is not None:
            pytest.fail(f"run ended before the marker:\n{process.stdout.read()[-3000:]}")
        if time.time() > deadline:
            give_up(process, f"{path.name} not written in {timeout} s")
        time.sleep(0.1)


def weights(path):
    return torch.load(path, weights_only=True)


@pytest.mark.slow
def test_killed_and_terminated_runs_resume_to_the_uninterrupted_weights(data8, tmp_path):
    """One process, validating every 2 steps (4 batches an epoch): killed after step 3, terminated after step 5 (the
    whole job, a persistent loader worker included, as SLURM does), interrupted by Ctrl-C after step 6 (stopped
    after the validation that follows), terminated in the validation after step 4 (the end of epoch 0; stopped when
    it ends) and stopped by max_steps after step 3 (last.ckpt written when training ends, as the configs do); each,
    resumed to step 8, equals the uninterrupted run."""
    code, out = finish(start(tmp_path, "straight", data8, extra=SCHEDULE))
    assert code == 0, out[-3000:]
    reference = weights(tmp_path / "straight.pt")
    assert reference["global_step"] == 8

    killed = start(tmp_path, "killed", data8, extra=SCHEDULE, pause=3)  # mid-epoch 0 (4 batches per epoch)
    wait_for(tmp_path / "killed.marker", killed)
    killed.send_signal(signal.SIGKILL)
    finish(killed)
    assert (tmp_path / "killed" / "last.ckpt").is_file()  # never half-written: the last complete step's

    workers = ["--data.init_args.num_workers", "1", "--data.init_args.persistent_workers", "true"]
    terminated = start(tmp_path, "termed", data8, extra=[*SCHEDULE, *workers], pause=5)  # mid-epoch 1
    wait_for(tmp_path / "termed.marker", terminated)
    terminate_job(terminated)  # the worker ignores it: the run saves and stops it, no DataLoader error
    code, out = finish(terminated)
    assert "Received SIGTERM" in out and (tmp_path / "termed" / "last.ckpt").is_file(), out[-2000:]
    assert code == EXIT_SIGTERM == 143, out[-2000:]  # pre-empted, not finished: a job script can requeue
    saved = torch.load(tmp_path / "termed" / "last.ckpt", weights_only=True)
    assert saved["global_step"] == 5

    interrupted = start(tmp_path, "ctrl_c", data8, extra=SCHEDULE, pause=6)  # Ctrl-C: saved like SIGTERM, status 130
    wait_for(tmp_path / "ctrl_c.marker", interrupted)
    interrupted.send_signal(signal.SIGINT)
    code, out = finish(interrupted)
    assert code == EXIT_SIGINT == 130 and "Received SIGINT (Ctrl-C)" in out, out[-2000:]
    assert torch.load(tmp_path / "ctrl_c" / "last.ckpt", weights_only=True)["global_step"] == 6
    assert f"saved {tmp_path / 'ctrl_c' / 'last.ckpt'} (step 6); resume with the same command and --ckpt_path " \
        "last" in out, out[-2000:]

    in_validation = start(tmp_path, "termed_val", data8, extra=SCHEDULE, pause="4,val")  # after 1 of 2 val batches
    wait_for(tmp_path / "termed_val.marker", in_validation)
    in_validation.send_signal(signal.SIGTERM)
    code, out = finish(in_validation)
    assert code == EXIT_SIGTERM, out[-2000:]
    saved = torch.load(tmp_path / "termed_val" / "last.ckpt", weights_only=True)
    assert saved["global_step"] == 4
    position = next(v for k, v in saved.items() if k.endswith("DataModule"))
    assert position == {"epoch": 1, "samples_seen": 0}  # epoch 0 trained through: epoch 1 from its start

    stopped = start(tmp_path, "stopped", data8, extra=[*SCHEDULE, "--trainer.max_steps", "3"], every_step=False)
    code, out = finish(stopped)
    assert code == 0, out[-3000:]
    saved = torch.load(tmp_path / "stopped" / "last.ckpt", weights_only=True)
    assert saved["global_step"] == 3  # written when training ended (the last validation's save was at step 2)
    position = next(v for k, v in saved.items() if k.endswith("DataModule"))
    assert position == {"epoch": 0, "samples_seen": 6}

    for name in ("killed", "termed", "ctrl_c", "termed_val", "stopped"):
        code, out = finish(start(tmp_path, name, data8, every_step=name != "stopped",
                                 extra=[*SCHEDULE, *(workers if name == "termed" else []),
                                        "--ckpt_path", str(tmp_path / name / "last.ckpt")]))
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


def fit_in_process(tmp_path, name, data, max_steps, extra=(), ckpt=None, schedule=SCHEDULE, epoch_starts=None,
                   callbacks=()):
    """Fit in this process as a resumable job validating every 2 steps (last.ckpt as the configs write it: at every
    validation and when training ends); returns the weights and the (step, epoch, images) of every batch.
    ``epoch_starts``: a list the epochs whose ``on_train_epoch_start`` ran are appended to."""
    seen = []

    class Record(L.Callback):
        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
            seen.append((trainer.global_step, trainer.current_epoch, tuple(batch["name"])))

        def on_train_epoch_start(self, trainer, pl_module):
            if epoch_starts is not None:
                epoch_starts.append(trainer.current_epoch)

    cli = run_lightning_cli([*job_config(tmp_path, name, every_step=False), "--data.class_path",
                             "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(data),
                             *TINY, *VALIDATE, *schedule, "--trainer.enable_model_summary", "false",
                             "--trainer.max_steps", str(max_steps), *extra], run=False)
    cli.trainer.callbacks.extend([Record(), *callbacks])
    cli.trainer.fit(cli.model, datamodule=cli.datamodule, ckpt_path=ckpt)
    return {k: v.clone() for k, v in cli.model.state_dict().items()}, seen


def assert_resumes_exactly(tmp_path, data, stops, extra=()):
    """Stopped by max_steps at each of ``stops`` and resumed from its last.ckpt to step 8: the batches and the
    weights of the uninterrupted run."""
    reference, order = fit_in_process(tmp_path, "straight", data, 8, extra)
    for stop in stops:
        fit_in_process(tmp_path, f"stop{stop}", data, stop, extra)
        last = tmp_path / f"stop{stop}" / "last.ckpt"
        assert torch.load(last, weights_only=True)["global_step"] == stop
        resumed, seen = fit_in_process(tmp_path, f"stop{stop}", data, 8, extra, ckpt=str(last))
        assert seen == [s for s in order if s[0] >= stop], f"stopped at {stop}: other batches"
        differ = [k for k in reference if not torch.equal(reference[k], resumed[k])]
        assert not differ, f"stopped at {stop}: {len(differ)} of {len(reference)} tensors differ"


def test_stopped_by_max_steps_at_or_after_a_validation_resumes_exactly(data8, tmp_path, monkeypatch):
    """The recipe of docs/long_jobs.md with validation: last.ckpt written by the validation at step 2, and when
    training ended at step 3 (Lightning counts that epoch as done: it would resume in the next one)."""
    monkeypatch.chdir(tmp_path)
    assert_resumes_exactly(tmp_path, data8, stops=(2, 3))


@pytest.mark.parametrize("stops", [(4, 8, 12), (3, 6, 9, 12), (4, 6, 12)])
def test_a_job_resumed_again_and_again_trains_as_the_uninterrupted_one(data8, tmp_path, monkeypatch, stops):
    """A pre-empted job resumed several times (3 epochs of 4 batches): each resume trains the batches the
    uninterrupted run trained from where the last one stopped, every epoch starts once (its start hooks run), and
    the weights end equal. A resume from an epoch's end used to leave the next save's counters such that the
    resume after it skipped a whole epoch and said it had finished."""
    monkeypatch.chdir(tmp_path)
    schedule = ["--model.optimizer.schedule_steps", "12"]
    starts = []
    reference, order = fit_in_process(tmp_path, "straight", data8, 12, schedule=schedule, epoch_starts=starts)
    assert starts == [0, 1, 2]
    starts, previous, weights_now = [], 0, None
    for stop in stops:
        last = tmp_path / "chain" / "last.ckpt"
        weights_now, seen = fit_in_process(tmp_path, "chain", data8, stop, schedule=schedule, epoch_starts=starts,
                                           ckpt=str(last) if previous else None)
        assert seen == [s for s in order if previous <= s[0] < stop], f"resumed at {previous}, to {stop}: other batches"
        assert torch.load(last, weights_only=True)["global_step"] == stop
        previous = stop
    assert sorted(set(starts)) == [0, 1, 2] and len(starts) == len(set(starts)), f"epoch starts {starts}"
    differ = [k for k in reference if not torch.equal(reference[k], weights_now[k])]
    assert not differ, f"{len(differ)} of {len(reference)} tensors differ"


def test_a_job_resumed_at_each_epoch_end_trains_every_epoch(data8, tmp_path, monkeypatch):
    """The configs' rhythm (a validation at each epoch's end, last.ckpt then and when training ends), stopped by
    max_epochs and resumed three times: every resume trains one whole epoch, the batches of the uninterrupted run,
    and saves where the next starts. The second resume used to train nothing and say `max_epochs` was reached."""
    monkeypatch.chdir(tmp_path)
    schedule = ["--model.optimizer.schedule_steps", "16"]

    def by_epochs(epochs):
        return ["--trainer.max_steps", "-1", "--trainer.max_epochs", str(epochs), "--trainer.val_check_interval",
                "1.0"]

    starts = []
    reference, order = fit_in_process(tmp_path, "straight", data8, 0, extra=by_epochs(4), schedule=schedule,
                                      epoch_starts=starts)
    assert starts == [0, 1, 2, 3] and len(order) == 16
    starts, weights_now = [], None
    last = tmp_path / "chain" / "last.ckpt"
    for epochs in (1, 2, 3, 4):
        weights_now, seen = fit_in_process(tmp_path, "chain", data8, 0, extra=by_epochs(epochs), schedule=schedule,
                                           epoch_starts=starts, ckpt=str(last) if epochs > 1 else None)
        assert seen == [s for s in order if s[1] == epochs - 1], f"the run to epoch {epochs}: other batches"
        saved = torch.load(last, weights_only=True)
        assert saved["global_step"] == 4 * epochs
        assert saved["UAPDDataModule"] == {"epoch": epochs, "samples_seen": 0}
    assert starts == [0, 1, 2, 3]
    differ = [k for k in reference if not torch.equal(reference[k], weights_now[k])]
    assert not differ, f"{len(differ)} of {len(reference)} tensors differ"


@pytest.mark.slow
@pytest.mark.parametrize("every", [2, 3])
def test_stopped_by_max_steps_anywhere_resumes_exactly_with_persistent_workers(data8, tmp_path, monkeypatch, every):
    """Every stop of two epochs: before, at and after a validation, at an epoch's end; with a persistent loader
    worker (it draws its first batches before Lightning tells the sampler the epoch)."""
    monkeypatch.chdir(tmp_path)
    assert_resumes_exactly(tmp_path, data8, stops=range(1, 8), extra=[
        "--trainer.val_check_interval", str(every), "--data.init_args.num_workers", "1",
        "--data.init_args.persistent_workers", "true"])


class SignalAfterBatch(L.Callback):
    """Sends ``signum`` to this process after training batch ``batch`` (counted over the run, from 1)."""

    def __init__(self, signum, batch):
        self.signum, self.batch = signum, batch

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.fit_loop.epoch_loop.batch_progress.total.processed == self.batch:
            os.kill(os.getpid(), self.signum)


def test_a_stop_inside_an_accumulation_window_waits_for_its_optimizer_step(data8, tmp_path, monkeypatch):
    """One process accumulating 2 batches a step (4 batches an epoch, validating every 2): SIGTERM after batch 1
    stops after batch 2 (step 1, after the validation that follows), Ctrl-C after batch 5 stops after batch 6 (step 3);
    each saves the position after its step, and resumed to step 4 equals the uninterrupted run bit for bit. (It
    stopped after the micro-batch: the position counted it as trained, but its gradients were not saved.)"""
    monkeypatch.chdir(tmp_path)
    accumulate = ["--trainer.accumulate_grad_batches", "2"]
    reference, _ = fit_in_process(tmp_path, "straight", data8, 4, accumulate)
    for signum, after, status, step, position in ((signal.SIGTERM, 1, EXIT_SIGTERM, 1, {"epoch": 0, "samples_seen": 4}),
                                                  (signal.SIGINT, 5, EXIT_SIGINT, 3, {"epoch": 1, "samples_seen": 4})):
        name = signal.Signals(signum).name
        with pytest.raises(SystemExit) as info:
            fit_in_process(tmp_path, name, data8, 4, accumulate, callbacks=[SignalAfterBatch(signum, after)])
        assert info.value.code == status, name
        saved = torch.load(tmp_path / name / "last.ckpt", weights_only=True)
        assert (saved["global_step"], saved["UAPDDataModule"]) == (step, position), name
        resumed, seen = fit_in_process(tmp_path, name, data8, 4, accumulate, ckpt=str(tmp_path / name / "last.ckpt"))
        assert len(seen) == 8 - 2 * step, name
        differ = [k for k in reference if not torch.equal(reference[k], resumed[k])]
        assert not differ, f"{name}: {len(differ)} of {len(reference)} tensors differ"


def names_per_epoch(*runs):
    """Every image trained in each epoch, over runs of :func:`fit_in_process` (their batches)."""
    epochs = {}
    for seen in runs:
        for _, epoch, names in seen:
            epochs.setdefault(epoch, []).extend(names)
    return epochs


def test_a_resume_with_another_global_batch_trains_each_sample_once(data8, tmp_path, monkeypatch):
    """Resumed with another global batch (batch size x processes; here the batch size, the process count in the slow
    tier): 2 a batch stopped by max_steps after 3 of 4 batches, resumed 4 a batch (epoch 0 ends with its last sample,
    the 2 samples of batch 3 trained twice: the position rounds down to whole batches; epoch 1 whole) to its end,
    resumed 2 a batch again (epoch 2 whole: 4 batches). The first resume ended its epoch after 0 batches, the second
    ran 2 of epoch 2's 4."""
    monkeypatch.chdir(tmp_path)

    def batch(size):
        return ["--data.init_args.batch_size", str(size), "--model.optimizer.schedule_steps", "10"]

    _, first = fit_in_process(tmp_path, "b2", data8, 3, batch(2))
    _, second = fit_in_process(tmp_path, "b4", data8, 6, batch(4), ckpt=str(tmp_path / "b2" / "last.ckpt"))
    assert torch.load(tmp_path / "b4" / "last.ckpt", weights_only=True)["UAPDDataModule"] == {"epoch": 2,
                                                                                           "samples_seen": 0}
    _, third = fit_in_process(tmp_path, "b2again", data8, 10, batch(2), ckpt=str(tmp_path / "b4" / "last.ckpt"))
    assert [len(names) for _, _, names in second] == [4, 4, 4] and len(third) == 4
    epochs = names_per_epoch(first, second, third)
    everything = sorted(set(epochs[0]))
    assert len(everything) == 8
    twice = sorted(name for name in everything if epochs[0].count(name) == 2)
    assert twice == sorted(first[-1][2]) and len(epochs[0]) == 10  # batch 3's, the rest once
    assert sorted(epochs[1]) == sorted(epochs[2]) == everything


def test_a_resume_past_this_runs_limit_train_batches_ends_that_epoch(data8, tmp_path, monkeypatch):
    """limit_train_batches 2 counts batches of each process: an epoch is 8 samples 4 a batch, 4 samples 2 a batch
    (the global batch here the batch size, the process count in the slow tier). Stopped after 1 batch of 4 (4
    samples: all of the resumed run's epoch) and resumed 2 a batch: epoch 0 trains the last batch of its 2 again
    (samples 2-3 of the order) and ends, epoch 1 trains 2. It ran 2 more batches (samples 4-7) in epoch 0."""
    monkeypatch.chdir(tmp_path)

    def batch(size):
        return ["--data.init_args.batch_size", str(size), "--trainer.limit_train_batches", "2",
                "--trainer.max_steps", "-1", "--trainer.max_epochs", "2", "--trainer.val_check_interval", "1"]

    _, first = fit_in_process(tmp_path, "run", data8, 0, [*batch(4), "--trainer.max_steps", "1"])
    assert torch.load(tmp_path / "run" / "last.ckpt", weights_only=True)["UAPDDataModule"] == {"epoch": 0,
                                                                                            "samples_seen": 4}
    _, second = fit_in_process(tmp_path, "run", data8, 0, batch(2), ckpt=str(tmp_path / "run" / "last.ckpt"))
    epochs = names_per_epoch(second)
    assert epochs[0] == list(first[0][2][2:]) and len(set(epochs[1])) == 4, epochs
    assert torch.load(tmp_path / "run" / "last.ckpt", weights_only=True)["UAPDDataModule"] == {"epoch": 2,
                                                                                            "samples_seen": 0}


def test_validation_leaves_training_alone_even_when_it_draws_random_numbers(data8, tmp_path, monkeypatch):
    """Training draws (dropout) the same numbers whether validations ran in between or not, whatever they draw: the
    RNG states of training are put back after each validation, and a checkpoint written during one saves those."""
    monkeypatch.chdir(tmp_path)
    states = []
    for validate in (False, True):
        cli = run_lightning_cli(["--config", str(QUICKSTART), "--data.class_path",
                                 "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(data8),
                                 *TINY, "--trainer.max_steps", "4", "--trainer.logger", "false",
                                 "--trainer.callbacks", "[]", "--trainer.enable_checkpointing", "false",
                                 *(["--trainer.limit_val_batches", "1.0", "--trainer.val_check_interval", "1"]
                                   if validate else [])], run=False)
        model, real = cli.model, cli.model.validation_step

        def drawing_validation_step(batch, batch_idx, real=real):
            torch.rand(3), np.random.rand(3), random.random()  # a metric or callback that samples
            return real(batch, batch_idx)

        model.validation_step = drawing_validation_step
        cli.trainer.fit(model, datamodule=cli.datamodule)
        assert cli.trainer.global_step == 4
        states.append({k: v.clone() for k, v in model.state_dict().items()})
    assert model.net_config.dropout > 0  # training does draw random numbers
    assert all(torch.equal(states[0][k], states[1][k]) for k in states[0])


def test_closed_epoch_counters_become_those_after_the_last_batch():
    """Lightning's counters when training ended by max_steps after 3 of 4 batches, rewritten to those of a save
    right after batch 3; those of a save after a batch, and of an open epoch, stay as they are."""
    def progress(**counts):
        return {"total": dict(counts), "current": dict(counts)}

    ended = {"epoch_progress": progress(ready=1, started=1, processed=1, completed=1),
             "epoch_loop.batch_progress": {**progress(ready=3, started=3, processed=3, completed=3),
                                           "is_last_batch": False},
             "epoch_loop.state_dict": {"_batches_that_stepped": 3}}
    assert resume_after_last_batch(ended)
    assert ended == {"epoch_progress": progress(ready=1, started=1, processed=0, completed=0),
                     "epoch_loop.batch_progress": {**progress(ready=3, started=3, processed=3, completed=2),
                                                   "is_last_batch": False},
                     "epoch_loop.state_dict": {"_batches_that_stepped": 2}}
    assert not resume_after_last_batch(ended)  # now the state of a save after a batch: Lightning resumes it well
    epoch_end = {"epoch_progress": progress(ready=1, started=1, processed=1, completed=0),  # on_train_epoch_end
                 "epoch_loop.batch_progress": progress(ready=4, started=4, processed=4, completed=4)}
    assert resume_after_last_batch(epoch_end)
    assert epoch_end["epoch_progress"]["current"] == {"ready": 1, "started": 1, "processed": 0, "completed": 0}
    assert epoch_end["epoch_loop.batch_progress"]["current"]["completed"] == 3


def test_restored_batch_counters_count_the_batches_the_loader_resumes_after():
    """Saved by 1 process after 3 batches (of 8 an epoch) and resumed on 2 (4 an epoch), whose loader skips 1 (the
    position rounded down to whole batches): the counters say 1 (Lightning would end the epoch after 1 more batch,
    or save 5 x 2 x 2 samples seen after 2). Saved by 2 after their epoch's 4 batches and resumed on 1: 8, all of the
    epoch (Lightning would run 4 of the next epoch's 8). On the same process count nothing changes."""
    def fit_loop(epoch, batches, last, per_epoch):
        progress = _BatchProgress()
        progress.increment_by(batches, is_last_batch=last)
        return SimpleNamespace(epoch_loop=SimpleNamespace(batch_progress=progress),
                               epoch_progress=SimpleNamespace(current=SimpleNamespace(processed=epoch)),
                               trainer=SimpleNamespace(num_training_batches=per_epoch))

    def counts(loop):
        return [(c.ready, c.started, c.processed, c.completed) for c in (loop.epoch_loop.batch_progress.current,
                                                                          loop.epoch_loop.batch_progress.total)]

    mid_epoch = fit_loop(epoch=0, batches=3, last=False, per_epoch=4)
    assert count_batches_as_resumed(mid_epoch, epoch=0, batches=1)
    assert counts(mid_epoch) == [(1, 1, 1, 1)] * 2
    for closed_by_lightning in (True, False):  # Lightning closes the epoch after a save on its last batch, or runs
        epoch_end = fit_loop(epoch=int(closed_by_lightning), batches=4, last=True, per_epoch=8)  # its end again
        assert count_batches_as_resumed(epoch_end, epoch=1, batches=0)
        assert counts(epoch_end) == [(8, 8, 8, 8)] * 2
    same = fit_loop(epoch=0, batches=3, last=False, per_epoch=8)
    assert not count_batches_as_resumed(same, epoch=0, batches=3) and counts(same) == [(3, 3, 3, 3)] * 2


def test_an_epoch_not_yet_started_is_not_closed():
    from dapm_lightning.training.resume import epoch_closed

    def progress(ready, started, processed):
        return {"current": {"ready": ready, "started": started, "processed": processed, "completed": 0}}

    assert not epoch_closed(progress(0, 0, 0))  # a fit before its first epoch
    assert epoch_closed(progress(1, 1, 1)) and not epoch_closed(progress(1, 1, 0))


def test_the_saved_position_counts_the_samples_of_every_process_and_the_epoch_limit_rounds_down():
    """The data module's checkpoint state: batches x batch size x processes (DDP), the next epoch from its start once
    the epoch's batches are all done; a share limit_train_batches cuts an epoch as Lightning does (rounded down)."""
    from lightning.pytorch.trainer.states import TrainerFn

    from dapm_lightning.data.datamodules import DAPMDataModule

    module = DAPMDataModule(batch_size=3, num_workers=0)
    current = SimpleNamespace(processed=2)
    module.trainer = SimpleNamespace(
        state=SimpleNamespace(fn=TrainerFn.FITTING), num_training_batches=5, world_size=4, limit_train_batches=0.5,
        fit_loop=SimpleNamespace(epoch_loop=SimpleNamespace(batch_progress=SimpleNamespace(current=current)),
                                 epoch_progress=SimpleNamespace(current=SimpleNamespace(started=2))))
    assert module.state_dict() == {"epoch": 1, "samples_seen": 2 * 3 * 4}
    current.processed = 5
    assert module.state_dict() == {"epoch": 2, "samples_seen": 0}
    assert module._epoch_batches(7) == 3  # int(3.5), as Lightning counts
    module.trainer.limit_train_batches = 4
    assert module._epoch_batches(7) == 4 and module._epoch_batches(3) == 3


def test_a_training_set_smaller_than_a_batch_still_trains_on_one_batch(tiny_uapd):
    from dapm_lightning.data.datamodules import UAPDDataModule

    module = UAPDDataModule(tiny_uapd, batch_size=8, num_workers=0)  # 4 training images
    module.setup("fit")
    assert [len(batch["name"]) for batch in module.train_dataloader()] == [4]


def test_rng_states_packed_for_ddp_restore_python_s_gauss_cache_alike():
    """Packed into tensors (per-rank checkpoints) and back: the draws after the restore are the same, with Python's
    cached second Gaussian present or not."""
    from dapm_lightning.training.rng import pack_rng_states, rng_states, set_rng_states, unpack_rng_states

    for cached in (False, True):
        random.seed(3)
        if cached:
            random.gauss(0.0, 1.0)  # leaves the pair's second value cached
        saved = rng_states()
        expected = [random.gauss(0.0, 1.0) for _ in range(3)], np.random.rand(2).tolist(), torch.rand(2).tolist()
        set_rng_states(unpack_rng_states(pack_rng_states(saved)))
        drawn = [random.gauss(0.0, 1.0) for _ in range(3)], np.random.rand(2).tolist(), torch.rand(2).tolist()
        assert drawn == expected, cached


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
    with pytest.warns(UserWarning, match="non-finite training loss .*step skipped, weights unchanged"):
        cli.trainer.fit(model, datamodule=cli.datamodule)
    assert model.nonfinite_steps >= 1
    for key, value in model.state_dict().items():
        if "running" not in key and "num_batches" not in key:  # batch-norm statistics move in any forward
            assert torch.equal(value, before[key]), key


def test_the_count_of_skipped_steps_goes_on_across_a_resume(tiny_uapd, tmp_path, monkeypatch):
    """The warning's "N so far" counted from 0 again after a resume: the count is in the checkpoint."""
    monkeypatch.chdir(tmp_path)

    def fit(max_steps, *extra):
        cli = run_lightning_cli(["--config", str(QUICKSTART), "--data.class_path",
                                 "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root",
                                 str(tiny_uapd), *TINY, "--trainer.max_steps", str(max_steps), "--trainer.logger",
                                 "false", "--trainer.callbacks", "[]", "--trainer.enable_checkpointing", "false"],
                                run=False)
        real = cli.model.criterion.forward
        monkeypatch.setattr(cli.model.criterion, "forward",
                            lambda out, t: {**real(out, t), "total": torch.tensor(float("nan"), requires_grad=True)})
        with pytest.warns(UserWarning, match="non-finite training loss") as caught:
            cli.trainer.fit(cli.model, datamodule=cli.datamodule, ckpt_path=extra[0] if extra else None)
        return cli, [str(w.message) for w in caught if "non-finite" in str(w.message)]

    first, _ = fit(1)
    assert first.model.nonfinite_steps == 1
    first.trainer.save_checkpoint(tmp_path / "skipped.ckpt")
    resumed, said = fit(2, str(tmp_path / "skipped.ckpt"))
    assert resumed.model.nonfinite_steps == 2 and "(2 so far)" in said[-1], said


class NonFiniteLossOn(L.Callback):
    """Makes the training loss of process ``rank`` NaN at step ``step``, once (the other processes' stay finite)."""

    def __init__(self, rank: int, step: int) -> None:
        self.rank, self.step = rank, step

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        if trainer.global_rank != self.rank or trainer.global_step != self.step:
            return
        criterion = pl_module.criterion
        real = criterion.forward

        def nan_once(out, targets):
            del criterion.forward  # the class's forward again
            return {**real(out, targets), "total": torch.tensor(float("nan"), requires_grad=True)}

        criterion.forward = nan_once


@pytest.mark.slow
def test_a_nonfinite_loss_on_one_ddp_process_skips_the_step_on_every_process_and_is_counted(data16, tmp_path):
    """Two processes, rank 1's loss NaN at step 1: every process takes the zero-gradient step, and the step is counted
    (the checkpoint's count, the resumed run's "N so far") and its files named. Before, rank 1 alone zeroed its
    gradients (rank 0's still stepped the weights), rank 1 alone counted the step and warned nowhere (rank_zero_warn),
    and the checkpoint held rank 0's count: 0."""
    out = tmp_path / "fit.json"
    cmd = [sys.executable, str(HERE / "ddp_run.py"), str(out), "fit", *job_config(tmp_path, "run"),
           "--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root",
           str(data16), *TINY, *DDP, "--trainer.max_steps", "2", f"--trainer.callbacks+={__name__}.NonFiniteLossOn",
           "--trainer.callbacks.rank", "1", "--trainer.callbacks.step", "1", "--data.init_args.num_workers", "0"]
    run = subprocess.Popen(cmd, cwd=tmp_path, env={**os.environ, "PYTHONPATH": str(HERE.parents[1])},
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    code, log = finish(run, timeout=300)
    assert code == 0, log[-3000:]
    saved = torch.load(tmp_path / "run" / "last.ckpt", weights_only=True)
    assert (saved["global_step"], saved["dapm_nonfinite_steps"]) == (2, 1)
    assert "non-finite training loss at step 1 (process 1, batch 1: " in log, log[-3000:]
    # not "weights unchanged": AdamW's momentum and decay move them (the one-process wording, before)
    assert "a zero-gradient step on every process (AdamW's momentum and weight decay still apply)" in log, log[-3000:]
    assert json.loads(out.read_text())["metrics"]["train_nonfinite_steps"] == 1.0  # logged by rank 0 too


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
    """2 processes, persistent workers, 4 steps per epoch, validating every 2 steps: stopped by max_steps at step 6
    (last.ckpt written by the validation there, as the configs do), by SIGTERM to rank 0 (step 3), and by SIGTERM to
    the whole job while rank 1 gathers the metrics of the validation after step 4 and rank 0 has not started to (both
    stop when that validation ends: no collective in a signal handler), each resumed from last.ckpt to step 10,
    equal the uninterrupted run bit for bit; Ctrl-C (step 3) saves too."""
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

    code, out = finish(start(tmp_path, "stopped", data16, extra=[*DDP, "--trainer.max_steps", "6"], every_step=False),
                       timeout=400)
    assert code == 0, out[-3000:]
    assert torch.load(tmp_path / "stopped" / "last.ckpt", weights_only=True)["global_step"] == 6

    # the main process 7 s slower to exit than the other: Lightning's watcher (polling every 5 s) must not take
    # the other's exit for a failure and kill it (status -9: a job script would not requeue)
    terminated = start(tmp_path, "termed", data16, extra=DDP, pause=3, slow_exit=7)
    wait_for(tmp_path / "termed.marker", terminated)
    terminated.send_signal(signal.SIGTERM)
    code, out = finish(terminated, timeout=400)
    saved = torch.load(tmp_path / "termed" / "last.ckpt", weights_only=True)
    assert saved["global_step"] == 3, out[-3000:]
    assert code == EXIT_SIGTERM, out[-3000:]
    position = next(v for k, v in saved.items() if k.endswith("DataModule"))
    assert position == {"epoch": 0, "samples_seen": 3 * 2 * 2}  # global: 3 batches of 2 on each of 2 processes

    interrupted = start(tmp_path, "ctrl_c", data16, extra=DDP, pause=3, slow_exit=7)  # Ctrl-C to the main: passed on
    wait_for(tmp_path / "ctrl_c.marker", interrupted)
    interrupted.send_signal(signal.SIGINT)
    code, out = finish(interrupted, timeout=400)
    assert code == EXIT_SIGINT, out[-3000:]
    assert torch.load(tmp_path / "ctrl_c" / "last.ckpt", weights_only=True)["global_step"] == 3, out[-3000:]

    between = start(tmp_path, "termed_valend", data16, extra=DDP, pause="4,valend,0")
    wait_for(tmp_path / "termed_valend.marker", between)
    terminate_job(between)
    code, out = finish(between, timeout=400)
    assert code == EXIT_SIGTERM, out[-3000:]
    saved = torch.load(tmp_path / "termed_valend" / "last.ckpt", weights_only=True)
    assert saved["global_step"] == 4, out[-3000:]  # the validation finished, then both stopped

    for name in ("stopped", "termed", "termed_valend"):
        code, out = finish(start(tmp_path, name, data16, every_step=name != "stopped",
                                 extra=[*DDP, "--ckpt_path", str(tmp_path / name / "last.ckpt")]), timeout=400)
        assert code == 0, out[-3000:]
        resumed = weights(tmp_path / f"{name}.pt")
        assert resumed["global_step"] == 10
        for key, value in reference["state_dict"].items():
            assert torch.equal(value, resumed["state_dict"][key]), f"{name}: {key} differs"


@pytest.mark.slow
def test_two_process_ddp_job_resumed_at_each_epoch_end_trains_every_epoch(data16, tmp_path):
    """2 processes with persistent workers, the configs' rhythm (a validation at each epoch's end), stopped by
    max_epochs after epochs 1 and 2 and resumed each time: the third run trains epoch 3 and ends equal to the
    uninterrupted run bit for bit (the second resume in a row used to train nothing)."""
    def by_epochs(epochs):
        return [*DDP, "--trainer.max_steps", "-1", "--trainer.max_epochs", str(epochs),
                "--model.optimizer.schedule_steps", "12", "--trainer.val_check_interval", "1.0"]

    code, out = finish(start(tmp_path, "straight", data16, extra=by_epochs(3), every_step=False), timeout=400)
    assert code == 0, out[-3000:]
    reference = weights(tmp_path / "straight.pt")
    assert reference["global_step"] == 12
    for epochs in (1, 2, 3):
        resume = ["--ckpt_path", str(tmp_path / "chain" / "last.ckpt")] if epochs > 1 else []
        code, out = finish(start(tmp_path, "chain", data16, extra=[*by_epochs(epochs), *resume], every_step=False),
                           timeout=400)
        assert code == 0, out[-3000:]
        saved = torch.load(tmp_path / "chain" / "last.ckpt", weights_only=True)
        assert saved["global_step"] == 4 * epochs, out[-3000:]
        assert next(v for k, v in saved.items() if k.endswith("DataModule")) == {"epoch": epochs, "samples_seen": 0}
    resumed = weights(tmp_path / "chain.pt")
    for key, value in reference["state_dict"].items():
        assert torch.equal(value, resumed["state_dict"][key]), f"{key} differs"


@pytest.mark.slow
def test_two_process_ddp_stop_inside_an_accumulation_window_resumes_exactly(data16, tmp_path):
    """2 processes accumulating 2 batches a step (4 batches an epoch, validating every 2): SIGTERM to the whole job
    after batch 1 stops both after batch 2 (step 1), saving the position after it, and the run resumed to step 4
    equals the uninterrupted one bit for bit; Ctrl-C to the main process after batch 5 stops both after batch 6."""
    accumulate = [*DDP, "--trainer.accumulate_grad_batches", "2", "--trainer.max_steps", "4",
                  "--model.optimizer.schedule_steps", "4"]
    code, out = finish(start(tmp_path, "straight", data16, extra=accumulate), timeout=400)
    assert code == 0, out[-3000:]
    reference = weights(tmp_path / "straight.pt")

    for name, pause, stop, status, step, position in (
            ("termed", "1,batch", terminate_job, EXIT_SIGTERM, 1, {"epoch": 0, "samples_seen": 2 * 2 * 2}),
            ("ctrl_c", "5,batch", lambda run: run.send_signal(signal.SIGINT), EXIT_SIGINT, 3,
             {"epoch": 1, "samples_seen": 2 * 2 * 2})):
        run = start(tmp_path, name, data16, extra=accumulate, pause=pause)
        wait_for(tmp_path / f"{name}.marker", run)
        stop(run)
        code, out = finish(run, timeout=400)
        assert code == status, out[-3000:]
        saved = torch.load(tmp_path / name / "last.ckpt", weights_only=True)
        assert (saved["global_step"], saved["UAPDDataModule"]) == (step, position), out[-3000:]

    code, out = finish(start(tmp_path, "termed", data16, extra=[*accumulate, "--ckpt_path",
                                                               str(tmp_path / "termed" / "last.ckpt")]), timeout=400)
    assert code == 0, out[-3000:]
    resumed = weights(tmp_path / "termed.pt")
    assert resumed["global_step"] == 4
    for key, value in reference["state_dict"].items():
        assert torch.equal(value, resumed["state_dict"][key]), f"{key} differs"


@pytest.mark.slow
def test_resumed_on_another_number_of_processes_each_sample_is_trained_once(data16, tmp_path):
    """A job requeued on 1, 2, 1 and 2 processes (16 images, 2 a batch: 8 batches an epoch on 1, 4 on 2), each run
    stopped by max_steps: 1 process after 3 batches (6 images), 2 to the end of epoch 0, 1 to the middle of epoch 1,
    2 to the end of epoch 2. Every epoch trains every image once, but for the 2 of the first run's last batch (the
    position rounds down to whole batches of both processes); every epoch runs its whole count of batches. Epoch 0
    skipped 4 images and ended early; 2 to 1 trained 4 images twice."""
    def processes(count, max_steps, resume=None):
        return [*DDP, "--trainer.devices", str(count), "--trainer.strategy", "ddp" if count > 1 else "auto",
                "--trainer.max_steps", str(max_steps), "--model.optimizer.schedule_steps", "16",
                *(["--ckpt_path", str(tmp_path / resume / "last.ckpt")] if resume else [])]

    runs = (("one", processes(1, 3), {"epoch": 0, "samples_seen": 6}),
            ("two", processes(2, 6, "one"), {"epoch": 1, "samples_seen": 0}),
            ("one_again", processes(1, 10, "two"), {"epoch": 1, "samples_seen": 8}),
            ("two_again", processes(2, 16, "one_again"), {"epoch": 3, "samples_seen": 0}))
    epochs = {}
    for name, args, position in runs:
        code, out = finish(start(tmp_path, name, data16, extra=args, every_step=False), timeout=400)
        assert code == 0, out[-3000:]
        saved = torch.load(tmp_path / name / "last.ckpt", weights_only=True)
        assert saved["UAPDDataModule"] == position, f"{name}: {saved['UAPDDataModule']}"
        for path in sorted(tmp_path.glob(f"{name}_images_rank*_names.json")):
            for epoch, names in json.loads(path.read_text()).items():
                epochs.setdefault(int(epoch), {}).setdefault(name, []).extend(names)
    everything = sorted(Path(name).stem for name in UAPDDataset(data16, "train").names)
    first_last_batch = json.loads((tmp_path / "one_images_rank0_names.json").read_text())["0"][4:6]
    epoch0 = epochs[0]["one"] + epochs[0]["two"]
    assert sorted(epoch0) == sorted(everything + first_last_batch), epochs[0]
    assert sorted(epochs[1]["one_again"] + epochs[1]["two_again"]) == everything, epochs[1]
    assert sorted(epochs[2]["two_again"]) == everything, epochs[2]


@pytest.mark.slow
@pytest.mark.parametrize("devices", [1, 2])
def test_a_stop_agreed_before_a_validation_runs_that_validation_first(data8, tmp_path, devices):
    """SIGTERM to the whole job after a step that a validation follows (2 batches an epoch, a validation after each:
    step 1 inside epoch 0, step 2 at its end; one process 2 validation batches, two processes 1 each), resumed each
    time, to step 3: the chain's validations (steps and val_loss), its best-model checkpoints and its weights are
    the uninterrupted run's. (The stop came before the validation under DDP, and cut it after its first batch with
    one process: the resumed run skipped it, its val_loss and its best-*.ckpt never existed.)"""
    args = [*DDP, "--trainer.devices", str(devices), "--trainer.strategy", "ddp" if devices > 1 else "auto",
            "--data.init_args.batch_size", str(4 // devices), "--trainer.val_check_interval", "1",
            "--trainer.max_steps", "3", "--model.optimizer.schedule_steps", "3"]

    def validations(name):  # [step, val_loss] of each validation that ended
        path = tmp_path / f"{name}_images_rank0_validations.json"
        return json.loads(path.read_text()) if path.exists() else []

    code, out = finish(start(tmp_path, "straight", data8, extra=args, every_step=False, best=True), timeout=400)
    assert code == 0, out[-3000:]
    chained = []
    for pause in (1, 2, None):
        for stale in (tmp_path / "chain.marker", tmp_path / "chain_images_rank0_validations.json"):
            stale.unlink(missing_ok=True)
        resume = ["--ckpt_path", str(tmp_path / "chain" / "last.ckpt")] if pause != 1 else []
        run = start(tmp_path, "chain", data8, extra=[*args, *resume], pause=pause, every_step=False, best=True)
        if pause:
            wait_for(tmp_path / "chain.marker", run)
            terminate_job(run)
        code, out = finish(run, timeout=400)
        assert code == (EXIT_SIGTERM if pause else 0), out[-3000:]
        if pause:
            assert torch.load(tmp_path / "chain" / "last.ckpt", weights_only=True)["global_step"] == pause
        chained += validations("chain")
    assert [step for step, _ in validations("straight")] == [1, 2, 3]
    assert chained == validations("straight"), chained
    best = sorted(path.name for path in (tmp_path / "chain").glob("*-step=*.ckpt"))
    assert best == sorted(path.name for path in (tmp_path / "straight").glob("*-step=*.ckpt")), best
    assert len(best) == 5  # best- at each of the 3 validations, epoch- at the 2 epochs' ends
    reference, resumed = weights(tmp_path / "straight.pt"), weights(tmp_path / "chain.pt")
    for key, value in reference["state_dict"].items():
        assert torch.equal(value, resumed["state_dict"][key]), f"{key} differs"


@pytest.mark.slow
def test_limit_train_batches_resumed_on_another_number_of_processes_ends_the_epoch_at_its_limit(data16, tmp_path):
    """limit_train_batches 3 counts each process's batches: an epoch is 12 of the 16 images on 2 processes, 6 on 1
    (2 a batch). 2 processes stopped after 2 steps (8 images) and resumed on 1: epoch 0 trains the last batch of its
    3 again (images 4-5 of the order) and ends, epoch 1 trains 3 batches (it ran 3 more, images 8-13, in epoch 0).
    1 process stopped after 2 steps (4 images) and resumed on 2: epoch 0 trains images 4-11 once each, epoch 1
    3 batches on each process."""
    def processes(count, resume=None):
        return [*DDP, "--trainer.devices", str(count), "--trainer.strategy", "ddp" if count > 1 else "auto",
                "--trainer.max_steps", "-1" if resume else "2", "--trainer.max_epochs", "2",
                "--trainer.limit_train_batches", "3", "--trainer.limit_val_batches", "0",
                *(["--ckpt_path", str(tmp_path / resume / "last.ckpt")] if resume else [])]

    def names(name):  # the images each epoch trained, all processes
        epochs = {}
        for path in sorted(tmp_path.glob(f"{name}_images_rank*_names.json")):
            for epoch, trained in json.loads(path.read_text()).items():
                epochs.setdefault(int(epoch), []).extend(trained)
        return epochs

    runs = (("two", processes(2), 8), ("one", processes(1, "two"), 0), ("one_b", processes(1), 4),
            ("two_b", processes(2, "one_b"), 0))
    for name, args, samples in runs:
        code, out = finish(start(tmp_path, name, data16, extra=args, every_step=False), timeout=400)
        assert code == 0, out[-3000:]
        saved = torch.load(tmp_path / name / "last.ckpt", weights_only=True)
        assert saved["UAPDDataModule"] == {"epoch": 2 if samples == 0 else 0, "samples_seen": samples}, name
    two = [json.loads((tmp_path / f"two_images_rank{rank}_names.json").read_text())["0"] for rank in (0, 1)]
    one = names("one")
    assert one[0] == [two[0][2], two[1][2]] and len(set(one[1])) == 6, one  # images 4 and 5 of the order: step 2's
    epoch0 = names("one_b")[0] + names("two_b")[0]
    assert len(epoch0) == len(set(epoch0)) == 12 and len(set(names("two_b")[1])) == 12


class WaitAtStep(L.Callback):
    """After training step ``step``: writes ``marker`` and waits (60 s at most) for the file ``go`` to appear."""

    def __init__(self, step: int, marker: str, go: str) -> None:
        self.step, self.marker, self.go = step, Path(marker), Path(go)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        if trainer.global_step == self.step:
            self.marker.write_text(str(self.step))
            deadline = time.time() + 60
            while not self.go.exists() and time.time() < deadline:
                time.sleep(0.05)


class WaitAtValidationEnd(L.Callback):
    """On process ``rank`` only, at the end of the validation after step ``step`` (before its metrics are gathered):
    writes ``marker`` and waits (60 s at most) for the file ``go``; the other processes run on into the gathering."""

    def __init__(self, step: int, rank: int, marker: str, go: str) -> None:
        self.step, self.rank, self.marker, self.go = step, rank, Path(marker), Path(go)

    def on_validation_epoch_end(self, trainer, pl_module):  # callbacks' hook: before the module's metric sync
        if trainer.sanity_checking or trainer.global_step != self.step or trainer.global_rank != self.rank:
            return
        self.marker.write_text(str(self.step))
        deadline = time.time() + 60
        while not self.go.exists() and time.time() < deadline:
            time.sleep(0.05)


@pytest.mark.slow
def test_lightning_s_slurm_requeue_signal_under_ddp_saves_and_requeues_after_the_same_step(data16, tmp_path):
    """``#SBATCH --signal=USR1@90`` to a job of two SLURM tasks (two processes, DDP) while rank 1 gathers a
    validation's metrics and rank 0 has not started to: Lightning's requeue runs on both processes after the next
    step (its hpc checkpoint of step 3, one ``scontrol requeue``) and training goes on to its end. Lightning's handler
    saved from inside the signal handler: rank 0's gather of the RNG states met rank 1's metric gather, gloo aborted
    both ("collective mismatch": status 1, and SIGABRT) and the job was not requeued."""
    scontrol = tmp_path / "bin" / "scontrol"
    scontrol.parent.mkdir()
    scontrol.write_text(f"#!/bin/sh\necho \"$@\" >> {tmp_path / 'scontrol.calls'}\n")
    scontrol.chmod(0o755)
    marker, go, root = tmp_path / "at_validation", tmp_path / "go", tmp_path / "root"
    config = job_config(tmp_path, "run")
    job = yaml.safe_load((tmp_path / "run.yaml").read_text())
    job["trainer"]["callbacks"].append({"class_path": f"{__name__}.WaitAtValidationEnd",
                                        "init_args": {"step": 2, "rank": 0, "marker": str(marker), "go": str(go)}})
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(job))
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    slurm = {"SLURM_NTASKS": "2", "SLURM_NTASKS_PER_NODE": "2", "SLURM_NNODES": "1", "SLURM_NODEID": "0",
             "SLURM_JOB_ID": "4242", "SLURM_JOB_NAME": "dapm", "SLURM_NODELIST": "127.0.0.1",
             "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)}
    cmd = [sys.executable, "-m", "dapm_lightning", "fit", *config, "--data.class_path",
           "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(data16), *TINY, *VALIDATE,
           "--trainer.max_steps", "4", "--trainer.accelerator", "cpu", "--trainer.devices", "2",
           "--trainer.strategy", "ddp", "--trainer.default_root_dir", str(root)]
    tasks = [subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              start_new_session=True,
                              env={**os.environ, **slurm, "SLURM_PROCID": str(rank), "SLURM_LOCALID": str(rank),
                                   "PATH": f"{scontrol.parent}{os.pathsep}{os.environ['PATH']}",
                                   "PYTHONPATH": str(HERE.parents[1])}) for rank in (0, 1)]
    try:
        wait_for(marker, tasks[0])
        for task in tasks:  # SLURM signals every process of the step
            os.killpg(task.pid, signal.SIGUSR1)
        time.sleep(1.0)
        go.touch()
        results = [finish(task) for task in tasks]
    finally:
        for task in tasks:
            if _group_alive(task.pid):
                os.killpg(task.pid, signal.SIGKILL)
    assert [status for status, _ in results] == [0, 0], "\n".join(out[-3000:] for _, out in results)
    assert "Requeued SLURM job: 4242" in results[0][1]
    assert (tmp_path / "scontrol.calls").read_text().split() == ["requeue", "4242"]
    assert weights(root / "hpc_ckpt_1.ckpt")["global_step"] == 3  # after the step that followed the signal
    assert weights(tmp_path / "run" / "last.ckpt")["global_step"] == 4  # and training went on to its end


@pytest.mark.slow
def test_lightning_s_slurm_requeue_signal_to_the_whole_step_leaves_the_loader_workers_serving(data8, tmp_path):
    """``#SBATCH --signal=USR1@90`` (Lightning's auto-requeue) reaches every process of the step: the loader workers,
    their fork server and multiprocessing's resource tracker too. Before, the workers and the server died of it and
    the run failed (``EOFError``, status 1); the tracker died and was started again with a warning."""
    scontrol = tmp_path / "bin" / "scontrol"
    scontrol.parent.mkdir()
    scontrol.write_text(f"#!/bin/sh\necho \"$@\" >> {tmp_path / 'scontrol.calls'}\n")
    scontrol.chmod(0o755)
    marker, go = tmp_path / "at_step", tmp_path / "go"
    config = job_config(tmp_path, "run")
    job = yaml.safe_load((tmp_path / "run.yaml").read_text())
    job["trainer"]["callbacks"].append({"class_path": f"{__name__}.WaitAtStep",
                                        "init_args": {"step": 3, "marker": str(marker), "go": str(go)}})
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(job))
    slurm = {"SLURM_NTASKS": "1", "SLURM_NTASKS_PER_NODE": "1", "SLURM_NNODES": "1", "SLURM_PROCID": "0",
             "SLURM_LOCALID": "0", "SLURM_NODEID": "0", "SLURM_JOB_ID": "4242", "SLURM_JOB_NAME": "dapm",
             "SLURM_NODELIST": "127.0.0.1"}
    env = {**os.environ, **slurm, "PATH": f"{scontrol.parent}{os.pathsep}{os.environ['PATH']}",
           "PYTHONPATH": str(HERE.parents[1])}
    cmd = [sys.executable, "-m", "dapm_lightning", "fit", *config, "--data.class_path",
           "dapm_lightning.data.datamodules.UAPDDataModule",
           "--data.init_args.root", str(data8), *TINY, "--data.init_args.num_workers", "1",
           "--data.init_args.persistent_workers", "true", "--trainer.default_root_dir", str(tmp_path)]
    process = subprocess.Popen(cmd, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               start_new_session=True)
    wait_for(marker, process)
    os.killpg(process.pid, signal.SIGUSR1)
    time.sleep(1.0)
    go.touch()
    status, out = finish(process)
    assert status == 0, out[-3000:]
    assert "Requeued SLURM job: 4242" in out
    assert (tmp_path / "scontrol.calls").read_text().split() == ["requeue", "4242"]
    assert "resource_tracker" not in out and "Error" not in out, out[-3000:]
    assert weights(tmp_path / "run" / "last.ckpt")["global_step"] == 8
