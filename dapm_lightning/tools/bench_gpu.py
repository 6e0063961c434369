"""``make bench-gpu``: the GPU kit. One command turns the first GPU into figures (docs/gpu.md).

``python -m dapm_lightning.tools.bench_gpu [--out outputs/bench_gpu]`` renders its own synthetic data
(512² and 256², every core), then measures, in one process:

1. **loader**: loader-only samples/s at 512² (decode + augmentation, all workers, nothing on the device);
2. **train**: the paper network and the efficient variant, ``--train-steps`` steps of batch 8 at 512², with
   ``32-true`` and ``bf16-mixed``, channels-last off and on: s/step, images/s, peak device memory and the
   share of step time spent waiting on the loader (stall); every loss finite;
3. **bf16 vs fp32**: the loss curves of the same seed and batches, their largest relative gap;
4. **inference** at 512², batch 1 and 16: eager fp32 and bf16, channels-last, ``torch.compile`` (CUDA graphs
   on a GPU: ``mode="reduce-overhead"``), onnxruntime (its CUDA provider where the wheel has one): FPS and
   the ratio to the paper's Table 7 (24.1 FPS);
5. **learning**: the efficient variant trained for the rest of ``--budget-s`` at 256² on a fixed synthetic
   split: val d1 and pose medians at the end.

It writes ``bench_gpu.json`` and ``bench_gpu.md`` to ``--out``. ``--device cpu --tiny`` runs the same path with
ResNet-18 networks, 64² images and a few steps (about a minute on 2 cores): the kit is tested before a GPU
exists (tests/tools/test_bench_gpu.py). Timings are only comparable within one run.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import resource
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import DataLoader

from dapm_lightning.data.datamodules import collate_samples
from dapm_lightning.data.sample import depth_masks
from dapm_lightning.data.synthetic import generate_uapd, is_current
from dapm_lightning.data.transforms import train_transform
from dapm_lightning.data.uapd import UAPDDataset
from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.metrics import DepthMetrics, PoseMetrics
from dapm_lightning.models import EFFICIENT_NETWORK, PAPER_NETWORK, DAPMConfig, DAPMNet
from dapm_lightning.training.loss import DAPMLoss, LossConfig
from dapm_lightning.training.module import warmup_cosine

TABLE7_FPS = 24.1
"""The paper's Table 7: DAPM at 512², fp32, on their GPU."""

NETWORKS = {"paper": dict(PAPER_NETWORK), "efficient": dict(EFFICIENT_NETWORK)}
NARROW = {"decoder_channels": 16, "head_channels": 8, "igd_channels": 4, "pose_hidden": 16, "pose_projection": 16}
"""``--tiny``: each network's structure, a few channels wide (the kit's test on a CPU)."""


@dataclass(frozen=True)
class Scale:
    """Sizes of one kit run: the GPU's (default) or ``--tiny`` (the same path on a CPU in about a minute)."""

    backbone: str = "resnet50"
    size: int = 512
    learn_size: int = 256
    train_images: int = 256
    learn_train: int = 2000
    learn_val: int = 200
    batch: int = 8
    infer_batches: tuple[int, ...] = (1, 16)
    infer_iters: int = 30
    loader_batches: int = 40
    warmup_steps: int = 10
    compile_backend: str = "inductor"
    narrow: bool = False

    @staticmethod
    def tiny() -> Scale:
        """Narrow ResNet-18 networks at 64²; ``torch.compile`` traces the network (dynamo), no code generation."""
        return Scale(backbone="resnet18", size=64, learn_size=64, train_images=16, learn_train=32, learn_val=8,
                     batch=2, infer_batches=(1, 2), infer_iters=2, loader_batches=4, warmup_steps=1,
                     compile_backend="eager", narrow=True)


def sync(device: torch.device) -> None:
    """Wait for the device (timings end here)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def peak_memory_mb(device: torch.device) -> float:
    """Peak allocated device memory since the last reset (CUDA), or the process's peak RSS (CPU), MiB."""
    if device.type == "cuda":
        return torch.cuda.max_memory_allocated(device) / 2**20
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def reset_peak_memory(device: torch.device) -> None:
    """Start a new peak of :func:`peak_memory_mb` (CUDA)."""
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)


