"""LightningCLI for ``dapm-lightning {fit,validate,test,predict}``."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from lightning.pytorch.cli import LightningCLI

from dapm_lightning.data.datamodules import DAPMDataModule
from dapm_lightning.module import DAPMModule
from dapm_lightning.reliability import ARCHITECTURE_KEYS, SafeCheckpointIO, check_architecture


TRAINER_DEFAULTS = {"plugins": [{"class_path": "dapm_lightning.reliability.SafeCheckpointIO"}]}
"""Checkpoints load with ``weights_only=True`` and a clear error for damaged files."""


class DAPMCLI(LightningCLI):
    """LightningCLI with DAPM's module and any :class:`DAPMDataModule` subclass (``--data.class_path``).

    With ``--ckpt_path``, the checkpoint is read safely (``weights_only``; a damaged file is named) and
    its architecture must match the configuration's: what differs is listed, instead of a shape
    error deep inside ``load_state_dict`` or a silent switch to the checkpoint's settings.
    """

    def _parse_ckpt_path(self) -> None:
        subcommand = self.config.get("subcommand")
        ckpt_path = self.config[subcommand].get("ckpt_path") if subcommand else None
        if ckpt_path and Path(ckpt_path).is_file():
            checkpoint = SafeCheckpointIO().load_checkpoint(ckpt_path, map_location="cpu")
            model_config = self.config[subcommand].get("model")
            current = {k: model_config.get(k) for k in ARCHITECTURE_KEYS} if model_config is not None else {}
            check_architecture(checkpoint.get("hyper_parameters", {}), current, str(ckpt_path))
        super()._parse_ckpt_path()


def run_lightning_cli(args: Sequence[str] | None = None, run: bool = True) -> DAPMCLI:
    """Parse ``args`` (``fit --config FILE ...``) and run the subcommand."""
    return DAPMCLI(DAPMModule, DAPMDataModule, subclass_mode_data=True, seed_everything_default=0,
                   save_config_kwargs={"overwrite": True}, args=list(args) if args is not None else None, run=run,
                   auto_configure_optimizers=False, trainer_defaults=TRAINER_DEFAULTS)
