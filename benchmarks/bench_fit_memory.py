"""Memory of a long ``fit``: does the training process, or its loader workers, grow with the steps?

``python -m benchmarks.bench_fit_memory``: the quickstart recipe (``dapm_lightning/configs/quickstart.yaml``: its
callbacks, loggers, checkpoints, validation every epoch) on a small synthetic set at 32², with persistent loader
workers, for many short epochs. After each epoch (its validation and checkpoints included) it prints the training
process's resident memory and its loader workers' proportional share (PSS: pages they share are counted once), and
whether the workers are the ones of the first epoch. The growth is how fast the median memory of each quarter of
the epochs after the warm-up rises from the third quarter to the last, in MiB per 1,000 steps, projected
to the paper's 32,000 steps: a leak (a tensor kept by a metric or a callback, a list a worker fills) keeps raising it
there, where what settles has stopped. It is called growth only if the median rises from the first quarter to the
last as fast: a leak lifts every quarter, an allocator's single step late in the run the last one only. Figures vary
between machines; compare them within one run.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import statistics
import tempfile
import warnings
from pathlib import Path
from typing import Any

import dapm_lightning
from benchmarks.callbacks import FitMemoryProbe

QUICKSTART = Path(dapm_lightning.__file__).resolve().parent / "configs" / "quickstart.yaml"
PAPER_STEPS = 32_000
"""The paper's training length (iterations), to which the growth is projected."""
FLAT_MIB_PER_1000_STEPS = 2.0
"""Growth below this per 1,000 steps (64 MiB over the paper's 32,000) is reported as flat."""


def quarter_floors(samples: list[dict[str, Any]], key: str, warmup: int) -> list[tuple[float, float]]:
    """``(mean step, median value)`` of ``key`` in each quarter of the samples after the first ``warmup``.

    The median: what the allocator holds or gives back for a moment (a checkpoint's buffers, a trimmed arena) moves
    a few samples and not the median, while a leak lifts every sample after it. [] with fewer than four samples
    after the warm-up.
    """
    settled = samples[warmup:]
    if len(settled) < 4:
        return []
    bounds = [round(i * len(settled) / 4) for i in range(5)]
    quarters = [settled[a:b] for a, b in zip(bounds, bounds[1:])]
    return [(sum(row["step"] for row in rows) / len(rows), statistics.median(row[key] for row in rows))
            for rows in quarters]


def rise_per_1000_steps(floors: list[tuple[float, float]], first: int) -> float:
    """How fast the median rises from quarter ``first`` of ``floors`` (:func:`quarter_floors`) to the last quarter.

    MiB per 1,000 steps; NaN without four quarters.
    """
    if len(floors) < 4 or floors[3][0] == floors[first][0]:
        return float("nan")
    return 1000 * (floors[3][1] - floors[first][1]) / (floors[3][0] - floors[first][0])


def growth_per_1000_steps(samples: list[dict[str, Any]], key: str, warmup: int) -> float:
    """How fast the median of ``key`` (MiB) rises at the end: from the third quarter's to the last, per 1,000 steps.

    A leak keeps raising it there; what settles (the allocator's first arenas, the workers' pages copied as they are
    written) has stopped. NaN with fewer than four samples after the warm-up.
    """
    return rise_per_1000_steps(quarter_floors(samples, key, warmup), 2)


def steady_growth_per_1000_steps(samples: list[dict[str, Any]], key: str, warmup: int) -> float:
    """How fast the median of ``key`` (MiB) rises over the whole settled run: from the first quarter's to the last's.

    A leak lifts every quarter, so it shows here as it does at the end; a single step of the allocator late in the
    run (an arena grown once) shows at the end only. NaN with fewer than four samples after the warm-up.
    """
    return rise_per_1000_steps(quarter_floors(samples, key, warmup), 0)


def growth_verdict(late: float, steady: float) -> str:
    """What the two rates (MiB per 1,000 steps) say: a rise at the end is growth only if the whole run rises too."""
    if math.isnan(late) or math.isnan(steady):
        return "too few epochs to tell"
    if late < FLAT_MIB_PER_1000_STEPS:
        return "flat" if late > -FLAT_MIB_PER_1000_STEPS else "falls"
    if steady >= FLAT_MIB_PER_1000_STEPS:
        return "GROWS"
    return (f"a step in the last quarter, the whole run {steady:+.2f} per 1000 steps: not a steady rise; "
            "more epochs tell a late leak from an allocator's step")