def autocast(device: torch.device, precision: str) -> contextlib.AbstractContextManager[Any]:
    """Lightning's ``bf16-mixed``: bf16 autocast; ``32-true``: nothing."""
    if precision == "bf16-mixed":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return contextlib.nullcontext()


def make_net(name: str, scale: Scale, device: torch.device, channels_last: bool, seed: int = 0) -> DAPMNet:
    """One of :data:`NETWORKS`, seeded, untrained (no pretrained weights: the node may be offline)."""
    torch.manual_seed(seed)
    settings = {**NETWORKS[name], **(NARROW if scale.narrow else {})}
    net = DAPMNet(DAPMConfig(backbone=scale.backbone, pretrained=False, **settings)).to(device)
    return net.to(memory_format=torch.channels_last) if channels_last else net  # type: ignore[call-overload]


def render(root: Path, size: int, train: int, val: int, workers: int) -> Path:
    """The kit's synthetic data (kept between runs: same settings, same bytes)."""
    settings = dict(train=train, val=val, size=(size, size), seed=0, families=None, effects=True, distortion=False)
    threads = torch.get_num_threads()  # rendering in this process sets one thread
    if not is_current(root, **settings):
        generate_uapd(root, train=train, val=val, size=size, seed=0, workers=workers)
    torch.set_num_threads(threads)
    return root


def loader(root: Path, split: str, batch: int, workers: int, device: torch.device, *, train: bool = True,
           seed: int = 0) -> DataLoader[dict[str, Any]]:
    """The training loader as the data modules build it: uint8 images, seeded augmentation and order."""
    dataset = UAPDDataset(root, split, train_transform() if train else None, image_dtype="uint8",
                          augment_seed=seed if train else None)
    return DataLoader(dataset, batch_size=batch, shuffle=train, drop_last=train, num_workers=workers,
                      collate_fn=collate_samples, pin_memory=device.type == "cuda",
                      persistent_workers=workers > 0, generator=torch.Generator().manual_seed(seed))


def endless(data: DataLoader[dict[str, Any]]) -> Iterator[dict[str, Any]]:
    """The loader's batches, epoch after epoch."""
    while True:
        yield from data


def to_device(batch: dict[str, Any], device: torch.device, channels_last: bool = False) -> dict[str, Any]:
    """The batch on the device, the uint8 image as float in [0, 1] (as ``DAPMModule`` does it)."""
    moved = {k: v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
    image = moved["image"].float().div_(255.0)
    moved["image"] = image.contiguous(memory_format=torch.channels_last) if channels_last else image
    return moved


def loader_speed(root: Path, batch: int, workers: int, batches: int, device: torch.device) -> dict[str, Any]:
    """Samples/s of the training loader alone (all workers; nothing on the device), after one warm-up batch."""
    batches_seen = endless(loader(root, "train", batch, workers, device))
    next(batches_seen)
    start = time.perf_counter()
    for _ in range(batches):
        next(batches_seen)
    seconds = time.perf_counter() - start
    return {"workers": workers, "batch": batch, "batches": batches, "samples_per_s": batches * batch / seconds}


def train_step_fn(net: DAPMNet, criterion: DAPMLoss, optimizer: torch.optim.Optimizer, device: torch.device,
                  precision: str) -> Callable[[dict[str, Any]], dict[str, float]]:
    """One optimiser step on a batch (autocast as Lightning's precision plugin does); the loss terms."""
    def step(batch: dict[str, Any]) -> dict[str, float]:
        sky, valid = depth_masks(batch["depth"])
        with autocast(device, precision):
            out = net(batch["image"])
            terms = criterion(out, {**batch, "sky": sky, "valid": valid})
        optimizer.zero_grad(set_to_none=True)
        terms["total"].backward()
        optimizer.step()
        return {k: float(v.detach()) for k, v in terms.items()}  # .item(): also waits for the device

    return step


def train_run(name: str, precision: str, channels_last: bool, data: DataLoader[dict[str, Any]], scale: Scale,
              steps: int, device: torch.device) -> dict[str, Any]:
    """``steps`` optimiser steps (after ``scale.warmup_steps`` untimed ones); wait and compute timed apart."""
    net = make_net(name, scale, device, channels_last).train()
    criterion = DAPMLoss(LossConfig(depth_space="log_norm"), net.config.igd)  # the paper configs' loss
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-4, weight_decay=0.01)
    step = train_step_fn(net, criterion, optimizer, device, precision)
    batches = endless(data)
    losses: list[float] = []
    finite = True
    for _ in range(scale.warmup_steps):
        losses.append(step(to_device(next(batches), device, channels_last))["total"])
    sync(device)
    reset_peak_memory(device)
    wait = compute = 0.0
    for _ in range(steps):
        start = time.perf_counter()
        batch = next(batches)
        fetched = time.perf_counter()
        terms = step(to_device(batch, device, channels_last))
        sync(device)
        wait, compute = wait + fetched - start, compute + time.perf_counter() - fetched
        losses.append(terms["total"])
        finite = finite and all(math.isfinite(v) for v in terms.values())
    seconds = wait + compute
    return {"network": name, "precision": precision, "channels_last": channels_last, "steps": steps,
            "batch": scale.batch, "s_per_step": seconds / steps, "images_per_s": steps * scale.batch / seconds,
            "stall_share": wait / seconds, "peak_memory_mb": peak_memory_mb(device), "finite": finite,
            "losses": losses}


