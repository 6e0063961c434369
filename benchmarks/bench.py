"""``make bench``: model size, compute, latency and memory of DAPM configurations, printed as a table.

``python -m benchmarks.bench`` from the repository root; ``--train-compare`` trains the networks side by side.

Latency ratios are measured in one process, side by side (the machine is noisy; compare ratios).
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch.utils.flop_counter import FlopCounterMode

import dapm_lightning
from benchmarks.callbacks import StepTimer
from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.models import EFFICIENT_NETWORK, PAPER_NETWORK, DAPMConfig, DAPMNet

REPO = Path(__file__).resolve().parents[1]
"""The repository root (``python -m benchmarks.bench`` runs from there)."""

CONFIGS: dict[str, dict[str, Any]] = {
    "efficient": dict(EFFICIENT_NETWORK),
    "paper": dict(PAPER_NETWORK),
}
"""``paper``: configs/paper/*.yaml (Table 7: 42.82 M); ``efficient``: configs/variants/efficient.yaml."""


def _median_latency(fn: Any, x: torch.Tensor, repeats: int) -> float:
    fn(x)  # warm-up
    times = []
    for _ in range(repeats):
        if x.is_cuda:
            torch.cuda.synchronize()
        start = time.perf_counter()
        fn(x)
        if x.is_cuda:
            torch.cuda.synchronize()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


@torch.no_grad()
def measure(config: str, backbone: str, size: int, repeats: int, device: str) -> dict[str, Any]:
    """Measure one configuration in this process."""
    net = DAPMNet(DAPMConfig(backbone=backbone, **CONFIGS[config])).eval().to(device)
    x = torch.rand(1, 3, size, size, device=device)

    def encoder(im: torch.Tensor) -> list[torch.Tensor]:
        return net.encoder((im - net.pixel_mean) / net.pixel_std)

    with FlopCounterMode(display=False) as counter:
        net(x)
    full_gmac = counter.get_total_flops() / 2e9
    with FlopCounterMode(display=False) as counter:
        encoder(x)
    encoder_gmac = counter.get_total_flops() / 2e9
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    latencies_full, latencies_encoder = [], []
    for _ in range(2):  # interleave, so both see the same machine state
        latencies_encoder.append(_median_latency(encoder, x, repeats))
        latencies_full.append(_median_latency(net, x, repeats))
    full, enc = min(latencies_full), min(latencies_encoder)
    if device == "cuda":
        peak_mb = torch.cuda.max_memory_allocated() / 2**20
    else:
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return {"config": config, "device": device, "params_m": sum(p.numel() for p in net.parameters()) / 1e6,
            "gmac": full_gmac, "encoder_gmac": encoder_gmac, "latency_ms": full * 1e3,
            "encoder_latency_ms": enc * 1e3, "ratio": full / enc, "peak_mb": peak_mb}


def sample_bytes(sample: dict[str, Any]) -> int:
    """Bytes of the tensors of one sample (what crosses the worker boundary)."""
    return sum(v.numel() * v.element_size() for v in sample.values() if isinstance(v, torch.Tensor))


def data_pipeline(size: int, images: int, repeats: int) -> list[dict[str, Any]]:
    """Samples/s of one loader worker (decode + augmentation + sample building) and bytes per sample."""
    import tempfile

    from dapm_lightning.data.synthetic import generate_uapd
    from dapm_lightning.data.transforms import train_transform
    from dapm_lightning.data.uapd import UAPDDataset

    with tempfile.TemporaryDirectory() as tmp:
        generate_uapd(tmp, train=images, val=0, size=size, seed=0)
        datasets = {dtype: UAPDDataset(tmp, "train", train_transform(), image_dtype=dtype, augment_seed=0)
                    for dtype in ("uint8", "float32")}
        best = dict.fromkeys(datasets, 0.0)
        for i in range(images):  # warm-up: page cache, first decode
            datasets["uint8"][i]
        for _ in range(repeats):  # rounds alternate between the two, best round kept (noisy machine)
            for dtype, dataset in datasets.items():
                start = time.perf_counter()
                for i in range(len(dataset)):
                    dataset[i]
                best[dtype] = max(best[dtype], len(dataset) / (time.perf_counter() - start))
        return [{"image_dtype": dtype, "samples_per_s": best[dtype],
                 "mb_per_sample": sample_bytes(dict(dataset[0])) / 2**20} for dtype, dataset in datasets.items()]


def train_compare(configs: list[str], *, backbone: str, size: int, steps: int, batch: int, train_images: int,
                  val_images: int, seed: int = 0) -> list[dict[str, Any]]:
    """Train each network configuration as ``dapm-lightning fit`` trains it; speed and accuracy.

    Each configuration is the quickstart recipe (dapm_lightning/configs/quickstart.yaml: its loss, optimizer,
    schedule, augmentation and IGD teacher forcing) with the network settings of :data:`CONFIGS`, trained
    by ``DAPMModule`` in a Lightning ``Trainer`` on the same synthetic data, from the same seed, one after the
    other in this process, then validated with the module's own metrics (toolbox depth in metres, the
    authors' protocol, pose medians). ``s_per_step`` is the median step time (loading excluded).
    """
    import tempfile

    from lightning.pytorch.callbacks import Checkpoint

    from dapm_lightning.data.synthetic import generate_uapd
    from dapm_lightning.training.lightning_cli import run_lightning_cli

    quickstart = Path(dapm_lightning.__file__).resolve().parent / "configs" / "quickstart.yaml"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        generate_uapd(Path(tmp) / "data", train=train_images, val=val_images, size=size, seed=seed)
        for name in configs:
            net = [f"--model.net.{key}={value if isinstance(value, str) else json.dumps(value)}"
                   for key, value in CONFIGS[name].items()]
            cli = run_lightning_cli([
                "--config", str(quickstart), "--seed_everything", str(seed), *net,
                "--model.net.backbone", backbone, "--model.net.pretrained", "false",
                "--model.authors_depth_metrics", "true",
                "--data.class_path", "dapm_lightning.data.datamodules.UAPDDataModule",
                "--data.init_args.root", str(Path(tmp) / "data"), "--data.init_args.batch_size", str(batch),
                "--data.init_args.num_workers", "0", "--data.init_args.seed", str(seed),
                "--trainer.max_steps", str(steps), "--trainer.max_epochs", "-1", "--trainer.limit_val_batches", "0",
                "--trainer.num_sanity_val_steps", "0", "--trainer.logger", "false",
                "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false",
                "--trainer.default_root_dir", str(Path(tmp) / name)], run=False)
            timer = StepTimer()
            trainer = cli.trainer
            trainer.callbacks[:] = [c for c in trainer.callbacks if not isinstance(c, Checkpoint)] + [timer]
            trainer.fit(cli.model, datamodule=cli.datamodule)
            trainer.limit_val_batches = 1.0
            start = time.perf_counter()
            metrics = trainer.validate(cli.model, datamodule=cli.datamodule, verbose=False)[0]
            eval_ms = (time.perf_counter() - start) / val_images * 1e3
            rows.append({"config": name, "params_m": sum(q.numel() for q in cli.model.net.parameters()) / 1e6,
                         "s_per_step": statistics.median(timer.seconds), "eval_ms_per_image": eval_ms,
                         "final_loss": timer.loss,
                         "d1": metrics["val_depth_d1"], "abs_rel": metrics["val_depth_abs_rel"],
                         "rmse_m": metrics["val_depth_rmse"], "authors_d1": metrics["val_depthauthors_d1"],
                         "authors_abs_rel": metrics["val_depthauthors_abs_rel"],
                         "authors_rmse_unit": metrics["val_depthauthors_rmse_unit"],
                         **{f"{k}_median": metrics[f"val_pose_{k}_median"] for k in POSE_KEYS}})
    return rows


def format_table(rows: Sequence[dict[str, Any]], columns: list[tuple[str, str, int, str]]) -> str:
    """``rows`` under a header and a rule, one line each.

    ``columns``: (row key, title, width, number format such as ``.2f`` or ``+.3f``; empty for a left-aligned
    text column).
    """
    def spec(width: int, fmt: str) -> str:
        sign = "+" if fmt.startswith("+") else ""
        return f"{'>' if fmt else '<'}{sign}{width}{fmt.removeprefix('+')}"

    header = "".join(f"{title:{'>' if fmt else '<'}{width}}" for _, title, width, fmt in columns)
    lines = [header, "-" * len(header)]
    lines += ["".join(f"{row[key]:{spec(width, fmt)}}" for key, _, width, fmt in columns) for row in rows]
    return "\n".join(lines)


def print_table(rows: Sequence[dict[str, Any]], columns: list[tuple[str, str, int, str]]) -> None:
    """Print :func:`format_table`."""
    print(format_table(rows, columns))


def print_train_compare(rows: list[dict[str, Any]], args: argparse.Namespace) -> None:
    """Print :func:`train_compare`'s rows as a table."""
    print(f"Training side by side: {args.backbone}, synthetic {args.train_size}x{args.train_size}, "
          f"{args.train_images} train / {args.val_images} val images, {args.train_steps} steps of batch "
          f"{args.train_batch}, {torch.get_num_threads()} CPU threads")
    print_table(rows, [("config", "config", 11, ""), ("params_m", "params M", 9, ".2f"),
                       ("s_per_step", "s/step", 8, ".2f"), ("eval_ms_per_image", "eval ms", 8, ".1f"),
                       ("d1", "d1", 7, ".3f"), ("abs_rel", "AbsRel", 8, ".3f"), ("rmse_m", "RMSE m", 8, ".1f"),
                       ("authors_d1", "A-d1", 7, ".3f"), ("authors_abs_rel", "A-AbsRel", 9, ".3f"),
                       ("authors_rmse_unit", "A-RMS", 7, ".3f"), ("height_median", "h med", 7, ".2f"),
                       ("pitch_median", "p med", 7, ".2f"), ("roll_median", "r med", 7, ".2f"),
                       ("fov_median", "f med", 7, ".2f")])
    print("d1/AbsRel/RMSE m: toolbox protocol in metres; A-*: the authors' protocol (grey levels, sky included, "
          "pooled; RMS in [0, 1] units); medians: pose errors (m, deg).")


def worker_start(method: str, root: str) -> dict[str, Any]:
    """Seconds to the first batch of a loader with 2 workers started by ``method``, in a fresh process.

    Two loaders one after the other: the process's first (a fork server starts with it), then a second one.
    """
    from dapm_lightning.data.datamodules import UAPDDataModule

    times = []
    for _ in range(2):
        module = UAPDDataModule(root=root, batch_size=4, num_workers=2, worker_start_method=method)  # type: ignore[arg-type]
        module.setup("fit")
        start = time.perf_counter()
        next(iter(module.train_dataloader()))
        times.append(time.perf_counter() - start)
    return {"method": method, "first_s": times[0], "next_s": times[1]}


def print_worker_starts(images: int) -> None:
    """Loader workers' start by each method, each in its own process, best of 3 alternating rounds."""
    import tempfile

    from dapm_lightning.data.synthetic import generate_uapd

    with tempfile.TemporaryDirectory() as tmp:
        generate_uapd(tmp, train=images, val=2, size=64, seed=0, workers=1)
        best: dict[str, dict[str, Any]] = {}
        for _ in range(3):
            for method in ("fork", "forkserver", "spawn"):
                cmd = [sys.executable, "-m", "benchmarks.bench", "--worker-start", method, "--root", tmp]
                result = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=REPO)
                row = json.loads(result.stdout.strip().splitlines()[-1])
                kept = best.setdefault(method, row)
                kept.update({k: min(kept[k], row[k]) for k in ("first_s", "next_s")})
    print("\nLoader workers' start (2 workers, 64x64): seconds to the first batch, best of 3 fresh processes")
    print(f"{'start method':<14}{'first loader':>13}{'next loader':>12}{'first / fork':>14}")
    for method, row in best.items():
        ratio = row["first_s"] / best["fork"]["first_s"]
        print(f"{method:<14}{row['first_s']:>13.2f}{row['next_s']:>12.2f}{ratio:>14.1f}")
    print("forkserver (the default) pays the server's start (PyTorch and the data code imported) once per process; "
          "its next loaders start as fork's do (docs/data.md).")


def main(argv: list[str] | None = None) -> None:
    """Run every configuration in its own process (clean peak memory) and print a table."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--backbone", default="resnet50")
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--data-images", type=int, default=24, help="synthetic files for the data-pipeline benchmark")
    parser.add_argument("--train-compare", action="store_true",
                        help="instead: train paper and efficient side by side on synthetic data (speed, accuracy)")
    parser.add_argument("--train-steps", type=int, default=300)
    parser.add_argument("--train-size", type=int, default=64)
    parser.add_argument("--train-batch", type=int, default=8)
    parser.add_argument("--train-images", type=int, default=400)
    parser.add_argument("--val-images", type=int, default=100)
    parser.add_argument("--json", help="also write the rows to this file")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    parser.add_argument("--worker-start", help=argparse.SUPPRESS)
    parser.add_argument("--root", help=argparse.SUPPRESS)
    parser.add_argument("--device", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(measure(args.one, args.backbone, args.size, args.repeats, args.device)))
        return
    if args.worker_start:
        print(json.dumps(worker_start(args.worker_start, args.root)))
        return
    if args.train_compare:
        rows = train_compare(list(CONFIGS), backbone=args.backbone, size=args.train_size, steps=args.train_steps,
                             batch=args.train_batch, train_images=args.train_images, val_images=args.val_images)
        print_train_compare(rows, args)
        if args.json:
            with open(args.json, "w") as f:
                json.dump(rows, f, indent=1)
        return
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    rows = []
    for device in devices:
        for config in CONFIGS:
            repeats = args.repeats if (config == "efficient" or device == "cuda") else 1
            cmd = [sys.executable, "-m", "benchmarks.bench", "--one", config, "--backbone", args.backbone,
                   "--size", str(args.size), "--repeats", str(repeats), "--device", device]
            result = subprocess.run(cmd, check=True, capture_output=True, text=True, cwd=REPO)
            rows.append(json.loads(result.stdout.strip().splitlines()[-1]))
    print(f"DAPM forward, {args.backbone}, {args.size}x{args.size}, batch 1, {torch.get_num_threads()} CPU threads")
    print_table(rows, [("config", "config", 16, ""), ("device", "device", 7, ""), ("params_m", "params M", 9, ".2f"),
                       ("gmac", "GMAC", 8, ".1f"), ("encoder_gmac", "enc GMAC", 9, ".1f"),
                       ("latency_ms", "full ms", 10, ".0f"), ("encoder_latency_ms", "enc ms", 9, ".0f"),
                       ("ratio", "ratio", 7, ".2f"), ("peak_mb", "peak MB", 9, ".0f")])
    print("ratio = full model latency / encoder-alone latency (same process). "
          "Paper (Table 7): 42.82 M params; the paper row within 1 %; efficient target: ratio <= 1.3.")
    print("peak MB: CPU = process max RSS (model + activations); CUDA = max allocated.")
    torch.set_num_threads(1)  # one loader worker = one core
    print(f"\nUAPD training pipeline, one worker ({args.size}x{args.size}: PNG decode + colour jitter, noise, "
          "pose-aware flip + sample)")
    print(f"{'image dtype':<14}{'samples/s':>10}{'MB/sample':>11}   (best of 4 alternating rounds)")
    for row in data_pipeline(args.size, args.data_images, repeats=4):
        print(f"{row['image_dtype']:<14}{row['samples_per_s']:>10.1f}{row['mb_per_sample']:>11.2f}")
    print("Authors' loader: 6.9 samples/s per worker, 90 MB/sample (one-hot maps). Targets: >= 70 and <= 2 MB. "
          "Data modules ship uint8 by default.")
    print_worker_starts(images=16)


if __name__ == "__main__":
    main()
