"""Fit through the DAPM CLI in a subprocess, optionally pausing at a step (for a test to signal it),
and save the final weights. Usage: python resume_run.py WEIGHTS.pt [CLI fit args without 'fit'].
Environment: PAUSE_AT="STEP,MARKER_FILE[,WHERE[,RANK]]" pauses until this process is told to stop (SIGTERM,
SIGINT) or 120 s, after writing MARKER_FILE: WHERE "train" (the default) after training step STEP, "batch" after
training batch STEP (counted over the run, from 1: a micro-batch under gradient accumulation), "val" in the
validation after STEP after its first batch, "valend" at the end of that validation before its metrics are gathered
across processes; with RANK, only that process pauses (the others run on, into the gathering).
RECORD_IMAGES=PREFIX writes PREFIX<rank>.json: per epoch, a digest of every training image as the model received
it (after augmentation), and PREFIX<rank>_names.json: per epoch, the names of the images trained, in order, and
PREFIX<rank>_validations.json: the step and val_loss of each validation that ran to its end (not the sanity check).
SLOW_EXIT=SECONDS: the main process waits that long at exit (as one with more to write than the others would).
SIGUSR1 prints every thread's stack (every process of the run registers it: a test that waits too long sends it to
the whole process group before killing it)."""

import atexit
import faulthandler
import hashlib
import json
import os
import signal
import sys
import time
from pathlib import Path

import lightning as L
import torch

from dapm_lightning.training.lightning_cli import run_lightning_cli
from dapm_lightning.training.signals import sigterm_received


class PauseAt(L.Callback):
    def __init__(self, step: int, marker: str, where: str = "train", rank: int | None = None) -> None:
        self.step, self.marker, self.where, self.rank = step, Path(marker), where, rank

    def pause(self, trainer, where):
        count = trainer.fit_loop.epoch_loop.batch_progress.total.processed if where == "batch" else trainer.global_step
        if where != self.where or count != self.step or trainer.sanity_checking:
            return
        if self.rank is not None and trainer.global_rank != self.rank:
            return
        self.marker.write_text(str(trainer.global_step))
        deadline, agreement = time.time() + 120, getattr(trainer.lightning_module, "sigterm", None)
        while not sigterm_received(trainer, agreement) and time.time() < deadline:
            time.sleep(0.05)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        self.pause(trainer, "train")
        self.pause(trainer, "batch")

    def on_validation_batch_end(self, trainer, pl_module, outputs, batch, batch_idx, dataloader_idx=0):
        if batch_idx == 0:
            self.pause(trainer, "val")

    def on_validation_epoch_end(self, trainer, pl_module):  # callbacks' hook runs before the module's metric sync
        self.pause(trainer, "valend")


class RecordImages(L.Callback):
    def __init__(self, prefix: str) -> None:
        self.prefix, self.seen, self.names, self.validations = prefix, {}, {}, []

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx):
        epoch = self.seen.setdefault(str(trainer.current_epoch), {})
        for name, image in zip(batch["name"], batch["image"]):
            epoch[name] = hashlib.sha1(image.cpu().numpy().tobytes()).hexdigest()
        self.names.setdefault(str(trainer.current_epoch), []).extend(batch["name"])

    def on_validation_end(self, trainer, pl_module):
        if not trainer.sanity_checking:
            self.validations.append([trainer.global_step, float(trainer.callback_metrics["val_loss"])])
            path = Path(f"{self.prefix}{trainer.global_rank}_validations.json")  # also in a run stopped later
            path.write_text(json.dumps(self.validations))

    def on_train_end(self, trainer, pl_module):
        Path(f"{self.prefix}{trainer.global_rank}.json").write_text(json.dumps(self.seen))
        Path(f"{self.prefix}{trainer.global_rank}_names.json").write_text(json.dumps(self.names))


if __name__ == "__main__":
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # DDP processes run this script too; workers inherit it
    if os.environ.get("SLOW_EXIT") and "LOCAL_RANK" not in os.environ:  # the main process: slow to exit
        atexit.register(time.sleep, float(os.environ["SLOW_EXIT"]))
    weights, args = sys.argv[1], sys.argv[2:]
    ckpt = None
    if "--ckpt_path" in args:
        i = args.index("--ckpt_path")
        ckpt = args[i + 1]
        del args[i:i + 2]
    cli = run_lightning_cli(args, run=False)
    if os.environ.get("PAUSE_AT"):
        step, marker, *where = os.environ["PAUSE_AT"].split(",")
        rank = int(where[1]) if len(where) > 1 else None
        cli.trainer.callbacks.append(PauseAt(int(step), marker, where[0] if where else "train", rank))
    if os.environ.get("RECORD_IMAGES"):
        cli.trainer.callbacks.append(RecordImages(os.environ["RECORD_IMAGES"]))
    cli.trainer.fit(cli.model, datamodule=cli.datamodule, ckpt_path=ckpt)
    if cli.trainer.is_global_zero:  # under DDP, rank 0's (BatchNorm running statistics are per process)
        torch.save({"state_dict": cli.model.state_dict(), "global_step": cli.trainer.global_step}, weights)