def curve_gap(reference: list[float], other: list[float], window: int = 10) -> dict[str, float]:
    """Largest relative gap of two loss curves, step by step and of their ``window``-step running means."""
    raw = max(abs(a - b) / max(abs(a), 1e-12) for a, b in zip(reference, other))
    window = max(1, min(window, len(reference)))

    def smooth(values: list[float]) -> list[float]:
        return [statistics.fmean(values[k:k + window]) for k in range(len(values) - window + 1)]

    smoothed = max(abs(a - b) / max(abs(a), 1e-12) for a, b in zip(smooth(reference), smooth(other)))
    return {"max_relative_gap": raw, "max_relative_gap_smoothed": smoothed, "window": window}


def _timed_fps(run: Callable[[], Any], batch: int, iters: int, device: torch.device) -> float:
    for _ in range(3):
        run()
    sync(device)
    start = time.perf_counter()
    for _ in range(iters):
        run()
    sync(device)
    return batch * iters / (time.perf_counter() - start)


def inference_variants(name: str, scale: Scale, batch: int, device: torch.device, work: Path, *, compile: bool,
                       onnx: bool) -> dict[str, Callable[[], Any]]:
    """Each inference variant of one network and batch as a call that returns the depth in metres."""
    image = torch.rand(batch, 3, scale.size, scale.size, generator=torch.Generator().manual_seed(0)).to(device)
    image_cl = image.contiguous(memory_format=torch.channels_last)
    net = make_net(name, scale, device, False).eval()
    net_cl = make_net(name, scale, device, True).eval()
    variants: dict[str, Callable[[], Any]] = {
        "eager fp32": lambda: net(image).depth_m,
        "eager bf16": lambda: _bf16(device, lambda: net(image).depth_m),
        "channels-last fp32": lambda: net_cl(image_cl).depth_m,
        "channels-last bf16": lambda: _bf16(device, lambda: net_cl(image_cl).depth_m),
    }
    if compile and name == "efficient":  # the goal's variant; compiling the paper network costs minutes
        inductor_cuda = device.type == "cuda" and scale.compile_backend == "inductor"
        mode = "reduce-overhead" if inductor_cuda else None  # CUDA graphs at this fixed size
        compiled = torch.compile(net_cl, dynamic=False, mode=mode, backend=scale.compile_backend)
        variants["compile bf16 channels-last"] = lambda: _bf16(device, lambda: compiled(image_cl).depth_m.clone())
    if onnx:
        session_run = _onnx_runner(net, image, device, work / f"{name}.onnx")
        if session_run is not None:
            variants[f"onnxruntime {session_run[1]}"] = session_run[0]
    return variants


