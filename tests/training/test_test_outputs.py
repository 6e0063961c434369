"""`dapm-lightning test` writes the per-stage bins maps and a per-image CSV (TestOutputWriter)."""

import csv
from pathlib import Path

import cv2
import lightning as L
import numpy as np

from dapm_lightning.data.datamodules import UAPDDataModule
from dapm_lightning.models import DAPMConfig
from dapm_lightning.training.module import DAPMModule
from dapm_lightning.training.test_outputs import TestOutputWriter


def test_writer_writes_stage_maps_and_per_image_rows(tiny_uapd, tmp_path):
    net = DAPMConfig(backbone="resnet18", decoder_channels=16, head_channels=8, igd_channels=4, pose_hidden=16)
    model = DAPMModule(net=net)
    data = UAPDDataModule(root=str(tiny_uapd), test_split="val", batch_size=2, num_workers=0, pin_memory=False,
                          persistent_workers=False)
    writer = TestOutputWriter(dirpath=str(tmp_path / "out"))
    trainer = L.Trainer(accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False, callbacks=[writer],
                        default_root_dir=str(tmp_path))
    trainer.test(model, datamodule=data)
    data.setup("test")
    names = sorted(Path(n).stem for n in data.make_dataset("val", train=False).names)
    rows = list(csv.DictReader(open(tmp_path / "out" / "per_image.csv")))
    assert sorted(r["name"] for r in rows) == names
    for row in rows:
        true = [float(row[k]) for k in ("height", "pitch", "roll", "fov")]
        pred = [float(row[f"pred_{k}"]) for k in ("height", "pitch", "roll", "fov")]
        errors = [float(row[f"err_{k}"]) for k in ("height", "pitch", "roll", "fov")]
        assert np.allclose(np.abs(np.subtract(pred, true)), errors, atol=1e-3)
        assert 0.0 <= float(row["depth_d1"]) <= 1.0 and float(row["depth_abs_rel"]) >= 0
    for stage in ("sky", "bins_16", "bins_64", "depth_init", "depth"):
        files = sorted(p.stem for p in (tmp_path / "out" / "maps" / stage).glob("*.png"))
        assert files == names, stage
    bins = cv2.imread(str(tmp_path / "out" / "maps" / "bins_16" / f"{names[0]}.png"), cv2.IMREAD_UNCHANGED)
    assert bins.dtype == np.uint8 and set(np.unique(bins)) <= {round(255 * k / 15) for k in range(16)}
