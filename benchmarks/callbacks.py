"""Lightning callbacks the benchmarks measure with.

Step times and losses, loader stalls, peak memory, channels-last training, resident memory while predicting and
over a long fit (its loader workers too).
Every benchmark that trains runs ``DAPMModule`` in a Lightning ``Trainer`` and measures it with these.
"""

from __future__ import annotations

import math
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch import Callback


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


def current_rss_mb() -> float:
    """Resident memory of this process now (MiB), from /proc; the peak where /proc is missing."""
    status = Path("/proc/self/status")
    if status.is_file():
        for line in status.read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return peak_rss_mb()


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MiB)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (1024 * 1024) if sys.platform == "darwin" else peak / 1024


class StepTimer(Callback):
    """Seconds and loss of every training step (forward, loss, backward and optimizer step; loading excluded).

    A step ends when the device has finished it. ``seconds`` and ``losses`` hold one value a step (the loss NaN
    where the module skipped a step), ``loss`` the last; ``first_start`` and ``last_end`` (``perf_counter``) span
    the steps, loading between them included. Every ``report_every`` steps a line goes to stderr.
    """

    def __init__(self, report_every: int = 50) -> None:
        self.report_every = report_every
        self.seconds: list[float] = []
        self.losses: list[float] = []
        self.loss = math.nan
        self.first_start: float | None = None
        self.last_end = math.nan
        self._start = 0.0

    def on_train_batch_start(self, trainer: Any, pl_module: Any, batch: Any, batch_idx: int) -> None:
        self._start = time.perf_counter()
        if self.first_start is None:
            self.first_start = self._start

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int) -> None:
        loss = outputs.get("loss") if isinstance(outputs, dict) else outputs
        self.loss = float(loss) if isinstance(loss, torch.Tensor) else math.nan  # float(): waits for the device
        sync(pl_module.device)
        self.last_end = time.perf_counter()
        self.seconds.append(self.last_end - self._start)
        self.losses.append(self.loss)
        if self.report_every and len(self.seconds) % self.report_every == 0:
            print(f"step {len(self.seconds)}: {statistics.median(self.seconds):.2f} s/step, loss {self.loss:.3f}",
                  file=sys.stderr, flush=True)

    @property
    def span_seconds(self) -> float:
        """Seconds from the first step's start to the last step's end."""
        return self.last_end - self.first_start if self.first_start is not None else math.nan


class LoaderStall(Callback):
    """Seconds each training step waited for its batch: the loader's stall.

    From the previous step's end (the first step: the start of the first epoch) to the step's start, which is
    where Lightning fetches the next batch and moves one to the device. ``waits`` holds one value a step;
    :meth:`share` is the waiting part of (waiting + step) time.
    """

    def __init__(self) -> None:
        self.waits: list[float] = []
        self._end: float | None = None

    def on_train_epoch_start(self, trainer: Any, pl_module: Any) -> None:
        if self._end is None:
            self._end = time.perf_counter()

    def on_train_batch_start(self, trainer: Any, pl_module: Any, batch: Any, batch_idx: int) -> None:
        self.waits.append(time.perf_counter() - (self._end if self._end is not None else time.perf_counter()))

    def on_train_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int) -> None:
        sync(pl_module.device)
        self._end = time.perf_counter()

    @staticmethod
    def share(waits: list[float], steps: list[float]) -> float:
        """Waiting time over waiting + step time."""
        total = sum(waits) + sum(steps)
        return sum(waits) / total if total > 0 else math.nan


class PeakMemory(Callback):
    """Peak memory from the start of training step ``from_step`` (counted from 0) to the end of training.

    ``peak_mb``, as :func:`peak_memory_mb` gives it: on a GPU the peak allocated since then, on a CPU the
    process's peak RSS.
    """

    def __init__(self, from_step: int = 0) -> None:
        self.from_step, self.peak_mb, self._seen = from_step, math.nan, 0

    def on_train_batch_start(self, trainer: Any, pl_module: Any, batch: Any, batch_idx: int) -> None:
        if self._seen == self.from_step:
            sync(pl_module.device)
            reset_peak_memory(pl_module.device)
        self._seen += 1

    def on_train_end(self, trainer: Any, pl_module: Any) -> None:
        self.peak_mb = peak_memory_mb(pl_module.device)


