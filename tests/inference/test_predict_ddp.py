"""predict under 2-process DDP (gloo): every image once, each process its own files and poses table."""

import csv
import subprocess
import sys

import cv2
import numpy as np
import pytest

pytestmark = pytest.mark.slow  # multi-process run: `make test-all`


def test_two_processes_predict_every_image_once(checkpoint, tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(0)
    shapes = [(40, 60), (40, 60), (60, 40), (48, 48), (40, 60), (30, 90), (48, 48)]
    for k, shape in enumerate(shapes):
        cv2.imwrite(str(folder / f"im{k}.png"), rng.integers(0, 255, (*shape, 3), np.uint8))
    out = tmp_path / "out"
    result = subprocess.run(
        [sys.executable, "-m", "dapm_lightning", "predict", "--config", "configs/predict.yaml",
         "--ckpt_path", str(checkpoint), "--data.init_args.source", str(folder),
         "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
         "--trainer.accelerator", "cpu", "--trainer.devices", "2", "--trainer.strategy", "ddp",
         "--trainer.callbacks.output_dir", str(out), "--trainer.callbacks.outputs", "[depth_npy]"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    names = []
    for rank in (0, 1):
        with (out / f"poses_rank{rank}.csv").open() as handle:
            rows = [row["name"] for row in csv.DictReader(handle)]
        assert rows, f"process {rank} predicted nothing"
        names += rows
    assert sorted(names) == sorted(f"im{k}" for k in range(len(shapes)))  # each image exactly once
    for k, shape in enumerate(shapes):
        assert np.load(out / f"im{k}_depth.npy").shape == shape
    assert result.stdout.count("predicted") == 2 and "(process 1 of 2)" in result.stdout
