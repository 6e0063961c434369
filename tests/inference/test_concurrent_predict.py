"""Two ``dapm-lightning predict`` processes into one folder at once: every row kept, both tables agree.

Each process runs the one-line command; both are held at the poses table until the other is there too (the
moment two runs of a flight finish together), then merge their rows into a 300,000-row table.
"""

import contextlib
import csv
import json
import multiprocessing
import threading

import cv2
import numpy as np
import pytest

pytestmark = pytest.mark.slow  # two processes, each loading torch and the model


def predict_meeting_at_the_table(argv, barrier, log):
    """``dapm-lightning predict ARGV``, held before the poses table until the other run reaches it too."""
    from dapm_lightning import cli
    from dapm_lightning.inference import writers

    merge = writers.write_poses

    def together(*args, **kwargs):
        with contextlib.suppress(threading.BrokenBarrierError):
            barrier.wait(timeout=300)
        return merge(*args, **kwargs)

    writers.write_poses = together
    with open(log, "w") as handle, contextlib.redirect_stdout(handle), contextlib.redirect_stderr(handle):
        cli.main(argv)


def test_two_predicts_into_one_folder_keep_every_row(checkpoint, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    earlier = [f"old{k:06d},{20 + k % 50},-45.5,1.25,72" for k in range(300_000)]
    (out / "poses.csv").write_text("name,height_m,pitch_deg,roll_deg,fov_deg\n" + "\n".join(earlier) + "\n")
    rng = np.random.default_rng(0)
    commands = []
    for run in ("a", "b"):
        folder = tmp_path / f"flight_{run}"
        folder.mkdir()
        for k in range(32):
            cv2.imwrite(str(folder / f"{run}{k:02d}.png"), rng.integers(0, 255, (40, 60, 3), np.uint8))
        commands.append(["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(out),
                         "--device", "cpu", "--outputs", "depth_npy", "--contact_sheet", "0", "--exist_ok"])
    spawn = multiprocessing.get_context("spawn")
    barrier = spawn.Barrier(2)
    logs = [tmp_path / f"run_{run}.log" for run in "ab"]
    runs = [spawn.Process(target=predict_meeting_at_the_table, args=(c, barrier, log))
            for c, log in zip(commands, logs)]
    for process in runs:
        process.start()
    for process, log in zip(runs, logs):
        process.join(timeout=600)
        assert process.exitcode == 0, log.read_text()[-3000:]
        summary = log.read_text().strip().splitlines()[-1]
        assert summary == f"predicted 32 images: depth_npy per image; poses.csv in {out}/"
    with (out / "poses.csv").open(newline="") as handle:
        table = list(csv.DictReader(handle))
    names = [row["name"] for row in table]
    assert len(names) == len(set(names)) == 300_000 + 64
    assert [",".join(row.values()) for row in table[:300_000]] == earlier  # every earlier row, as it was
    assert sorted(names[300_000:]) == sorted(f"{run}{k:02d}" for run in "ab" for k in range(32))
    assert all(len(row) == 5 and None not in row and float(row["fov_deg"]) > 0 for row in table)  # no garbage
    poses = json.loads((out / "poses.json").read_text())
    assert [p["name"] for p in poses] == names  # the JSON table is the CSV's
    assert poses[300_000 + 5]["height_m"] == float(table[300_000 + 5]["height_m"])
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == [".dapm_predict"]  # no lock or temp file
