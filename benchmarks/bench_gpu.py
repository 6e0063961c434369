"""``make bench-gpu``: the GPU kit. One command turns the first GPU into figures (docs/gpu.md).

``python -m benchmarks.bench_gpu [--out outputs/bench_gpu]`` (from the repository root) renders its own synthetic
data (512² and 256², every core), then measures, in one process:

1. **loader**: loader-only samples/s at 512² (decode + augmentation, all workers, nothing on the device);
2. **train**: the paper network and the efficient variant, ``--train-steps`` steps of batch 8 at 512², with
   ``32-true`` and ``bf16-mixed``, channels-last off and on: s/step, images/s, peak device memory and the
   share of step time spent waiting on the loader (stall); every loss finite. Each run is ``DAPMModule`` in a
   Lightning ``Trainer`` on ``UAPDDataModule``, measured by callbacks (:mod:`benchmarks.callbacks`);
3. **bf16 vs fp32**: the loss curves of the same seed and batches, their largest relative gap;
4. **inference** at 512², batch 1 and 16: eager fp32 and bf16, channels-last, ``torch.compile`` (CUDA graphs
   on a GPU: ``mode="reduce-overhead"``), onnxruntime (its CUDA provider where the wheel has one): FPS and
   the ratio to the paper's Table 7 (24.1 FPS);
5. **learning**: the efficient variant trained for the rest of ``--budget-s`` at 256² on a fixed synthetic
   split (``Trainer(max_time=...)``, the schedule over the time: ``OptimizerConfig.schedule_seconds``), then
   ``trainer.validate``: val d1 and pose medians.

It writes ``bench_gpu.json`` and ``bench_gpu.md`` to ``--out``. ``--device cpu --tiny`` runs the same path with
ResNet-18 networks, 64² images and a few steps (about a minute on 2 cores): the kit is tested before a GPU
exists (tests/benchmarks/test_bench_gpu.py). Timings are only comparable within one run.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import platform
import statistics
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import lightning as L
import torch

from benchmarks.callbacks import ChannelsLast, LoaderStall, PeakMemory, StepTimer, sync
from dapm_lightning.data.datamodules import UAPDDataModule
from dapm_lightning.data.synthetic import generate_uapd, is_current
from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.models import EFFICIENT_NETWORK, PAPER_NETWORK, DAPMConfig, DAPMNet
from dapm_lightning.training.loss import LossConfig
from dapm_lightning.training.module import DAPMModule, OptimizerConfig

TABLE7_FPS = 24.1
"""The paper's Table 7: DAPM at 512², fp32, on their GPU."""

NETWORKS = {"paper": dict(PAPER_NETWORK), "efficient": dict(EFFICIENT_NETWORK)}
NARROW = {"decoder_channels": 16, "head_channels": 8, "igd_channels": 4, "pose_hidden": 16, "pose_projection": 16}
"""``--tiny``: each network's structure, a few channels wide (the kit's test on a CPU)."""

TRAIN_LOSS = LossConfig(depth_space="log_norm")
"""The paper configs' loss (Eq. 17 in the authors' space), for every run of the kit."""
TRAIN_OPTIMIZER = OptimizerConfig(lr=1e-4, weight_decay=0.01, warmup_fraction=0.0, min_lr_ratio=1.0)
"""The timed runs: AdamW at a constant 1e-4 (no warm-up, no decay: every step alike)."""
LEARN_LR = 1e-3
"""The learning phase's peak rate (AdamW, weight decay 0.01; warm-up over 10 %, cosine to 2 % over the time)."""


@dataclass(frozen=True)
class Scale:
    """Sizes of one kit run: the GPU's (default) or ``--tiny`` (the same path on a CPU in about a minute)."""

    backbone: str = "resnet50"
    size: int = 512
    learn_size: int = 256
    train_images: int = 256
    """Training images at ``size``² (and a batch of val images, which a ``Trainer``'s fit sets up unused)."""
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


def network_config(name: str, scale: Scale) -> DAPMConfig:
    """One of :data:`NETWORKS` at the scale's backbone (narrow with ``--tiny``), without pretrained weights.

    No ImageNet weights: the node may be offline.
    """
    settings = {**NETWORKS[name], **(NARROW if scale.narrow else {})}
    return DAPMConfig(backbone=scale.backbone, pretrained=False, **settings)


def make_module(name: str, scale: Scale, optimizer: OptimizerConfig = TRAIN_OPTIMIZER, seed: int = 0) -> DAPMModule:
    """``DAPMModule`` of one of :data:`NETWORKS` with the kit's loss, seeded, untrained."""
    torch.manual_seed(seed)
    return DAPMModule(net=network_config(name, scale), loss=TRAIN_LOSS, optimizer=optimizer)


def make_net(name: str, scale: Scale, device: torch.device, channels_last: bool, seed: int = 0) -> DAPMNet:
    """The network of :func:`make_module` (the same weights for the same seed), for inference."""
    net = make_module(name, scale, seed=seed).net.to(device)
    return net.to(memory_format=torch.channels_last) if channels_last else net  # type: ignore[call-overload]


