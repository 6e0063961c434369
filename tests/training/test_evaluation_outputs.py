"""`dapm-lightning test` writes the per-stage bins maps and a per-image CSV (EvaluationOutputWriter)."""

import csv
from pathlib import Path

import cv2
import lightning as L
import numpy as np
import torch

from dapm_lightning.data import parse_uapd_filename
from dapm_lightning.data.datamodules import UAPDDataModule
from dapm_lightning.geometry import encode_log_depth, ideal_ground_depth
from dapm_lightning.models import DAPMConfig
from dapm_lightning.training.evaluation_outputs import EvaluationOutputWriter
from dapm_lightning.training.module import DAPMModule


def test_writer_writes_stage_maps_and_per_image_rows(tiny_uapd, tmp_path):
    net = DAPMConfig(backbone="resnet18", decoder_channels=16, head_channels=8, igd_channels=4, pose_hidden=16)
    model = DAPMModule(net=net)
    data = UAPDDataModule(root=str(tiny_uapd), test_split="val", batch_size=2, num_workers=0, pin_memory=False,
                          persistent_workers=False)
    writer = EvaluationOutputWriter(dirpath=str(tmp_path / "out"))
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


def test_writer_writes_the_igd_of_the_predicted_and_true_pose(tiny_uapd, tmp_path):
    """maps/igd_true is the paper IGD of the pose in the file name as 8-bit grey; igd_pred that of the prediction."""
    net = DAPMConfig(backbone="resnet18", decoder_channels=16, head_channels=8, igd_channels=4, pose_hidden=16,
                     igd={"model": "paper"})
    model = DAPMModule(net=net)
    data = UAPDDataModule(root=str(tiny_uapd), test_split="val", batch_size=2, num_workers=0, pin_memory=False,
                          persistent_workers=False)
    trainer = L.Trainer(accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False,
                        callbacks=[EvaluationOutputWriter(dirpath=str(tmp_path / "out"), write_csv=True)],
                        default_root_dir=str(tmp_path))
    trainer.test(model, datamodule=data)
    rows = {r["name"]: r for r in csv.DictReader(open(tmp_path / "out" / "per_image.csv"))}
    data.setup("test")
    assert sorted(rows) == sorted(Path(n).stem for n in data.make_dataset("val", train=False).names)  # not none
    for name, row in rows.items():
        true = cv2.imread(str(tmp_path / "out" / "maps" / "igd_true" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        pred = cv2.imread(str(tmp_path / "out" / "maps" / "igd_pred" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        pose = parse_uapd_filename(name)
        # the true pose exactly; the predicted one as the CSV prints it (float32: a grey level may round apart)
        for image, values, tolerance in ((true, [pose[k] for k in ("height", "pitch", "roll", "fov")], 0),
                                         (pred, [float(row[f"pred_{k}"]) for k in ("height", "pitch", "roll", "fov")],
                                          1)):
            igd = ideal_ground_depth(torch.tensor(values, dtype=torch.float64), image.shape, model="paper")
            expected = (encode_log_depth(igd, 1000.0)[0, 0] * 255).round().numpy()
            assert np.abs(image.astype(float) - expected).max() <= tolerance, name