def inference_rows(name: str, scale: Scale, device: torch.device, work: Path, *, compile: bool = True,
                   onnx: bool = True) -> list[dict[str, Any]]:
    """FPS of one network at ``scale.size``² for each variant and batch; the largest depth change to eager."""
    rows: list[dict[str, Any]] = []
    for batch in scale.infer_batches:
        variants = inference_variants(name, scale, batch, device, work, compile=compile, onnx=onnx)
        with torch.inference_mode():
            reference = variants["eager fp32"]().float().clamp(min=1e-3)
            for variant, run in variants.items():
                setup = time.perf_counter()
                depth = torch.as_tensor(run()).float().to(device)  # first call: compiles, captures
                setup = time.perf_counter() - setup
                fps = _timed_fps(run, batch, scale.infer_iters, device)
                rows.append({"network": name, "variant": variant, "batch": batch, "fps": fps,
                             "x_table7": fps / TABLE7_FPS, "setup_s": setup,
                             "max_depth_rel_change": float(((depth - reference).abs() / reference).max())})
                print(f"  {name:<10}{variant:<28}batch {batch:>3}: {fps:8.1f} FPS", file=sys.stderr, flush=True)
    return rows


def _bf16(device: torch.device, fn: Callable[[], torch.Tensor]) -> torch.Tensor:
    with torch.autocast(device.type, dtype=torch.bfloat16):
        return fn()


def _onnx_runner(net: DAPMNet, image: torch.Tensor, device: torch.device, path: Path
                 ) -> tuple[Callable[[], Any], str] | None:
    """Run onnxruntime on the device's provider (CUDA where the wheel has it; the CPU on a CPU); None otherwise."""
    try:
        import onnxruntime
    except ImportError:
        return None
    from dapm_lightning.inference.onnx import export_onnx

    provider = "CUDAExecutionProvider" if device.type == "cuda" else "CPUExecutionProvider"
    if provider not in onnxruntime.get_available_providers():
        return None
    if not path.is_file():
        export_onnx(net.cpu(), path, (image.shape[-2], image.shape[-1]), checks=1, dynamic=True)
        net.to(device)
    session = onnxruntime.InferenceSession(str(path), providers=[provider])
    feed = {"image": image.cpu().numpy()}
    depth_index = [o.name for o in session.get_outputs()].index("depth_m")
    return (lambda: session.run(None, feed)[depth_index]), provider.removesuffix("ExecutionProvider")


def learn(root: Path, scale: Scale, seconds: float, device: torch.device, workers: int,
          precision: str = "32-true") -> dict[str, Any]:
    """The efficient variant trained for ``seconds`` (cosine schedule over the time), then validated."""
    net = make_net("efficient", scale, device, False).train()
    criterion = DAPMLoss(LossConfig(depth_space="log_norm"), net.config.igd)
    optimizer = torch.optim.AdamW(net.parameters(), lr=1e-3, weight_decay=0.01)
    step = train_step_fn(net, criterion, optimizer, device, precision)
    batches = endless(loader(root, "train", scale.batch, workers, device))
    start, steps, loss = time.perf_counter(), 0, math.nan
    while (elapsed := time.perf_counter() - start) < seconds or steps == 0:
        for group in optimizer.param_groups:  # warm-up and cosine over the time budget (10 % / to 2 %)
            group["lr"] = 1e-3 * warmup_cosine(int(1000 * elapsed / seconds), 1000, 0.1, 0.02)
        loss = step(to_device(next(batches), device))["total"]
        steps += 1
    train_seconds = time.perf_counter() - start
    net.eval()
    depth, pose = DepthMetrics(), PoseMetrics()
    with torch.inference_mode():
        for batch in loader(root, "val", scale.batch, workers, device, train=False):
            batch = to_device(batch, device)
            out = net(batch["image"])
            depth.update(out.depth_m, batch["depth"])
            pose.update(out.pose_physical, batch["pose"])
    d, p = depth.compute(), pose.compute()
    return {"network": "efficient", "precision": precision, "size": scale.learn_size, "steps": steps,
            "train_s": train_seconds, "images_per_s": steps * scale.batch / train_seconds, "final_loss": loss,
            "val_images": scale.learn_val, "d1": float(d["d1"]), "abs_rel": float(d["abs_rel"]),
            **{f"{k}_median": float(p[f"{k}_median"]) for k in POSE_KEYS}}


