"""One predict pipeline: the one-line command, the Lightning form and the Python API give the same files."""

import csv
import json

import cv2
import numpy as np
import pytest
import torch

from dapm_lightning.cli import main
from dapm_lightning.data.unlabelled import PredictBatch, PredictInput
from dapm_lightning.inference.inputs import PredictSource, predict_loader
from dapm_lightning.inference.predictor import DAPMPredictor
from dapm_lightning.inference.writers import PredictionFiles
from dapm_lightning.models.prior import PriorSettings

OUTPUTS = ["depth_npy", "sky", "camera", "points", "npz"]


@pytest.fixture()
def mixed_flight(tmp_path):
    """Images of four sizes and aspects, with a telemetry CSV for some of them."""
    folder = tmp_path / "flight"
    folder.mkdir()
    rng = np.random.default_rng(7)
    for name, shape in (("a", (40, 60)), ("b", (48, 48)), ("c", (30, 50)), ("d", (40, 60)), ("e", (64, 36))):
        cv2.imwrite(str(folder / f"{name}.png"), rng.integers(0, 255, (*shape, 3), np.uint8))
    table = tmp_path / "flight.csv"
    table.write_text("name,height_m,pitch_deg,roll_deg,fov_deg\na.png,45.5,-35,2.5,70\nb,,-60,,\nd,30,,,\n")
    return folder, table


def files_of(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.parametrize("telemetry", [False, True])
def test_the_three_forms_write_bit_identical_files(checkpoint, mixed_flight, tmp_path, monkeypatch, telemetry):
    folder, table = mixed_flight
    flight_args = ["--telemetry", str(table)] if telemetry else []
    one_line = tmp_path / "one_line"
    main(["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(one_line), "--device", "cpu",
          "--batch_size", "2", "--outputs", *OUTPUTS, *flight_args])

    monkeypatch.chdir(tmp_path)  # the package's configs/predict.yaml; LightningCLI writes its config here
    lightning = tmp_path / "lightning"
    main(["predict", "--config", "configs/predict.yaml", "--ckpt_path", str(checkpoint),
          "--data.init_args.source", str(folder), "--data.init_args.batch_size", "2",
          "--data.init_args.num_workers", "0", "--trainer.callbacks.output_dir", str(lightning),
          "--trainer.callbacks.outputs", f"[{', '.join(OUTPUTS)}]",
          *(["--data.init_args.telemetry", str(table)] if telemetry else [])])

    api = tmp_path / "api"
    predictor = DAPMPredictor.from_checkpoint(checkpoint, batch_size=2)
    files = PredictionFiles(api, OUTPUTS)
    for prediction in predictor.predict_source(folder, keep_rgb=True, telemetry=table if telemetry else None):
        files.add(prediction)
    files.finish()

    expected = files_of(one_line)
    assert len([n for n in expected if n.endswith("_depth.npy")]) == 5
    assert files_of(lightning) == expected and files_of(api) == expected
    sources = (one_line / "poses.csv").read_text()
    assert ("telemetry" in sources) == telemetry


def test_one_loader_batches_by_size_with_the_runs_prior_settings(mixed_flight):
    folder, table = mixed_flight
    settings = PriorSettings("both", (3.0, 1.0, 1.0, 2.0))
    batches = list(predict_loader(PredictSource(folder, telemetry=table), 64, settings, batch_size=4))
    assert [b.names for b in batches] == [["a", "d"], ["b"], ["c"], ["e"]]  # grouped by network size, file order
    first = batches[0]
    assert isinstance(first, PredictBatch) and first.mode == "both" and first.images.dtype == torch.uint8
    assert first.sizes == [(40, 60), (40, 60)] and first.images.shape == (2, 3, 43, 64)
    assert first.prior is not None and torch.equal(first.prior.sigma[0], torch.tensor([3.0, 1.0, 1.0, 2.0]))
    assert first.prior.value[0, 0] == 45.5 and first.prior.value[1, 0] == 30.0 and first.prior.value[1, 1].isnan()
    assert batches[2].prior is None  # nothing known of c: no prior
    assert batches[1].network_prior is batches[1].prior  # "both": the network is given it
    scale_only = PredictBatch.collate([PredictInput(first.images[0], "a", (40, 60), prior=first.prior.value[0])],
                                      PriorSettings("scale"))
    assert scale_only.prior is not None and scale_only.network_prior is None  # applied after the network only
    with pytest.raises(ValueError, match="one network size"):
        PredictBatch.collate([PredictInput(torch.zeros(3, 32, 32, dtype=torch.uint8), "x", (32, 32)),
                              PredictInput(torch.zeros(3, 32, 64, dtype=torch.uint8), "y", (32, 64))])


def test_the_poses_table_keeps_the_pose_order_then_sources_provenance_and_network_values(checkpoint, mixed_flight,
                                                                                          tmp_path):
    folder, table = mixed_flight
    out = tmp_path / "out"
    main(["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(out), "--device", "cpu",
          "--telemetry", str(table), "--outputs", "camera"])
    with (out / "poses.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    fields = ["height_m", "pitch_deg", "roll_deg", "fov_deg"]
    assert list(rows[0]) == ["name", *fields, *(f"{f}_{kind}" for kind in ("source", "provenance", "network")
                                                 for f in fields)]
    first = {row["name"]: row for row in rows}["a"]
    assert first["height_m_source"] == "telemetry" and first["height_m_provenance"] == "flight.csv line 2"
    assert first["roll_deg_source"] == "telemetry" and first["roll_deg_provenance"] == "flight.csv line 2"
    assert {row["name"]: row for row in rows}["c"]["height_m_source"] == "network"


def test_video_rows_carry_the_frame_time(checkpoint, tmp_path):
    from tests.inference.test_predict import write_video

    video = write_video(tmp_path / "clip.avi", frames=6)  # 10 frames per second
    out = tmp_path / "out"
    main(["predict", str(video), "--ckpt_path", str(checkpoint), "--out", str(out), "--device", "cpu",
          "--frame_step", "2", "--outputs", "camera"])
    with (out / "poses.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0])[:2] == ["name", "time_s"]
    assert [(row["name"], float(row["time_s"])) for row in rows] == [
        ("clip_f000000", 0.0), ("clip_f000002", 0.2), ("clip_f000004", 0.4)]
    camera = json.loads((out / "clip_f000004_camera.json").read_text())
    assert camera["time_s"] == 0.4