class ChannelsLast(Callback):
    """Train in channels-last memory (NHWC convolutions): the module's weights, and each batch's image."""

    def setup(self, trainer: Any, pl_module: Any, stage: str) -> None:
        pl_module.to(memory_format=torch.channels_last)

    def on_train_batch_start(self, trainer: Any, pl_module: Any, batch: Any, batch_idx: int) -> None:
        batch["image"] = batch["image"].contiguous(memory_format=torch.channels_last)


class MemoryProbe(Callback):
    """Prints resident memory (now and peak) every ``every`` predicted images; keeps the rows in ``samples``.

    ``seen``: images predicted; ``seconds``: from the first predict batch's start to the last one's end.
    """

    def __init__(self, every: int = 200) -> None:
        self.every, self.seen = every, 0
        self.samples: list[tuple[int, float, float]] = []
        self._first: float | None = None
        self.seconds = 0.0

    def on_predict_batch_start(self, trainer: Any, pl_module: Any, batch: Any, batch_idx: int,
                               dataloader_idx: int = 0) -> None:
        if self._first is None:
            self._first = time.perf_counter()

    def on_predict_batch_end(self, trainer: Any, pl_module: Any, outputs: Any, batch: Any, batch_idx: int,
                             dataloader_idx: int = 0) -> None:
        before = self.seen
        self.seen += len(batch)  # a PredictBatch
        self.seconds = time.perf_counter() - (self._first or time.perf_counter())
        if self.seen // self.every > before // self.every:
            self.samples.append((self.seen, current_rss_mb(), peak_rss_mb()))
            print(f"  {self.seen:>6} frames: RSS {self.samples[-1][1]:7.1f} MiB, peak {self.samples[-1][2]:7.1f} MiB",
                  flush=True)


def descendant_pids(pid: int | str = "self") -> list[int]:
    """The live processes started by ``pid`` or by those (Linux ``/proc``; [] elsewhere).

    A fit's loader workers are among them: started by the forkserver the fit started, or by the fit itself.
    """
    found: list[int] = []
    parents = [pid]
    while parents:
        children = []
        for task in (task for parent in parents for task in Path(f"/proc/{parent}/task").glob("*")):
            try:
                children += [int(each) for each in (task / "children").read_text().split()]
            except OSError:  # a thread or process that ended, or a kernel without the file
                continue
        parents = sorted(set(children) - set(found))
        found += parents
    return sorted(found)


def proportional_mb(pid: int) -> float:
    """A process's proportional set size (MiB: its private pages, and its share of those it shares), else its RSS.

    0 when it has ended.
    """
    for name, field in (("smaps_rollup", "Pss:"), ("status", "VmRSS:")):
        try:
            for line in Path(f"/proc/{pid}/{name}").read_text().splitlines():
                if line.startswith(field):
                    return int(line.split()[1]) / 1024
        except OSError:
            continue
    return 0.0


class FitMemoryProbe(Callback):
    """Memory after each training epoch (its validation and checkpoints done), in ``samples``.

    Each sample: the epoch, the step, this process's RSS and the PSS of the processes it started (the loader workers,
    their forkserver), MiB. ``worker_sets``: the sets of those processes seen, in order (one set: persistent workers).
    """

    def __init__(self) -> None:
        self.samples: list[dict[str, Any]] = []
        self.worker_sets: list[tuple[int, ...]] = []

    def on_train_epoch_end(self, trainer: Any, pl_module: Any) -> None:
        workers = tuple(descendant_pids())
        if not self.worker_sets or self.worker_sets[-1] != workers:
            self.worker_sets.append(workers)
        self.samples.append({"epoch": trainer.current_epoch, "step": trainer.global_step,
                             "main_mb": current_rss_mb(), "workers_mb": sum(map(proportional_mb, workers)),
                             "workers": len(workers)})


__all__ = ["ChannelsLast", "FitMemoryProbe", "LoaderStall", "MemoryProbe", "PeakMemory", "StepTimer", "current_rss_mb",
           "descendant_pids", "peak_memory_mb", "peak_rss_mb", "proportional_mb", "reset_peak_memory", "sync"]
