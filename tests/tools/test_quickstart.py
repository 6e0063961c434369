"""The quickstart's report: the model beside its baselines and beside itself given telemetry."""

import json
from pathlib import Path

import cv2

from dapm_lightning.tools.quickstart import ROWS, baselines, report, with_telemetry


def test_report_has_a_telemetry_column_from_the_real_model(checkpoint, tiny_uapd):
    telemetry = with_telemetry(str(checkpoint), tiny_uapd)
    assert {"d1", "abs_rel", "rmse"} <= set(telemetry["depth"]) and "height_median" in telemetry["pose"]
    # the pose used is the noisy telemetry (sigma 3 m in height): far closer than an untrained network
    assert telemetry["pose"]["height_median"] < 6.0 and telemetry["pose"]["pitch_median"] < 3.0
    base = baselines(tiny_uapd)
    model = {"depth": dict(base["depth"]), "pose": dict(base["pose"])}
    table, failures = report(model, base, telemetry)
    header, *rows = table.splitlines()
    assert header.split()[-1] == "+telem." and len(rows) == len(ROWS) + 1
    depth_d1 = next(r for r in rows if r.startswith("depth d1"))
    assert depth_d1.split()[-1] == f"{telemetry['depth']['d1']:.3f}"
    assert "depth d1" in failures  # equal to the baseline is not beating it


def test_a_trained_checkpoint_is_tested_without_training(checkpoint, tmp_path, capsys):
    from dapm_lightning.data.uapd import UAPDDataset
    from dapm_lightning.tools.quickstart import main
    from dapm_lightning.training.checkpoint_files import split_checkpoint

    folder = tmp_path / "model"
    split_checkpoint(checkpoint, folder, part_bytes=1 << 20, card={"image_size": 32})
    out = tmp_path / "demo"
    code = main(["--out", str(out), "--checkpoint", str(folder), "--train-size", "4", "--val-size", "4",
                 "--render-seed", "3"])
    printed = capsys.readouterr().out
    summary = json.loads((out / "metrics.json").read_text())
    assert code == (0 if summary["beats_baselines"] else 1)
    data = Path(summary["data"]["root"])
    assert data == out / "data_32_seed3" and len(UAPDDataset(data, "val")) == 4  # the card's size, a new seed
    assert UAPDDataset(data, "val")[0]["image"].shape[-2:] == (32, 32)
    panel = cv2.imread(str(out / "panels" / "test_val.png"))
    assert panel is not None and panel.shape[0] >= 4 * 32  # one row per image
    assert f"{summary['model']['depth']['d1']:9.3f}" in printed and "+telem." in printed
    assert summary["with_telemetry"]["pose"]["height_median"] < 6.0  # the noisy telemetry's pose, used
    assert "(no training)" in printed and not (out / "tensorboard").exists()


def test_a_missing_checkpoint_stops_before_rendering(tmp_path):
    import pytest

    from dapm_lightning.tools.quickstart import main

    with pytest.raises(FileNotFoundError, match="nope: no such checkpoint file or folder"):
        main(["--out", str(tmp_path / "demo"), "--checkpoint", str(tmp_path / "nope")])
    assert not (tmp_path / "demo").exists()


def test_a_zero_baseline_shows_no_ratio():
    """A figure of 0 (an AUC no baseline pose reaches) has no ratio: a dash, not `nanx` or `infx`."""
    model = {group: {name: 0.5 for g, name, _ in ROWS if g == group} for group, _, _ in ROWS}
    base = {group: {name: 0.0 for g, name, _ in ROWS if g == group} for group, _, _ in ROWS}
    table, _ = report(model, base)
    assert "nan" not in table and "inf" not in table
    assert all(line.rstrip().endswith("-") for line in table.splitlines()[2:])


def test_a_second_run_in_the_same_folder_names_its_own_outputs(tmp_path):
    """`make demo` twice: the second run logs to new version folders; the listing names those, not the first's."""
    from dapm_lightning.tools.quickstart import outputs_listing

    runs = tmp_path / "tensorboard"
    for name in ("version_0/panels/val.png", "version_1/panels/test_val.png", "version_1/viewpoints.png",
                 "version_2/panels/val.png", "version_10/panels/test_val.png", "version_10/viewpoints.png"):
        (runs / name).parent.mkdir(parents=True, exist_ok=True)
        (runs / name).write_bytes(b"png")
    checkpoint = runs / "version_2" / "checkpoints" / "best-epoch=3.ckpt"
    listing = "\n".join(outputs_listing(tmp_path, runs / "version_2", runs / "version_10", checkpoint))
    assert "version_0" not in listing and "version_1/" not in listing and "version_1," not in listing
    assert "tensorboard/version_10/viewpoints.png" in listing
    assert "tensorboard/version_2/panels, tensorboard/version_10/panels: 2 picture(s)" in listing
    assert "tensorboard/version_2, tensorboard/version_10: logs of the fit and the test" in listing
    assert "tensorboard/version_2/checkpoints/best-epoch=3.ckpt: the checkpoint tested" in listing


def test_a_checkpoint_file_is_tested_at_its_training_size_and_zero_counts_are_refused(checkpoint, tmp_path, capsys):
    """`make demo CKPT=best.ckpt` of a model trained at 256 was tested on 64² renders: only a split folder's card was
    read. 0 epochs or images silently meant the config's (a full 12-epoch run)."""
    import pytest

    from dapm_lightning.tools.quickstart import checkpoint_image_size, main
    from dapm_lightning.training.checkpoint_files import read_checkpoint
    from dapm_lightning.training.module import training_image_size

    trained = training_image_size(read_checkpoint(checkpoint))
    assert trained is not None and checkpoint_image_size(str(checkpoint)) == max(trained) != 64
    assert checkpoint_image_size(str(tmp_path / "nope.ckpt")) == 64
    for args in (["--max-epochs", "0"], ["--train-size", "0"], ["--image-size", "32"]):
        with pytest.raises(SystemExit) as info:
            main(["--out", str(tmp_path / "demo"), *args])
        assert info.value.code == 2
    assert "--image-size is for --checkpoint" in capsys.readouterr().err
    assert not (tmp_path / "demo").exists()
