"""Inference benchmarks of the predict path: speed side by side, and memory over a long video.

``python -m benchmarks.bench_predict speed``: the network at 512x512, batch 1, as eager PyTorch,
channels-last, ``torch.compile`` and the exported ONNX model in onnxruntime, measured in alternating
rounds in one process; each row is a ratio to eager with the largest depth (metres) and pose difference
to eager on the same input.

``python -m benchmarks.bench_predict int8 --ckpt_path CKPT``: a trained checkpoint as eager PyTorch, the float32
ONNX model and its int8 quantisation (``export --int8``) side by side in one process, batch 1, at the checkpoint's
network size, 256² and 512²: median latency, speed-ups, and the toolbox d1 and pose medians on held-out renders,
with their changes against eager.

``python -m benchmarks.bench_predict memory``: ``dapm-lightning predict`` (the Lightning form) on a 2,000-frame
video (tiny untrained model or ``--ckpt_path``, 64x64 frames, every output written), printing the process's
resident memory every 200 frames: it stays flat because nothing is kept once written.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import lightning as L
import numpy as np
import torch
from torch import Tensor

import dapm_lightning
from benchmarks.bench import format_table
from benchmarks.callbacks import MemoryProbe
from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.inference.int8_check import Runner, compare_runners, ort_session, session_runner
from dapm_lightning.inference.onnx import onnx_feed
from dapm_lightning.models.config import DAPMConfig
from dapm_lightning.models.dapm import DAPMNet
from dapm_lightning.training.checkpointing import load_dapm_module
from dapm_lightning.training.module import DAPMModule

PREDICT_CONFIG = Path(dapm_lightning.__file__).resolve().parent / "configs" / "predict.yaml"
"""The Lightning form of ``dapm-lightning predict`` (``--config configs/predict.yaml``)."""
TINY_NETWORK = {"backbone": "resnet18", "decoder_channels": 16, "head_channels": 8, "igd_channels": 4,
                "pose_hidden": 16, "depth_bins": (2, 4), "pose_bins": (4,)}
"""``memory``'s model when no checkpoint is given: ResNet-18 with a few channels, untrained."""


def _module(ckpt_path: str | None, backbone: str) -> DAPMModule:
    """The checkpoint's module, or the ``DAPMConfig`` defaults at ``backbone`` with random weights (seed 0)."""
    if ckpt_path:
        return load_dapm_module(ckpt_path).eval()
    torch.manual_seed(0)
    module = DAPMModule(net=DAPMConfig(backbone=backbone)).eval()
    if module.net.config.use_depth:  # random weights give all-sky depth; tilt them to ground so differences show
        module.net.depth_pqb.blocks[0].body[-1].bias.data.fill_(-4.0)
    return module


def write_checkpoint(module: DAPMModule, path: Path) -> Path:
    """``module`` as a checkpoint file, written by a Lightning ``Trainer`` as ``fit`` writes one."""
    trainer = L.Trainer(accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, default_root_dir=str(path.parent))
    trainer.strategy.connect(module)
    trainer.save_checkpoint(path, weights_only=True)  # the weights and settings: nothing to resume
    return path


def export_onnx(ckpt_path: str | Path, out: Path, size: tuple[int, int], int8: bool = False,
                calibration_images: int = 32) -> Path:
    """``dapm-lightning export``: the float32 ONNX model (dynamic batch and size), checked once against PyTorch.

    With ``int8`` also its int8 quantisation, calibrated on ``calibration_images`` rendered images: ``out`` is
    then the int8 file, and the float32 one is beside it without the ``_int8`` of its name.
    """
    from dapm_lightning.cli import main as dapm_lightning_cli

    args = ["export", "--ckpt_path", str(ckpt_path), "--out", str(out), "--height", str(size[0]), "--width",
            str(size[1]), "--checks", "1"]
    dapm_lightning_cli(args + (["--int8", "true", "--calibration_images", str(calibration_images)] if int8 else []))
    return out


def _outputs(out: Any) -> tuple[Tensor, Tensor]:
    return out.depth_m.float(), out.pose_physical.float()


