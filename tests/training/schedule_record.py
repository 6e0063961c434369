"""A callback for the DDP tests: each process writes the learning rate, the time a
:class:`~dapm_lightning.training.module.TimeBudgetLR` counted and the IGD share after every training batch, and its
network's parameter digest when training ends; ``rank1_delay`` seconds of sleep on rank 1 in its first step, before the
optimiser steps, skew that process's clock."""

import json
import time
from pathlib import Path

import lightning as L
from weights_digest import parameters_digest


class ScheduleRecord(L.Callback):
    """Writes ``FOLDER/rank{global_rank}.json``: ``{"steps": [[lr, seconds, share], ...], "digest": ...}``."""

    def __init__(self, folder: str, rank1_delay: float = 0.0) -> None:
        self.folder, self.rank1_delay, self.steps = Path(folder), rank1_delay, []

    def on_before_optimizer_step(self, trainer, pl_module, optimizer):
        if trainer.global_rank == 1 and self.rank1_delay and not self.steps:
            time.sleep(self.rank1_delay)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        scheduler = trainer.lr_scheduler_configs[0].scheduler
        self.steps.append([trainer.optimizers[0].param_groups[0]["lr"], getattr(scheduler, "seconds", None),
                           pl_module.igd_predicted_share])

    def on_train_end(self, trainer, pl_module):
        self.folder.mkdir(parents=True, exist_ok=True)
        record = {"steps": self.steps, "digest": parameters_digest(pl_module.net.named_parameters())}
        (self.folder / f"rank{trainer.global_rank}.json").write_text(json.dumps(record))
