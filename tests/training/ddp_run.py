"""Run the DAPM CLI (possibly under DDP, which re-launches this file) and dump rank 0's metrics as JSON.

Usage: python tests/training/ddp_run.py OUT.json SUBCOMMAND [CLI args...]
"""

import json
import sys

from dapm_lightning.training.lightning_cli import run_lightning_cli

if __name__ == "__main__":
    out_path, args = sys.argv[1], sys.argv[2:]
    cli = run_lightning_cli(args)
    if cli.trainer.is_global_zero:
        metrics = {k: float(v) for k, v in cli.trainer.callback_metrics.items()}
        checkpoint = getattr(cli.trainer.checkpoint_callback, "last_model_path", "")
        with open(out_path, "w") as handle:
            json.dump({"metrics": metrics, "global_step": cli.trainer.global_step, "last": checkpoint}, handle)