def speed(ckpt_path: str | None = None, backbone: str = "resnet50", size: int = 512, rounds: int = 5,
          onnx: bool = True, compile: bool = True, threads: int | None = None) -> list[dict[str, Any]]:
    """Side-by-side latency of the predict path's network at ``size`` x ``size``, batch 1.

    Args:
        ckpt_path: a checkpoint (default: the efficient variant, the ``DAPMConfig`` defaults, with random
            weights and ``backbone``).
        backbone: timm backbone when no checkpoint is given (resnet50: the paper's).
        size: image height and width.
        rounds: timed rounds; the variants alternate within each round, the median counts.
        onnx: include onnxruntime (export first; needs the export extra).
        compile: include torch.compile (compiles first).
        threads: torch intra-op threads (default: torch's).
    """
    if threads:
        torch.set_num_threads(threads)
    module = _module(ckpt_path, backbone)
    net = module.net
    image = torch.rand(1, 3, size, size, generator=torch.Generator().manual_seed(0))
    variants: dict[str, Callable[[], tuple[Tensor, Tensor]]] = {}
    setup: dict[str, float] = {}
    with torch.inference_mode():
        variants["eager"] = lambda: _outputs(net(image))
        channels_last = DAPMNet(net.config).eval()
        channels_last.load_state_dict(net.state_dict())
        channels_last = channels_last.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
        image_cl = image.contiguous(memory_format=torch.channels_last)
        variants["channels-last"] = lambda: _outputs(channels_last(image_cl))
    if compile:
        start = time.perf_counter()
        compiled = torch.compile(net, dynamic=False)
        with torch.inference_mode():
            compiled(image)
        setup["torch.compile"] = time.perf_counter() - start
        variants["torch.compile"] = lambda: _outputs(torch.inference_mode()(compiled)(image))
    if onnx:
        import onnxruntime

        start = time.perf_counter()
        with tempfile.TemporaryDirectory() as folder:
            ckpt = ckpt_path or write_checkpoint(module, Path(folder) / "bench.ckpt")
            path = export_onnx(ckpt, Path(folder) / "bench.onnx", (size, size))
            options = onnxruntime.SessionOptions()
            if threads:
                options.intra_op_num_threads = threads
            session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        setup["onnxruntime"] = time.perf_counter() - start
        names = [o.name for o in session.get_outputs()]

        def run_onnx() -> tuple[Tensor, Tensor]:
            feed = onnx_feed(image.numpy(), [i.name for i in session.get_inputs()])
            result = dict(zip(names, session.run(None, feed)))
            return torch.from_numpy(result["depth_m"]), torch.from_numpy(result["pose"])

        variants["onnxruntime"] = run_onnx
    times: dict[str, list[float]] = {name: [] for name in variants}
    results: dict[str, tuple[Tensor, Tensor]] = {}
    with torch.inference_mode():
        for name, run in variants.items():  # warm-up
            results[name] = run()
        for _ in range(rounds):
            for name, run in variants.items():
                start = time.perf_counter()
                run()
                times[name].append(time.perf_counter() - start)
    eager_s = statistics.median(times["eager"])
    rows = []
    for name in variants:
        median = statistics.median(times[name])
        depth_diff = float((results[name][0] - results["eager"][0]).abs().max())
        pose_diff = float((results[name][1] - results["eager"][1]).abs().max())
        rows.append({"variant": name, "median_ms": 1000 * median, "speedup": eager_s / median,
                     "max_depth_diff_m": depth_diff, "max_pose_diff": pose_diff,
                     "setup_s": setup.get(name, 0.0)})
    return rows


def format_speed(rows: Sequence[dict[str, Any]], title: str) -> str:
    """The speed rows as a table."""
    return title + "\n" + format_table(rows, [
        ("variant", "variant", 15, ""), ("median_ms", "median ms", 11, ".1f"), ("speedup", "x eager", 9, ".2f"),
        ("max_depth_diff_m", "max |depth - eager| m", 24, ".3g"), ("max_pose_diff", "max |pose - eager|", 20, ".3g"),
        ("setup_s", "setup s", 9, ".0f")])


def eager_runner(net: torch.nn.Module) -> Runner:
    """The network in PyTorch as an :data:`~dapm_lightning.inference.int8_check.Runner` (depth_m, pose)."""
    def run(image: np.ndarray) -> dict[str, np.ndarray]:
        with torch.inference_mode():
            out = net(torch.from_numpy(image))
        result = {"depth_m": out.depth_m, "pose": out.pose_physical}
        return {k: v.float().numpy() for k, v in result.items() if v is not None}

    return run


