"""Shared fixtures: tiny UAPD-format trees written by the project's own generator."""

from __future__ import annotations

import os
import random
import shutil
import signal
import tempfile
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from dapm_lightning.data.synthetic import generate_uapd, render_scene, sample_scene
from dapm_lightning.geometry import MAX_DEPTH_M, depth_to_grey
from dapm_lightning.training.lightning_cli import run_lightning_cli

TINY_HW = (24, 40)  # non-square, so an H/W swap fails


@pytest.fixture(autouse=True)
def _global_rngs_seeded_by_test(request):
    """Each test starts from global RNG states of its own (seeded by its id), whatever ran before it in its process
    or xdist worker: a test drawing without a seed gets the same draws alone, in one process or in any worker."""
    seed = zlib.crc32(request.node.nodeid.encode())
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def _threads_per_worker() -> int | None:
    """Under pytest-xdist (``make test``), the cores shared out among the workers; None in one process."""
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0"))
    if workers < 2:
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return max(1, cores // workers)


# N workers each with every core would run N times more threads than there are cores: this worker's share, for
# torch here and for the processes its tests start
if (_THREADS := _threads_per_worker()) is not None:
    torch.set_num_threads(_THREADS)
    os.environ["OMP_NUM_THREADS"] = str(_THREADS)

# Ctrl-C as in a terminal: a suite started as a background job inherits SIGINT ignored, and so would the processes
# the Ctrl-C tests start; Python's own handler here gives this process and (reset on exec) its children the default
signal.signal(signal.SIGINT, signal.default_int_handler)


SUITE_DISK_GIB = 1.5  # the peak of the fast or the slow tier: checkpoints of 190 MB, a passed test's folder removed
WORKER_DISK_GIB = 0.5  # each pytest-xdist worker past the first (the fast tier's peak: 1.3 GB in one, 1.5 GB in two)


def _free_temporary_disk(config) -> tuple[Path, float]:
    folder = Path(config.option.basetemp or tempfile.gettempdir())
    while not folder.exists():
        folder = folder.parent
    return folder, shutil.disk_usage(folder).free / 2**30


def pytest_report_header(config) -> str:
    folder, free = _free_temporary_disk(config)
    return f"free disk for temporary files ({folder}): {free:.1f} GiB (the suite needs ~{_suite_disk_gib(config):.1f})"


def _suite_disk_gib(config) -> float:
    """The peak for this run: each pytest-xdist worker holds its own session fixtures and running test."""
    workers = int(config.getoption("numprocesses", None) or 1)  # xdist has resolved "auto" to a count here
    return SUITE_DISK_GIB + WORKER_DISK_GIB * (max(1, workers) - 1)


def pytest_configure(config) -> None:
    """Too little disk is named up front: "no space left" failures are then the machine, not the code."""
    if "PYTEST_XDIST_WORKER" in os.environ:
        return  # checked once, by the process that started the workers
    folder, free = _free_temporary_disk(config)
    need = _suite_disk_gib(config)
    if free < need:
        config.issue_config_time_warning(pytest.PytestConfigWarning(
            f"only {free:.1f} GiB free in {folder}; the suite needs ~{need:.1f} GiB at its peak: free space there, "
            "point TMPDIR (or --basetemp) at a larger disk, or test in one process (make test TEST_WORKERS=0)"),
            stacklevel=2)


def write_pair(root: Path, split: str, name: str, pose, seed: int = 0, size=TINY_HW) -> None:
    rgb, depth_m, _ = render_scene(np.asarray(pose, float), size, sample_scene(np.random.default_rng(seed)))
    grey = depth_to_grey(np.where(np.isfinite(depth_m), depth_m, MAX_DEPTH_M))
    (root / split / "rgb").mkdir(parents=True, exist_ok=True)
    (root / split / "depth").mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(root / split / "rgb" / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(root / split / "depth" / name), grey)


@pytest.fixture(scope="session")
def tiny_uapd(tmp_path_factory) -> Path:
    """3 train + 2 val generated images plus one shuffled-token name and one above-horizon pose each."""
    root = tmp_path_factory.mktemp("uapd")
    generate_uapd(root, train=3, val=2, size=TINY_HW, seed=7, workers=1)
    write_pair(root, "train", "yaw_12.5_fov_70_roll_-8.25_Town03_z_45.5_pitch_-60_000777_x_-3.png",
               (45.5, -60.0, -8.25, 70.0), seed=1)
    write_pair(root, "val", "idx_3_pitch_5.0_z_30_fov_90.0_roll_4.png", (30.0, 5.0, 4.0, 90.0), seed=2)
    return root


@pytest.fixture()
def uapd_copy(tiny_uapd, tmp_path) -> Path:
    """A private copy of :func:`tiny_uapd` a test may break."""
    return Path(shutil.copytree(tiny_uapd, tmp_path / "uapd"))


@pytest.fixture(scope="session")
def tiny_potsdam(tmp_path_factory) -> Path:
    """Two Potsdam-named tiles (RGB + float height TIFF), 64x96 each: 12 crops of 32 pixels."""
    root = tmp_path_factory.mktemp("potsdam")
    (root / "rgb").mkdir()
    (root / "height").mkdir()
    rng = np.random.default_rng(0)
    for a, b in ((2, 10), (3, 11)):
        cv2.imwrite(str(root / "rgb" / f"top_potsdam_{a}_{b}_RGB.tif"), rng.integers(0, 255, (64, 96, 3), np.uint8))
        height = (rng.random((64, 96)) * 30).astype(np.float32)
        cv2.imwrite(str(root / "height" / f"dsm_potsdam_{a:02d}_{b:02d}.tif"), height)
    return root


REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
QUICKSTART = REPO / "dapm_lightning" / "configs" / "quickstart.yaml"


def _one_step_quickstart(tiny_uapd: Path, work: Path, *extra: str) -> Path:
    """The quickstart model after one training step on :func:`tiny_uapd` (``extra``: more fit arguments)."""
    cli = run_lightning_cli(["fit", "--config", str(QUICKSTART), "--data.class_path",
                             "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(tiny_uapd),
                             "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
                             "--trainer.max_steps", "1", "--trainer.limit_val_batches", "0",
                             "--trainer.logger", "false", "--trainer.callbacks", "[]",
                             "--trainer.enable_checkpointing", "false", "--trainer.default_root_dir", str(work),
                             *extra])
    path = work / "model.ckpt"
    cli.trainer.save_checkpoint(path)
    return path


@pytest.fixture(scope="session")
def checkpoint(tiny_uapd, tmp_path_factory):
    """The quickstart model (depth relative to the IGD) after one step."""
    return _one_step_quickstart(tiny_uapd, tmp_path_factory.mktemp("predict_ckpt"))


@pytest.fixture(scope="session")
def absolute_checkpoint(tiny_uapd, tmp_path_factory):
    """The quickstart model with the paper's absolute depth read from the head (free to predict beyond the ground),
    after one step."""
    return _one_step_quickstart(tiny_uapd, tmp_path_factory.mktemp("absolute_ckpt"),
                                "--model.net.depth_parametrization", "absolute", "--model.net.depth_readout", "head")




def run_main(args, capsys):
    """``dapm-lightning ARGS`` expected to exit: ``(exit status, stderr)``, and no traceback shown."""
    from dapm_lightning.cli import main

    with pytest.raises(SystemExit) as info:
        main(args)
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return info.value.code, err
