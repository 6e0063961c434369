"""`bench_fit_memory`: the memory of a fit and its loader workers, epoch by epoch, and its growth."""

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from benchmarks.bench_fit_memory import (
    growth_per_1000_steps,
    growth_verdict,
    main,
    quarter_floors,
    report,
    steady_growth_per_1000_steps,
)
from benchmarks.callbacks import FitMemoryProbe, descendant_pids, proportional_mb


def test_growth_is_how_fast_the_median_rises_at_the_end():
    # a warm-up, a one-off step of 2 MiB, 9 MiB held or given back at some epochs, then 0.4 MiB per 100 steps
    mib = [550.0, 500.0, 502.0, 511.0, 502.0, 502.0, 440.0, 502.4, 502.8, 511.8, 503.2, 503.6, 512.6]
    samples = [{"step": 100 * i, "main_mb": value} for i, value in enumerate(mib)]
    floors = quarter_floors(samples, "main_mb", warmup=1)
    assert floors == [(200.0, 502.0), (500.0, 502.0), (800.0, 502.8), (1100.0, 503.6)]
    assert math.isclose(growth_per_1000_steps(samples, "main_mb", warmup=1), 8 / 3)  # 0.8 MiB over 300 steps
    flat = [{"step": 100 * i, "main_mb": 500.0 + 9 * (i % 3 == 0) - 60 * (i == 7)} for i in range(12)]
    assert growth_per_1000_steps(flat, "main_mb", warmup=0) == 0.0
    assert math.isnan(growth_per_1000_steps(samples, "main_mb", warmup=10))  # three samples left


def test_a_rise_in_the_last_quarter_alone_is_a_step_not_growth(capsys):
    # 0.8 MiB once, late (an allocator's arena): as fast as a leak at the end, not over the whole run
    samples = [{"epoch": i, "step": 16 * i, "main_mb": 1157.4 + 0.8 * (i >= 45), "workers_mb": 760.0, "workers": 6}
               for i in range(60)]
    late = growth_per_1000_steps(samples, "main_mb", warmup=5)
    steady = steady_growth_per_1000_steps(samples, "main_mb", warmup=5)
    assert late > 2 > steady > 0
    assert growth_verdict(late, steady).startswith("a step in the last quarter")
    assert growth_verdict(late, 2.5) == "GROWS" and growth_verdict(1.0, 0.0) == "flat"
    assert growth_verdict(-3.0, -1.0) == "falls" and growth_verdict(float("nan"), 0.0) == "too few epochs to tell"
    probe = FitMemoryProbe()
    probe.samples, probe.worker_sets = samples, [(1, 2)]
    report(probe, warmup=5)
    said = capsys.readouterr().out
    assert "GROWS" not in said and "training process:" in said and "(a step in the last quarter" in said


GRANDCHILD = "import time; x = bytearray(64 << 20); time.sleep(30)"
CHILD = (f"import subprocess, sys, time; print(subprocess.Popen([sys.executable, '-c', {GRANDCHILD!r}]).pid, "
         "flush=True); time.sleep(30)")


def test_descendants_are_found_and_measured_while_alive():
    """As a forkserver's loader workers: started by a process this one started."""
    child = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True)
    grandchild = int(child.stdout.readline())
    try:
        deadline = time.monotonic() + 20
        while proportional_mb(grandchild) < 60 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert {child.pid, grandchild} <= set(descendant_pids()) and proportional_mb(grandchild) >= 60  # its 64 MiB
    finally:
        os.kill(grandchild, signal.SIGKILL)
        child.kill()
        child.wait()
    deadline = time.monotonic() + 10
    while grandchild in descendant_pids() and time.monotonic() < deadline:  # reparented, then reaped by init
        time.sleep(0.1)
    assert not {child.pid, grandchild} & set(descendant_pids()) and proportional_mb(child.pid) == 0.0


def test_report_calls_a_steadily_rising_median_growth(capsys):
    probe = FitMemoryProbe()
    probe.samples = [{"epoch": i, "step": 1000 * i, "main_mb": 900.0, "workers_mb": 300.0 + 5 * i, "workers": 2}
                     for i in range(9)]
    probe.worker_sets = [(11, 12), (13, 14)]
    report(probe, warmup=1)
    said = capsys.readouterr().out
    assert "loader workers replaced 1 time(s) over 9 epochs" in said
    assert "training process: median MiB in each quarter after epoch 1: 900.0, 900.0, 900.0, 900.0; +0.00 MiB per " \
        "1000 steps in the last (flat" in said
    assert "loader workers: median MiB in each quarter after epoch 1: 307.5, 317.5, 327.5, 337.5; +5.00 MiB per 1000 " \
        "steps in the last (GROWS; +160 MiB over the paper's 32000 steps)" in said


def test_a_short_fit_with_persistent_workers_keeps_its_workers(capsys, tmp_path):
    main(["--epochs", "5", "--train", "4", "--val", "2", "--batch", "2", "--workers", "1", "--warmup", "1",
          "--out", str(tmp_path)])
    said = capsys.readouterr().out
    rows = [line.split() for line in said.splitlines() if line.strip() and line.split()[0].isdigit()]
    assert [(row[0], row[1]) for row in rows] == [(str(epoch), str(2 * epoch + 2)) for epoch in range(5)]
    # a training process, and its loader workers (one for training, one for validation) and their forkserver
    assert all(float(row[2]) > 100 and float(row[3]) > 10 and int(row[4]) == int(rows[0][4]) >= 2 for row in rows)
    assert "replaced 0 time(s) over 5 epochs (persistent" in said and "median MiB in each quarter after epoch 1" in said
    named = [line.split(": ", 1)[1] for line in said.splitlines() if line.startswith("last checkpoint (step 10)")]
    assert len(named) == 1 and Path(named[0]).is_file() and "removed now" not in said  # --out keeps what fit names


def test_too_few_epochs_are_refused_and_a_slope_of_one_sample_is_not_called_growth(capsys):
    with pytest.raises(SystemExit):
        main(["--epochs", "4", "--warmup", "1"])
    assert "--epochs must exceed --warmup by at least 4" in capsys.readouterr().err
    probe = FitMemoryProbe()
    probe.samples = [{"epoch": i, "step": i, "main_mb": 1.0, "workers_mb": 0.0, "workers": 0} for i in range(2)]
    probe.worker_sets = [()]
    report(probe, warmup=1)
    said = capsys.readouterr().out
    assert "too few epochs to tell" in said
    # no worker process ever seen: neither "persistent" nor a verdict on memory that was not measured
    assert "no loader worker was seen" in said and "persistent" not in said and "loader workers:" not in said
