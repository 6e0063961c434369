"""LightningCLI for ``dapm-lightning {fit,validate,test,predict}``."""

from __future__ import annotations

from collections.abc import Sequence

from lightning.pytorch.cli import LightningCLI

from dapm_lightning.data.datamodules import DAPMDataModule
from dapm_lightning.module import DAPMModule


class DAPMCLI(LightningCLI):
    """LightningCLI with DAPM's module and any :class:`DAPMDataModule` subclass (``--data.class_path``)."""


def run_lightning_cli(args: Sequence[str] | None = None, run: bool = True) -> DAPMCLI:
    """Parse ``args`` (``fit --config FILE ...``) and run the subcommand."""
    return DAPMCLI(DAPMModule, DAPMDataModule, subclass_mode_data=True, seed_everything_default=0,
                   save_config_kwargs={"overwrite": True}, args=list(args) if args is not None else None, run=run,
                   auto_configure_optimizers=False)
