"""Runs never mix: a new folder per run by default, a folder with files refused unless --exist_ok."""

import cv2
import numpy as np
import pytest

from dapm_lightning.cli import main
from dapm_lightning.inference.predictor import DAPMPredictor
from dapm_lightning.inference.run_folder import new_run_folder, remove_stale_files
from tests.conftest import run_main


@pytest.fixture()
def two_images(tmp_path):
    folder = tmp_path / "flight"
    folder.mkdir()
    for name, value in (("a", 60), ("b", 120)):
        cv2.imwrite(str(folder / f"{name}.png"), np.full((30, 40, 3), value, np.uint8))
    return folder


def test_each_run_gets_a_new_folder_by_default(checkpoint, two_images, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert new_run_folder() == tmp_path.joinpath("runs", "predict").relative_to(tmp_path)
    for folder in ("runs/predict", "runs/predict2"):
        main(["predict", str(two_images), "--ckpt_path", str(checkpoint), "--device", "cpu", "--outputs", "camera"])
        assert capsys.readouterr().out.strip().endswith(f"in {folder}/")
        assert sorted(p.name for p in (tmp_path / folder).glob("*_camera.json")) == ["a_camera.json", "b_camera.json"]
    (tmp_path / "runs" / "predict3").mkdir()  # an empty folder is taken
    assert str(new_run_folder()) == "runs/predict3"


def test_a_folder_with_files_is_refused_unless_exist_ok(checkpoint, two_images, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")

    def no_model(*args, **kwargs):
        raise AssertionError("the model was loaded")

    with monkeypatch.context() as patch:
        patch.setattr(DAPMPredictor, "from_checkpoint", no_model)
        code, err = run_main(["predict", str(two_images), "--ckpt_path", str(checkpoint), "--out", str(out)], capsys)
    assert code == 1 and err.splitlines()[0] == (f"error: --out {out} already holds files (an earlier run's?): give a "
                                                 "new folder, leave --out out (a new runs/predict<N> per run), or add "
                                                 "--exist_ok to add to it")
    monkeypatch.chdir(tmp_path)
    code, err = run_main(["predict", "--config", "configs/predict.yaml", "--ckpt_path", str(checkpoint),
                          "--data.init_args.source", str(two_images), "--data.init_args.num_workers", "0",
                          "--trainer.callbacks.output_dir", str(out)], capsys)
    assert code == 1 and "--trainer.callbacks.exist_ok" in err.splitlines()[0]
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_exist_ok_rewrites_all_files_of_an_image_together(checkpoint, two_images, tmp_path, capsys):
    out = tmp_path / "out"
    base = ["--ckpt_path", str(checkpoint), "--out", str(out), "--device", "cpu", "--contact_sheet", "0"]
    main(["predict", str(two_images), *base, "--outputs", "depth_npy", "points", "camera"])
    (two_images / "b.png").unlink()
    main(["predict", str(two_images), *base, "--outputs", "camera", "--exist_ok"])
    # a: this run's camera alone (no earlier depth or cloud beside it); b, not predicted again, keeps its files
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(("a_", "b_"))) == [
        "a_camera.json", "b_camera.json", "b_depth.npy", "b_points.ply"]
    assert remove_stale_files(out, "b", [out / "b_camera.json"]) == [out / "b_depth.npy", out / "b_points.ply"]