def device_name(device: torch.device) -> str:
    """The GPU's name, or the CPU's and its threads."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"CPU ({platform.processor() or platform.machine()}, {torch.get_num_threads()} threads)"


def run_kit(out: Path, device: torch.device, scale: Scale, *, train_steps: int, budget_s: float, workers: int,
            compile: bool = True, onnx: bool = True, data_root: Path | None = None) -> dict[str, Any]:
    """Every measurement of the kit; returns the report (also written as JSON and markdown to ``out``)."""
    began = time.perf_counter()
    out.mkdir(parents=True, exist_ok=True)
    data_root = data_root or out / "data"
    timings: dict[str, float] = {}

    def phase(name: str, since: float) -> float:
        timings[name] = time.perf_counter() - since
        print(f"[bench_gpu] {name}: {timings[name]:.1f} s", file=sys.stderr, flush=True)
        return time.perf_counter()

    mark = time.perf_counter()
    cores = os.cpu_count() or 1
    big = render(data_root / str(scale.size), scale.size, scale.train_images, 0, cores)
    small = render(data_root / f"learn{scale.learn_size}", scale.learn_size, scale.learn_train, scale.learn_val,
                   cores)
    mark = phase("render", mark)
    loader_row = loader_speed(big, scale.batch, workers, scale.loader_batches, device)
    mark = phase("loader", mark)
    train_rows = []
    for name in NETWORKS:
        for precision in ("32-true", "bf16-mixed"):
            for channels_last in (False, True):
                data = loader(big, "train", scale.batch, workers, device)  # each run: the same batches in order
                row = train_run(name, precision, channels_last, data, scale, train_steps, device)
                print(f"  {name:<10}{precision:<11}channels-last {channels_last!s:<6}{row['s_per_step']:.3f} s/step, "
                      f"stall {row['stall_share']:.1%}", file=sys.stderr, flush=True)
                train_rows.append(row)
                del data
    mark = phase("train", mark)
    gaps = []
    for name in NETWORKS:
        fp32, bf16 = (next(r for r in train_rows if r["network"] == name and r["precision"] == p
                           and not r["channels_last"]) for p in ("32-true", "bf16-mixed"))
        gaps.append({"network": name, **curve_gap(fp32["losses"], bf16["losses"]),
                     "all_finite": fp32["finite"] and bf16["finite"]})
    inference = []
    with tempfile.TemporaryDirectory() as work:
        for name in NETWORKS:
            inference += inference_rows(name, scale, device, Path(work), compile=compile, onnx=onnx)
    mark = phase("inference", mark)
    learn_seconds = max(budget_s - (time.perf_counter() - began) - 20.0, 30.0 if scale.size >= 256 else 3.0)
    learning = learn(small, scale, learn_seconds, device, workers)
    phase("learning", mark)
    report = {"device": device_name(device), "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
              "torch": torch.__version__, "python": platform.python_version(), "cpu_cores": os.cpu_count(),
              "scale": asdict(scale), "train_steps": train_steps, "loader": loader_row, "train": train_rows,
              "bf16_vs_fp32": gaps, "inference": inference, "learning": learning, "phase_seconds": timings,
              "total_seconds": time.perf_counter() - began}
    (out / "bench_gpu.json").write_text(json.dumps(report, indent=1))
    (out / "bench_gpu.md").write_text(markdown(report))
    return report


def markdown(report: dict[str, Any]) -> str:
    """The report as the markdown that goes into docs/gpu.md."""
    scale, loader_row = report["scale"], report["loader"]
    lines = [f"**{report['device']}**, {report['date']}, torch {report['torch']}, {report['cpu_cores']} CPU cores, "
             f"{report['total_seconds'] / 60:.1f} min; backbone {scale['backbone']}, no pretrained weights.", "",
             f"Loader alone at {scale['size']}², {loader_row['workers']} workers: "
             f"**{loader_row['samples_per_s']:.1f} samples/s**.", "",
             f"Training at {scale['size']}², batch {scale['batch']}, {report['train_steps']} steps each:", "",
             "| network | precision | channels-last | s/step | images/s | x loader | stall | peak MB | finite |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in report["train"]:
        lines.append(f"| {r['network']} | {r['precision']} | {'on' if r['channels_last'] else 'off'} | "
                     f"{r['s_per_step']:.3f} | {r['images_per_s']:.1f} | "
                     f"{r['images_per_s'] / loader_row['samples_per_s']:.2f} | {r['stall_share']:.1%} | "
                     f"{r['peak_memory_mb']:.0f} | {'yes' if r['finite'] else '**no**'} |")
    lines += ["", "x loader: training images/s over the loader's samples/s (above 1: the loader cannot keep up).",
              "", "bf16-mixed against 32-true, same seed and batches (loss curves):", "",
              "| network | largest relative gap | of 10-step means | all finite |", "| --- | --- | --- | --- |"]
    for g in report["bf16_vs_fp32"]:
        lines.append(f"| {g['network']} | {g['max_relative_gap']:.2%} | {g['max_relative_gap_smoothed']:.2%} | "
                     f"{'yes' if g['all_finite'] else '**no**'} |")
    lines += ["", f"Inference at {scale['size']}² (x Table 7: FPS / {TABLE7_FPS}):", "",
              "| network | variant | batch | FPS | x Table 7 | setup s | max depth change |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in report["inference"]:
        lines.append(f"| {r['network']} | {r['variant']} | {r['batch']} | {r['fps']:.1f} | {r['x_table7']:.2f} | "
                     f"{r['setup_s']:.1f} | {r['max_depth_rel_change']:.1%} |")
    learning = report["learning"]
    lines += ["", f"Learning: the efficient variant, {learning['size']}², {learning['precision']}, "
                  f"{learning['steps']} steps in {learning['train_s']:.0f} s "
                  f"({learning['images_per_s']:.1f} images/s), "
                  f"final loss {learning['final_loss']:.3f}; on {learning['val_images']} val images: "
                  f"d1 {learning['d1']:.3f}, AbsRel {learning['abs_rel']:.3f}, medians height "
                  f"{learning['height_median']:.2f} m, pitch {learning['pitch_median']:.2f}°, roll "
                  f"{learning['roll_median']:.2f}°, FoV {learning['fov_median']:.2f}°.", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    """Run the kit and print the markdown report."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else None,
                        help="cuda (default where there is one) or cpu (with --tiny: the kit's test)")
    parser.add_argument("--tiny", action="store_true", help="ResNet-18, 64², a few steps: the same path in ~1 min")
    parser.add_argument("--out", default="outputs/bench_gpu", help="folder for bench_gpu.json / .md and the data")
    parser.add_argument("--train-steps", type=int, default=None, help="timed steps per training run (200; tiny 2)")
    parser.add_argument("--budget-s", type=float, default=None,
                        help="the whole kit's wall time; learning gets what is left (540; tiny 60)")
    parser.add_argument("--workers", type=int, default=None, help="loader workers (default: CPU cores - 1)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads of this process (default: torch's; tiny 1, as a shared CPU runs it best)")
    parser.add_argument("--no-compile", action="store_true", help="leave torch.compile out")
    parser.add_argument("--no-onnx", action="store_true", help="leave onnxruntime out")
    args = parser.parse_args(argv)
    if args.device is None:
        parser.error("no GPU on this machine: pass --device cpu --tiny to check the kit")
    device = torch.device(args.device)
    if args.threads or args.tiny:
        torch.set_num_threads(args.threads or 1)
    scale = Scale.tiny() if args.tiny else Scale()
    workers = args.workers if args.workers is not None else max(1, (os.cpu_count() or 2) - 1)
    report = run_kit(Path(args.out), device, scale, train_steps=args.train_steps or (2 if args.tiny else 200),
                     budget_s=args.budget_s or (60.0 if args.tiny else 540.0), workers=workers,
                     compile=not args.no_compile, onnx=not args.no_onnx)
    print(markdown(report))
    print(f"written: {Path(args.out) / 'bench_gpu.json'}, {Path(args.out) / 'bench_gpu.md'}")


if __name__ == "__main__":
    main()