def run(epochs: int = 60, train: int = 64, val: int = 16, size: int = 32, batch: int = 4, workers: int = 2,
        warmup: int = 5, root: str | None = None, out: str | None = None) -> FitMemoryProbe:
    """Fit the quickstart recipe for ``epochs`` epochs of ``train // batch`` steps; print its memory (:func:`report`).

    ``workers`` persistent loader workers (0: loading in this process); the synthetic set is rendered into the run
    folder, or read from ``root``. The run folder (its data, checkpoints and logs) is ``out``, kept, or a temporary
    folder removed when the fit ends.
    """
    from dapm_lightning.training.lightning_cli import run_lightning_cli

    warnings.filterwarnings("ignore", message="LightningCLI's args parameter")  # the CLI called from Python
    with contextlib.ExitStack() as stack:
        folder = out or stack.enter_context(tempfile.TemporaryDirectory())
        cli = run_lightning_cli([
            "fit", "--config", str(QUICKSTART), "--trainer.default_root_dir", str(Path(folder) / "run"),
            "--trainer.max_epochs", str(epochs), "--trainer.enable_progress_bar", "false",
            "--trainer.enable_model_summary", "false", "--trainer.callbacks+=benchmarks.callbacks.FitMemoryProbe",
            "--data.init_args.root", root or str(Path(folder) / "data"), "--data.init_args.train_size", str(train),
            "--data.init_args.val_size", str(val), "--data.init_args.image_size", str(size),
            "--data.init_args.batch_size", str(batch), "--data.init_args.num_workers", str(workers),
            "--data.init_args.persistent_workers", "true"])
        probe = next(c for c in cli.trainer.callbacks if isinstance(c, FitMemoryProbe))
    if out is None:
        print(f"(the files named above were in {folder}, removed now: --out DIR keeps the run)")
    report(probe, warmup)
    return probe


def report(probe: FitMemoryProbe, warmup: int) -> None:
    """Print the samples every few epochs, the growth after ``warmup`` epochs and its projection."""
    samples = probe.samples
    shown = sorted({0, *range(warmup - 1, len(samples), max(1, len(samples) // 8)), len(samples) - 1})
    print(f"{'epoch':>6}{'step':>7}{'main RSS MiB':>14}{'workers PSS MiB':>17}{'workers':>9}")
    for i in (i for i in shown if 0 <= i < len(samples)):
        row = samples[i]
        print(f"{row['epoch']:>6}{row['step']:>7}{row['main_mb']:>14.1f}{row['workers_mb']:>17.1f}{row['workers']:>9}")
    restarted = len(probe.worker_sets) - 1
    seen = any(probe.worker_sets)
    if seen:
        print(f"loader workers replaced {restarted} time(s) over {len(samples)} epochs"
              + (" (persistent: the same processes throughout)" if restarted == 0 else ""))
    else:  # not "persistent" nor "flat" when nothing was measured
        print("no loader worker was seen (--workers 0, or no /proc/PID/task/*/children on this system): the workers' "
              "memory is not measured")
    measured = [("main_mb", "training process")] + ([("workers_mb", "loader workers")] if seen else [])
    for key, what in measured:
        floors = quarter_floors(samples, key, warmup)
        slope = rise_per_1000_steps(floors, 2)
        verdict = growth_verdict(slope, rise_per_1000_steps(floors, 0))
        print(f"{what}: median MiB in each quarter after epoch {warmup}: "
              f"{', '.join(f'{floor:.1f}' for _, floor in floors) or '-'}; {slope:+.2f} MiB per 1000 steps in the "
              f"last ({verdict}; {slope * PAPER_STEPS / 1000:+.0f} MiB over the paper's {PAPER_STEPS} steps)")


def main(argv: list[str] | None = None) -> None:
    """``python -m benchmarks.bench_fit_memory [--epochs N ...]``."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--epochs", type=int, default=60)
    parser.add_argument("--train", type=int, default=64, help="training images (steps per epoch: train // batch)")
    parser.add_argument("--val", type=int, default=16)
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2, help="persistent loader workers (0: none)")
    parser.add_argument("--warmup", type=int, default=5, help="epochs left out of the growth (allocator warm-up)")
    parser.add_argument("--out", help="a folder to keep the run in (data, checkpoints, logs); default: a temporary one")
    args = parser.parse_args(argv)
    if args.epochs < args.warmup + 4:  # a sample, at least, in each quarter after the warm-up
        parser.error(f"--epochs must exceed --warmup by at least 4 (got {args.epochs} and {args.warmup})")
    run(args.epochs, args.train, args.val, args.size, args.batch, args.workers, args.warmup, out=args.out)


if __name__ == "__main__":
    main()