def int8_compare(ckpt_path: str | Path, sizes: Sequence[int] | None = None, images: int = 64,
                 calibration_images: int = 64, threads: int = 1) -> list[dict[str, Any]]:
    """Eager fp32, ORT fp32 and ORT int8 of a checkpoint at each size, on the same held-out renders, batch 1.

    At each size (default: the checkpoint's network size, 256² and 512²) the int8 model is the one
    ``dapm-lightning export --int8 true --height S --width S`` writes: calibrated on ``calibration_images``
    renders at the training size plus a quarter as many at ``S``. The three run ``images`` renders of the
    held-out split, alternating image by image on ``threads`` threads; the median latency counts, and
    accuracy is the toolbox d1 and the pose medians against the rendered truth.
    """
    from dapm_lightning.inference.inputs import checkpoint_network_size
    from dapm_lightning.inference.onnx import export_metadata
    from dapm_lightning.inference.onnx import export_onnx as export_model
    from dapm_lightning.inference.quantize import calibration_images as calibration_set
    from dapm_lightning.inference.quantize import quantize_int8, render_set

    module = load_dapm_module(ckpt_path, map_location="cpu").eval()
    trained = checkpoint_network_size(module)
    shapes = [trained] + [(s, s) for s in (256, 512) if (s, s) != trained] if sizes is None else \
        [(s, s) for s in sizes]
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as folder:
        float_path = Path(folder) / "model.onnx"
        export_model(module.net, float_path, trained, checks=1,
                     metadata=export_metadata(module.net, module.train_image_size, ckpt_path))
        for shape in shapes:
            int8_path = Path(folder) / f"model_{shape[0]}x{shape[1]}_int8.onnx"
            extra = max(1, calibration_images // 4) if shape != trained else 0
            quantize_int8(float_path, int8_path, calibration_set(trained, shape, at_train=calibration_images,
                                                                 at_export=extra))
            renders = render_set(shape, images)
            torch.set_num_threads(threads)  # rendering may have changed it
            scores = compare_runners({"eager fp32": eager_runner(module.net),
                                      "ORT fp32": session_runner(ort_session(float_path, threads)),
                                      "ORT int8": session_runner(ort_session(int8_path, threads))}, renders)
            eager, ort_float = scores["eager fp32"], scores["ORT fp32"]
            for name, score in scores.items():
                rows.append({"size": f"{shape[0]}x{shape[1]}", "variant": name, "median_ms": score.median_ms,
                             "x_eager": eager.median_ms / score.median_ms,
                             "x_ort_fp32": ort_float.median_ms / score.median_ms,
                             "d1": score.d1 if score.d1 is not None else float("nan"),
                             "d1_change": (score.d1 - eager.d1) if score.d1 is not None and eager.d1 is not None
                             else float("nan"),
                             **{f"{k}_median": v for k, v in score.pose_median.items()},
                             "worst_median_growth": max((v - eager.pose_median[k]
                                                         for k, v in score.pose_median.items()), default=0.0)})
    return rows


def format_int8(rows: Sequence[dict[str, Any]], title: str) -> str:
    """The int8 rows as a table."""
    return title + "\n" + format_table(rows, [
        ("size", "size", 8, ""), ("variant", "variant", 11, ""), ("median_ms", "median ms", 10, ".1f"),
        ("x_eager", "x eager", 8, ".2f"), ("x_ort_fp32", "x ORT fp32", 11, ".2f"), ("d1", "d1", 7, ".3f"),
        ("d1_change", "d1 change", 11, "+.3f"),
        *((f"{k}_median", f"{k} med", 12, ".2f") for k in POSE_KEYS),
        ("worst_median_growth", "worst med growth", 17, "+.2f")])


def write_video(path: Path, frames: int, size: int = 64, seed: int = 0) -> Path:
    """A synthetic MJPG video of ``frames`` frames (moving gradients and noise)."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (size, size))
    rng = np.random.default_rng(seed)
    base = np.linspace(0, 255, size, dtype=np.float32)
    for k in range(frames):
        frame = np.stack([np.roll(base, k)[None].repeat(size, 0), np.roll(base, -k)[:, None].repeat(size, 1),
                          rng.uniform(0, 255, (size, size))], -1)
        writer.write(frame.astype(np.uint8))
    writer.release()
    return path


def tiny_checkpoint(path: Path, seed: int = 0) -> Path:
    """A checkpoint of an untrained :data:`TINY_NETWORK` DAPM."""
    torch.manual_seed(seed)
    return write_checkpoint(DAPMModule(net=DAPMConfig(**TINY_NETWORK)), path)  # type: ignore[arg-type]


def memory(frames: int = 2000, every: int = 200, batch_size: int = 16, ckpt_path: str | None = None,
           image_width: int = 64, num_workers: int = 1, out: str | None = None) -> list[tuple[int, float, float]]:
    """``dapm-lightning predict`` on a ``frames``-frame video, all outputs written; RSS every ``every`` frames.

    The Lightning form of the command (``--config configs/predict.yaml``: ``PredictionWriter``, nothing kept
    in memory) on the CPU, with :class:`~benchmarks.callbacks.MemoryProbe` added. ``ckpt_path``: the model
    (default: an untrained :data:`TINY_NETWORK`, written as a checkpoint by :func:`tiny_checkpoint` and passed as
    ``--ckpt_path``: ``predict`` refuses to run without one, and memory does not depend on the weights); frames
    are ``image_width`` pixels square; ``out``: where the predictions go (default: a temporary folder). Returns the
    probe's ``(frames, RSS MiB, peak RSS MiB)`` rows.
    """
    from dapm_lightning.inference.writers import PredictionWriter
    from dapm_lightning.training.lightning_cli import run_lightning_cli

    warnings.filterwarnings("ignore", message="LightningCLI's args parameter")  # the CLI called from Python
    with tempfile.TemporaryDirectory() as folder:
        video = write_video(Path(folder) / "long.avi", frames, size=image_width)
        ckpt = ckpt_path or str(tiny_checkpoint(Path(folder) / "tiny.ckpt"))
        cli = run_lightning_cli([
            "predict", "--config", str(PREDICT_CONFIG), "--ckpt_path", ckpt, "--trainer.accelerator", "cpu",
            "--trainer.enable_progress_bar", "false",
            "--data.init_args.source", str(video), "--data.init_args.image_width", str(image_width),
            "--data.init_args.batch_size", str(batch_size), "--data.init_args.num_workers", str(num_workers),
            "--trainer.callbacks.output_dir", out or str(Path(folder) / "pred"),
            "--trainer.callbacks.outputs", "depth_npy,depth_tiff,depth16,depth_color,sky,camera,points",
            "--trainer.callbacks+=benchmarks.callbacks.MemoryProbe", "--trainer.callbacks.every", str(every)])
        probe = next(c for c in cli.trainer.callbacks if isinstance(c, MemoryProbe))
        writer = next(c for c in cli.trainer.callbacks if isinstance(c, PredictionWriter))
        files = sum(1 for p in Path(writer.output_dir).iterdir() if not p.name.startswith("."))  # not the marker
    seconds = probe.seconds
    print(f"{probe.seen} frames in {seconds:.0f} s ({probe.seen / max(seconds, 1e-9):.1f} frames/s), "
          f"{files} files written")
    if len(probe.samples) > 2:
        growth = probe.samples[-1][1] - probe.samples[1][1]
        print(f"RSS change from frame {probe.samples[1][0]} to {probe.samples[-1][0]}: {growth:+.1f} MiB")
    return probe.samples


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m benchmarks.bench_predict {speed,int8,memory} [--option value ...]``."""
    from jsonargparse import auto_cli

    args = list(sys.argv[1:] if argv is None else argv)
    if args and args[0] == "speed":
        def run_speed(ckpt_path: str | None = None, backbone: str = "resnet50", size: int = 512, rounds: int = 5,
                      onnx: bool = True, compile: bool = True, threads: int | None = None) -> None:
            """Speed of the predict path's network: eager, channels-last, torch.compile, onnxruntime."""
            rows = speed(ckpt_path, backbone, size, rounds, onnx, compile, threads)
            what = ckpt_path or f"DAPM ({backbone}, random weights)"
            print(format_speed(rows, f"{what}, {size}x{size}, batch 1, {torch.get_num_threads()} threads, "
                                     f"median of {rounds} alternating rounds, torch {torch.__version__}"))

        auto_cli(run_speed, args=args[1:], prog="bench_predict speed")
    elif args and args[0] == "int8":
        def run_int8(ckpt_path: str, sizes: list[int] | None = None, images: int = 64, calibration_images: int = 64,
                     threads: int = 1) -> None:
            """Eager fp32 vs ORT fp32 vs ORT int8 of a trained checkpoint: latency, held-out d1 and pose medians."""
            rows = int8_compare(ckpt_path, sizes, images, calibration_images, threads)
            print(format_int8(rows, f"{ckpt_path}: batch 1, {threads} thread(s), {images} held-out renders per size, "
                                    f"int8 calibrated on {calibration_images} renders at the training size "
                                    f"(+{max(1, calibration_images // 4)} at each other size), "
                                    f"torch {torch.__version__}"))

        auto_cli(run_int8, args=args[1:], prog="bench_predict int8", as_positional=False)
    elif args and args[0] == "memory":
        def run_memory(frames: int = 2000, every: int = 200, batch_size: int = 16, ckpt_path: str | None = None,
                       image_width: int = 64, num_workers: int = 1, out: str | None = None) -> None:
            """Resident memory while predicting a long video (tiny model, every output written)."""
            memory(frames, every, batch_size, ckpt_path, image_width, num_workers, out)

        auto_cli(run_memory, args=args[1:], prog="bench_predict memory")
    else:
        print(__doc__)
        raise SystemExit(0 if args and args[0] in ("-h", "--help") else 2)


if __name__ == "__main__":
    main()


__all__ = ["int8_compare", "memory", "speed"]
