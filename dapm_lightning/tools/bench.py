"""``make bench``: model size, compute, latency and memory of DAPM configurations, printed as a table.

Latency ratios are measured in one process, side by side (the machine is noisy; compare ratios).
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import statistics
import subprocess
import sys
import time
from typing import Any

import torch
from torch.utils.flop_counter import FlopCounterMode

from dapm_lightning.models import EFFICIENT_NETWORK, PAPER_NETWORK, DAPMConfig, DAPMNet

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
    """Train each network configuration for the same steps on the same batches; speed and accuracy.

    One process, the configurations interleaved step by step (each step, every configuration trains on
    the same batch, timed on its own), so a noisy machine slows them alike. Same initial seed and loss
    (the paper's: Eq. 17 in the authors' normalised log space); AdamW 1e-3, 10 % warm-up then cosine;
    the IGD fed the predicted pose (no teacher forcing). Accuracy on the validation split: toolbox
    depth metrics in metres, the authors' protocol, pose medians.
    """
    import tempfile

    from torch.utils.data import DataLoader

    from dapm_lightning.data.sample import depth_masks
    from dapm_lightning.data.synthetic import generate_uapd
    from dapm_lightning.data.transforms import train_transform
    from dapm_lightning.data.uapd import UAPDDataset
    from dapm_lightning.metrics import AuthorsDepthMetrics, DepthMetrics, PoseMetrics
    from dapm_lightning.training.loss import DAPMLoss, LossConfig
    from dapm_lightning.training.module import warmup_cosine

    with tempfile.TemporaryDirectory() as tmp:
        generate_uapd(tmp, train=train_images, val=val_images, size=size, seed=seed)
        train_set = UAPDDataset(tmp, "train", train_transform(), augment_seed=seed)
        val_set = UAPDDataset(tmp, "val")
        runs: dict[str, dict[str, Any]] = {}
        for name in configs:
            torch.manual_seed(seed)
            net = DAPMNet(DAPMConfig(backbone=backbone, **CONFIGS[name])).train()
            optimizer = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=0.01)
            runs[name] = {"net": net, "optimizer": optimizer, "seconds": 0.0, "loss": math.nan,
                          "criterion": DAPMLoss(LossConfig(depth_space="log_norm"), net.config.igd),
                          "schedule": torch.optim.lr_scheduler.LambdaLR(
                              optimizer, lambda k: warmup_cosine(k, steps, 0.1, 0.02))}
        loader = DataLoader(train_set, batch_size=batch, shuffle=True, drop_last=True,
                            generator=torch.Generator().manual_seed(seed))
        step = 0
        while step < steps:
            for sample in loader:
                sky, valid = depth_masks(sample["depth"])
                targets = {**sample, "sky": sky, "valid": valid}
                for run in runs.values():
                    start = time.perf_counter()
                    loss = run["criterion"](run["net"](sample["image"].float()), targets)["total"]
                    run["optimizer"].zero_grad()
                    loss.backward()
                    run["optimizer"].step()
                    run["schedule"].step()
                    run["seconds"] += time.perf_counter() - start
                    run["loss"] = float(loss.detach())
                step += 1
                if step % 10 == 0:
                    print(f"step {step}/{steps}: " + ", ".join(f"{k} {r['seconds'] / step:.2f} s/step loss "
                                                              f"{r['loss']:.3f}" for k, r in runs.items()),
                          file=sys.stderr, flush=True)
                if step == steps:
                    break
        rows = []
        for name, run in runs.items():
            net = run["net"].eval()
            depth, authors, pose = DepthMetrics(), AuthorsDepthMetrics(), PoseMetrics()
            start = time.perf_counter()
            with torch.no_grad():
                for sample in DataLoader(val_set, batch_size=batch):
                    out = net(sample["image"].float())
                    depth.update(out.depth_m, sample["depth"])
                    authors.update(out.depth_m, sample["depth"])
                    pose.update(out.pose_physical, sample["pose"])
            eval_ms = (time.perf_counter() - start) / len(val_set) * 1e3
            d, a, p = depth.compute(), authors.compute(), pose.compute()
            rows.append({"config": name, "params_m": sum(q.numel() for q in net.parameters()) / 1e6,
                         "s_per_step": run["seconds"] / steps, "eval_ms_per_image": eval_ms,
                         "final_loss": run["loss"], "d1": float(d["d1"]), "abs_rel": float(d["abs_rel"]),
                         "rmse_m": float(d["rmse"]), "authors_d1": float(a["d1"]),
                         "authors_abs_rel": float(a["abs_rel"]), "authors_rmse_unit": float(a["rmse_unit"]),
                         **{f"{k}_median": float(p[f"{k}_median"]) for k in ("height", "pitch", "roll", "fov")}})
    return rows


def print_table(rows: list[dict[str, Any]], columns: list[tuple[str, str, int, str]]) -> None:
    """Print ``rows`` under a header.

    ``columns``: (row key, title, width, number format such as ``.2f``; empty for a left-aligned text column).
    """
    header = "".join(f"{title:{'>' if fmt else '<'}{width}}" for _, title, width, fmt in columns)
    print(header)
    print("-" * len(header))
    for row in rows:
        print("".join(f"{row[key]:{'>' if fmt else '<'}{width}{fmt}}" for key, _, width, fmt in columns))


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
    parser.add_argument("--device", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        print(json.dumps(measure(args.one, args.backbone, args.size, args.repeats, args.device)))
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
            cmd = [sys.executable, "-m", "dapm_lightning.tools.bench", "--one", config, "--backbone", args.backbone,
                   "--size", str(args.size), "--repeats", str(repeats), "--device", device]
            result = subprocess.run(cmd, check=True, capture_output=True, text=True)
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


if __name__ == "__main__":
    main()
