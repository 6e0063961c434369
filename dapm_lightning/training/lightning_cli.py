"""LightningCLI for ``dapm-lightning {fit,validate,test,predict}``."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
from lightning.pytorch.cli import LightningCLI, SaveConfigCallback
from lightning.pytorch.utilities import rank_zero_info

from dapm_lightning.data.datamodules import DAPMDataModule
from dapm_lightning.models.config import DAPMConfig
from dapm_lightning.training.checkpointing import SafeCheckpointIO, check_architecture, find_last_checkpoint
from dapm_lightning.training.module import DAPMModule

TRAINER_DEFAULTS = {"plugins": [{"class_path": "dapm_lightning.training.checkpointing.SafeCheckpointIO"}]}
"""Checkpoints load with ``weights_only=True`` and a clear error for damaged files."""


class SaveConfigOfRun(SaveConfigCallback):
    """Saves the resolved ``config.yaml`` into the run's log folder for fit, validate and test.

    Not for predict: its outputs go to the prediction writer's folder, and without a logger Lightning's
    log folder would be the current directory.
    """

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        if stage != "predict":
            super().setup(trainer, pl_module, stage)


class DAPMCLI(LightningCLI):
    """LightningCLI with DAPM's module and any :class:`DAPMDataModule` subclass (``--data.class_path``).

    With ``--ckpt_path``, the checkpoint is read safely (``weights_only``; a damaged file is named).
    ``validate``, ``test`` and ``predict`` then build the checkpoint's own model (its saved settings
    override the configuration's). ``fit`` resumes only into the same architecture: what differs is
    listed with the fix, instead of a shape error deep inside ``load_state_dict`` or a silent switch
    to the checkpoint's settings.
    """

    def _parse_ckpt_path(self) -> None:
        subcommand = self.config.get("subcommand")
        ckpt_path = self.config[subcommand].get("ckpt_path") if subcommand else None
        if ckpt_path == "last":
            ckpt_path = self._resolve_last(self.config[subcommand])
        if ckpt_path and Path(ckpt_path).is_file():
            checkpoint = SafeCheckpointIO().load_checkpoint(ckpt_path, map_location="cpu")  # names a damaged file
            saved = checkpoint.get("hyper_parameters", {}).get("net")
            net = self.config[subcommand].get("model", {}).get("net")
            if subcommand == "fit" and saved is not None and net is not None:
                current = DAPMConfig.from_dict(net.as_dict() if hasattr(net, "as_dict") else dict(net))
                check_architecture(saved, current, str(ckpt_path))
        super()._parse_ckpt_path()

    @staticmethod
    def _resolve_last(config: Any) -> str:
        """``--ckpt_path last``: the newest ``last.ckpt`` under the run's folders, across its log versions.

        The folders: ``trainer.default_root_dir``, every logger's ``save_dir`` and every callback's
        ``dirpath``. With none there, ``"last"`` stays as it is: Lightning warns and starts from scratch
        (the first submission of a job that is always launched with ``--ckpt_path last``).
        """
        trainer = config.get("trainer") or {}
        roots = [trainer.get("default_root_dir") or "."]
        for entry in _as_list(trainer.get("logger")) + _as_list(trainer.get("callbacks")):
            init_args = entry.get("init_args") if hasattr(entry, "get") else None
            for key in ("save_dir", "dirpath"):
                if init_args is not None and init_args.get(key):
                    roots.append(init_args.get(key))
        found = find_last_checkpoint(roots)
        if found is None:
            return "last"
        rank_zero_info(f"--ckpt_path last: resuming from {found}")
        config["ckpt_path"] = str(found)
        return str(found)


def _as_list(value: Any) -> list[Any]:
    return list(value) if isinstance(value, (list, tuple)) else [] if value in (None, False, True) else [value]


def run_lightning_cli(args: Sequence[str] | None = None, run: bool = True) -> DAPMCLI:
    """Parse ``args`` (``fit --config FILE ...``) and run the subcommand."""
    return DAPMCLI(DAPMModule, DAPMDataModule, subclass_mode_data=True, seed_everything_default=0,
                   save_config_callback=SaveConfigOfRun, save_config_kwargs={"overwrite": True},
                   args=list(args) if args is not None else None, run=run, auto_configure_optimizers=False,
                   trainer_defaults=TRAINER_DEFAULTS)