def render(root: Path, size: int, train: int, val: int, workers: int) -> Path:
    """The kit's synthetic data (kept between runs: same settings, same bytes)."""
    settings = dict(train=train, val=val, size=(size, size), seed=0, families=None, effects=True, distortion=False)
    threads = torch.get_num_threads()  # rendering in this process sets one thread
    if not is_current(root, **settings):
        generate_uapd(root, train=train, val=val, size=size, seed=0, workers=workers)
    torch.set_num_threads(threads)
    return root


def datamodule(root: Path, batch: int, workers: int, device: torch.device, seed: int = 0) -> UAPDDataModule:
    """The data as ``dapm-lightning fit`` loads it: uint8 images, the default augmentation, seeded order and draws."""
    return UAPDDataModule(root=str(root), batch_size=batch, num_workers=workers, pin_memory=device.type == "cuda",
                          persistent_workers=workers > 0, seed=seed)


def make_trainer(device: torch.device, precision: str, callbacks: list[L.Callback], root: Path | None = None,
                 **limits: Any) -> L.Trainer:
    """A one-device ``Trainer`` on ``device`` without logger, checkpoints, progress bar or validation during fit.

    ``limits``: ``max_steps``, ``max_time`` and the like.
    """
    cuda = device.type == "cuda"
    return L.Trainer(accelerator="gpu" if cuda else "cpu", devices=[device.index] if cuda and device.index else 1,
                     precision=precision, callbacks=callbacks, logger=False, enable_checkpointing=False,
                     enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=0,
                     limit_val_batches=0, max_epochs=-1, default_root_dir=str(root) if root else None, **limits)


def endless(data: Any) -> Iterator[dict[str, Any]]:
    """The loader's batches, epoch after epoch."""
    while True:
        yield from data


def loader_speed(root: Path, batch: int, workers: int, batches: int, device: torch.device) -> dict[str, Any]:
    """Samples/s of the training loader alone (all workers; nothing on the device), after one warm-up batch."""
    data = datamodule(root, batch, workers, device)
    data.setup("fit")
    batches_seen = endless(data.train_dataloader())
    next(batches_seen)
    start = time.perf_counter()
    for _ in range(batches):
        next(batches_seen)
    seconds = time.perf_counter() - start
    return {"workers": workers, "batch": batch, "batches": batches, "samples_per_s": batches * batch / seconds}


def train_run(name: str, precision: str, channels_last: bool, root: Path, scale: Scale, steps: int,
              device: torch.device, workers: int, seed: int = 0) -> dict[str, Any]:
    """``steps`` timed optimiser steps of ``DAPMModule`` in a ``Trainer`` (after ``scale.warmup_steps`` untimed).

    The same seed gives the same weights, batches and augmentation, so runs differing only in precision or
    memory format see the same data. Step time (until the device is done), the wait before each step (loader
    stall) and peak memory come from callbacks; ``losses``: every step's loss, the untimed ones first.
    """
    module = make_module(name, scale, seed=seed)
    timer, stall, memory = StepTimer(report_every=0), LoaderStall(), PeakMemory(from_step=scale.warmup_steps)
    callbacks: list[L.Callback] = [stall, timer, memory] + ([ChannelsLast()] if channels_last else [])
    with tempfile.TemporaryDirectory() as work:
        trainer = make_trainer(device, precision, callbacks, Path(work), max_steps=scale.warmup_steps + steps)
        trainer.fit(module, datamodule=datamodule(root, scale.batch, workers, device, seed))
    compute, wait = sum(timer.seconds[scale.warmup_steps:]), sum(stall.waits[scale.warmup_steps:])
    seconds = wait + compute
    finite = module.nonfinite_steps == 0 and all(math.isfinite(v) for v in timer.losses)
    return {"network": name, "precision": precision, "channels_last": channels_last, "steps": steps,
            "batch": scale.batch, "s_per_step": seconds / steps, "images_per_s": steps * scale.batch / seconds,
            "stall_share": wait / seconds, "peak_memory_mb": memory.peak_mb, "finite": finite,
            "losses": timer.losses}


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
        session_run = _onnx_runner(name, scale, image, device, work)
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
            reference_bf16 = variants["eager bf16"]().float().clamp(min=1e-3)
            for variant, run in variants.items():
                setup = time.perf_counter()
                depth = torch.as_tensor(run()).float().to(device)  # first call: compiles, captures
                setup = time.perf_counter() - setup
                fps = _timed_fps(run, batch, scale.infer_iters, device)
                # both changes: a bf16 variant should be near eager bf16; near fp32 instead, it ran in fp32
                rows.append({"network": name, "variant": variant, "batch": batch, "fps": fps,
                             "x_table7": fps / TABLE7_FPS, "setup_s": setup,
                             "max_depth_rel_change": float(((depth - reference).abs() / reference).max()),
                             "max_depth_rel_change_to_bf16": float(
                                 ((depth - reference_bf16).abs() / reference_bf16).max())})
                print(f"  {name:<10}{variant:<28}batch {batch:>3}: {fps:8.1f} FPS", file=sys.stderr, flush=True)
    return rows


