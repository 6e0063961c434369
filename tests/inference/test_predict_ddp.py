"""predict under 2-process DDP (gloo): every image once, each process its own files, one merged poses table."""

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
    with (out / "poses.csv").open() as handle:  # one table of both processes' images
        names = [row["name"] for row in csv.DictReader(handle)]
    assert names == sorted(f"im{k}" for k in range(len(shapes)))  # each image exactly once, in name order
    assert not list(out.glob("poses_rank*")) and (out / "contact_sheet.png").is_file()
    for k, shape in enumerate(shapes):
        assert np.load(out / f"im{k}_depth.npy").shape == shape
    said = result.stdout + result.stderr
    assert said.count("predicted") == 1 and "predicted 7 images" in said and "(2 processes)" in said, said[-2000:]
