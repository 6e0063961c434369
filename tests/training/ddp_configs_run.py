"""Under torchrun (2 processes, gloo): fit every paper config and every ablation and variant overlay for 2 steps
in one process group, then report, per config, the steps done and the Lightning warnings about unsynced logging.

Usage: python -m torch.distributed.run --nproc_per_node 2 ddp_configs_run.py OUT.json DATA POTSDAM [CONFIG ...]
A CONFIG is `paper/X.yaml`, or `ablations/Y.yaml` / `variants/Z.yaml` (stacked on paper/uapd_dapm.yaml, as the
README says).
"""

import json
import resource
import shutil
import sys
import warnings
from pathlib import Path

import torch
import torch.distributed as dist

from dapm_lightning.training.checkpointing import find_last_checkpoint
from dapm_lightning.training.lightning_cli import run_lightning_cli

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
GPU_ONLY = ["--trainer.accelerator", "cpu", "--trainer.devices", "2", "--trainer.sync_batchnorm", "false",
            "--trainer.precision", "32-true", "--model.net.pretrained", "false"]
# 2 steps inside the first epoch (12 images, 3 batches per process): DDP checks at its second step that every
# parameter got a gradient; no validation (validation under DDP has its own test); the configs' LastCheckpoint
# (every 1000 steps) writes last.ckpt when the fit ends; loader workers are covered by the data and resume tests
SMALL_RUN = ["--trainer.max_steps", "2", "--trainer.limit_val_batches", "0",
             "--trainer.enable_progress_bar", "false", "--data.init_args.batch_size", "2",
             "--data.init_args.eval_batch_size", "2", "--data.init_args.num_workers", "0"]


def stack(config: str) -> list[str]:
    files = [CONFIGS / config] if config.startswith("paper/") else [CONFIGS / "paper" / "uapd_dapm.yaml",
                                                                    CONFIGS / config]
    return [arg for path in files for arg in ("--config", str(path))]


if __name__ == "__main__":
    out, data, potsdam, configs = sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:]
    results = {}
    for config in configs:
        root = ["--data.init_args.root", potsdam, "--data.init_args.crop_size", "32"] if "potsdam" in config else [
            "--data.init_args.root", data]
        runs = Path(out).parent / "runs"
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cli = run_lightning_cli(["fit", *stack(config), *GPU_ONLY, *SMALL_RUN, *root,
                                     "--trainer.default_root_dir", str(runs)])
        # the paper configs write a last.ckpt of about 0.5 GB each (42.6 M parameters with AdamW state) under the
        # run's folder (their logs and checkpoints follow trainer.default_root_dir): remove it before the next
        # config, or the run needs ~9 GB of disk
        dist.barrier()
        last = find_last_checkpoint([runs])
        last_step = torch.load(last, map_location="cpu", weights_only=True, mmap=True)["global_step"] if last else None
        dist.barrier()
        if dist.get_rank() == 0:
            shutil.rmtree(runs, ignore_errors=True)
        unsynced = [str(w.message)[:200] for w in caught if "sync_dist" in str(w.message)]
        results[config] = {"global_step": cli.trainer.global_step, "world_size": cli.trainer.world_size,
                           "last_ckpt_step": last_step,
                           "unsynced": unsynced,
                           "find_unused": bool(getattr(cli.trainer.strategy, "_ddp_kwargs", {})
                                               .get("find_unused_parameters", False)),
                           "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}
    if dist.get_rank() == 0:
        Path(out).write_text(json.dumps(results, indent=1))