def _bf16(device: torch.device, fn: Callable[[], torch.Tensor]) -> torch.Tensor:
    with torch.autocast(device.type, dtype=torch.bfloat16):
        return fn()


def _onnx_runner(name: str, scale: Scale, image: torch.Tensor, device: torch.device, work: Path
                 ) -> tuple[Callable[[], Any], str] | None:
    """Run onnxruntime on the device's provider (CUDA where the wheel has it; the CPU on a CPU); None otherwise.

    The model is :func:`make_module`'s (the eager variants' weights), exported by ``dapm-lightning export``.
    """
    try:
        import onnxruntime
    except ImportError:
        return None
    from benchmarks.bench_predict import export_onnx, write_checkpoint
    from dapm_lightning.inference.onnx import onnx_feed

    provider = "CUDAExecutionProvider" if device.type == "cuda" else "CPUExecutionProvider"
    if provider not in onnxruntime.get_available_providers():
        return None
    path = work / f"{name}.onnx"
    if not path.is_file():
        checkpoint = write_checkpoint(make_module(name, scale), work / f"{name}.ckpt")
        export_onnx(checkpoint, path, (image.shape[-2], image.shape[-1]))
    session = onnxruntime.InferenceSession(str(path), providers=[provider])
    feed = onnx_feed(image.cpu().numpy(), [i.name for i in session.get_inputs()])
    depth_index = [o.name for o in session.get_outputs()].index("depth_m")
    return (lambda: session.run(None, feed)[depth_index]), provider.removesuffix("ExecutionProvider")


def learn(root: Path, scale: Scale, seconds: float, device: torch.device, workers: int,
          precision: str = "32-true") -> dict[str, Any]:
    """The efficient variant trained for ``seconds`` (warm-up and cosine over the time), then validated.

    ``DAPMModule`` in a ``Trainer(max_time=seconds)`` with ``OptimizerConfig.schedule_seconds``, then
    ``trainer.validate`` on the val split: the module's own metrics (depth in metres, pose medians).
    """
    optimizer = OptimizerConfig(lr=LEARN_LR, weight_decay=0.01, warmup_fraction=0.1, min_lr_ratio=0.02,
                                schedule_seconds=seconds)
    module = make_module("efficient", scale, optimizer)
    timer = StepTimer(report_every=200)
    data = datamodule(root, scale.batch, workers, device)
    with tempfile.TemporaryDirectory() as work:
        trainer = make_trainer(device, precision, [timer], Path(work), max_steps=-1,
                               max_time=timedelta(seconds=seconds))
        trainer.fit(module, datamodule=data)
        trainer.limit_val_batches = 1.0
        metrics = trainer.validate(module, datamodule=data, verbose=False)[0]
    steps, train_seconds = len(timer.seconds), timer.span_seconds
    return {"network": "efficient", "precision": precision, "size": scale.learn_size, "steps": steps,
            "train_s": train_seconds, "images_per_s": steps * scale.batch / train_seconds, "final_loss": timer.loss,
            "val_images": scale.learn_val, "d1": float(metrics["val_depth_d1"]),
            "abs_rel": float(metrics["val_depth_abs_rel"]),
            **{f"{k}_median": float(metrics[f"val_pose_{k}_median"]) for k in POSE_KEYS}}


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
    big = render(data_root / str(scale.size), scale.size, scale.train_images, scale.batch, cores)  # val: fit asks
    small = render(data_root / f"learn{scale.learn_size}", scale.learn_size, scale.learn_train, scale.learn_val,
                   cores)
    mark = phase("render", mark)
    loader_row = loader_speed(big, scale.batch, workers, scale.loader_batches, device)
    mark = phase("loader", mark)
    train_rows = []
    for name in NETWORKS:
        for precision in ("32-true", "bf16-mixed"):
            for channels_last in (False, True):  # each run: the same seed, so the same batches in order
                row = train_run(name, precision, channels_last, big, scale, train_steps, device, workers)
                print(f"  {name:<10}{precision:<11}channels-last {channels_last!s:<6}{row['s_per_step']:.3f} s/step, "
                      f"stall {row['stall_share']:.1%}", file=sys.stderr, flush=True)
                train_rows.append(row)
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
              "| network | variant | batch | FPS | x Table 7 | setup s | max depth change | to eager bf16 |",
              "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in report["inference"]:
        lines.append(f"| {r['network']} | {r['variant']} | {r['batch']} | {r['fps']:.1f} | {r['x_table7']:.2f} | "
                     f"{r['setup_s']:.1f} | {r['max_depth_rel_change']:.1%} | "
                     f"{r['max_depth_rel_change_to_bf16']:.1%} |")
    lines += ["", "max depth change: the largest relative depth difference to eager fp32; to eager bf16: to eager "
                  "bf16 (a bf16 variant near fp32 and far from eager bf16 did not run in bf16)."]
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
    logging.getLogger("lightning.pytorch.utilities.rank_zero").setLevel(logging.WARNING)  # one Trainer a run
    warnings.filterwarnings("ignore", message=".*does not have many workers")
    warnings.filterwarnings("ignore", message=".*treespec, LeafSpec.*")
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
