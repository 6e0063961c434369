"""Prediction outputs as a user meets them: nothing lost, nothing faked.

A full disk, an image the encoder refuses, an output folder inside the source or one that cannot be written,
a run that fails before writing, images of extreme aspect, and runs writing one poses table at once.
"""

import csv
import json
import os
import re
import signal
import subprocess
import threading
from collections import Counter

import cv2
import numpy as np
import pytest
import torch

from dapm_lightning.data import files as files_module
from dapm_lightning.data.files import (
    WriteError,
    check_folder_writable,
    exclusive_lock,
    make_folder,
    open_atomic,
    remove_empty_folders,
    write_bytes,
    write_image,
)
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.inference.contact_sheet import (
    CONTACT_HEADING,
    CONTACT_MAX_ASPECT,
    CONTACT_MAX_IMAGES,
    CONTACT_TILE,
    contact_row,
    contact_sheet,
    contact_tiles,
)
from dapm_lightning.inference.poses_table import write_poses
from dapm_lightning.inference.postprocess import make_prediction
from dapm_lightning.inference.predictor import DAPMPredictor
from dapm_lightning.inference.writers import (
    PredictionFiles,
    PredictionWriter,
    check_output_outside_source,
    source_holding,
)
from dapm_lightning.models import DAPMConfig
from dapm_lightning.training.module import DAPMModule
from tests.conftest import run_main

TINY = {"backbone": "resnet18", "decoder_channels": 16, "head_channels": 8, "igd_channels": 4, "pose_hidden": 16,
        "depth_bins": (2, 4), "pose_bins": (4,)}
ROW_MAX_WIDTH = 3 * CONTACT_MAX_ASPECT * CONTACT_TILE + 2 * CONTACT_TILE


def mount_tmpfs(folder, options):
    """Mount a tmpfs on ``folder`` (root only); False where this machine does not allow it."""
    folder.mkdir(parents=True, exist_ok=True)
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(folder)], capture_output=True)
    except FileNotFoundError:
        return False
    return done.returncode == 0


@pytest.fixture()
def small_disk(tmp_path):
    """A 384 KiB file system (a tmpfs), or None where none can be mounted (the tests then fake the failure)."""
    disk = tmp_path / "disk"
    if not mount_tmpfs(disk, "size=384k"):
        yield None
        return
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def fill(disk, leave=0):
    """Fill ``disk`` up to ``leave`` bytes."""
    try:
        with (disk / "filler").open("wb") as handle:
            while True:
                handle.write(b"\0" * 4096)
                handle.flush()
    except OSError:
        pass
    if leave:
        size = (disk / "filler").stat().st_size
        with (disk / "filler").open("r+b") as handle:
            handle.truncate(max(0, size - leave))


@pytest.fixture()
def flight(tmp_path):
    folder = tmp_path / "flight"
    folder.mkdir()
    rng = np.random.default_rng(3)
    for k in range(48):
        cv2.imwrite(str(folder / f"im{k:02d}.png"), rng.integers(0, 255, (40, 60, 3), np.uint8))
    return folder


def assert_whole(folder, earlier=None):
    """Every file in ``folder`` is complete: no empty or temporary file, each image and array readable."""
    names = sorted(p.name for p in folder.iterdir())
    assert not [n for n in names if n.startswith(".") and n != ".dapm_predict"], names  # no temporary or lock file
    for path in folder.iterdir():
        assert path.stat().st_size > 0, path
        if path.suffix in (".png", ".tif"):
            assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED) is not None, path
        elif path.suffix == ".npy":
            np.load(path)
        elif path.suffix == ".json":
            json.loads(path.read_text())
        elif path.name == "poses.csv" and earlier is not None:
            assert path.read_text() == earlier  # the earlier table, untouched
    return names


# ------------------------------------------------------------------------------------------------- the file helper
def test_a_failed_write_leaves_the_earlier_file_and_no_temporary_file(tmp_path):
    target = write_bytes(tmp_path / "table.csv", b"earlier\n")
    with pytest.raises(RuntimeError), open_atomic(target, "w") as handle:
        handle.write("half a ta")
        raise RuntimeError("the writer stops half-way")
    assert target.read_bytes() == b"earlier\n" and sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]
    with pytest.raises(WriteError, match=r"missing/x.png: cannot be written \(its folder .* does not exist\)"):
        write_image(tmp_path / "missing" / "x.png", np.zeros((4, 4), np.uint8))
    # OpenCV returns False, it does not raise: a row libpng refuses (over 1,000,000 pixels) is an error here
    with pytest.raises(WriteError, match=r"wide.png: cannot be written \(OpenCV cannot encode a 2x1100000x3 uint8"):
        write_image(tmp_path / "wide.png", np.zeros((2, 1_100_000, 3), np.uint8))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]
    error = WriteError(tmp_path / "x", "why")
    assert isinstance(error, OSError) and isinstance(error, ValueError)  # a user's error: a message, no traceback


def test_a_long_name_of_multibyte_characters_is_written_as_a_plain_write_would(tmp_path):
    """A name that fits NAME_MAX in bytes (78 CJK characters + .csv: 238 bytes): its temporary name fits too."""
    target = tmp_path / ("深度" * 39 + ".csv")
    assert len(target.name.encode()) == 238
    write_bytes(target, b"rows\n")
    assert target.read_bytes() == b"rows\n" and [p.name for p in tmp_path.iterdir()] == [target.name]
    ascii_name = tmp_path / ("a" * 250 + ".csv")
    write_bytes(ascii_name, b"x")
    assert ascii_name.read_bytes() == b"x"


def test_the_table_lock_is_exclusive_and_leaves_no_file(tmp_path):
    table = tmp_path / "poses.csv"
    inside, most = [0], [0]

    def hold():
        for _ in range(20):
            with exclusive_lock(table):
                inside[0] += 1
                most[0] = max(most[0], inside[0])
                threading.Event().wait(0.001)
                inside[0] -= 1

    threads = [threading.Thread(target=hold) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert most[0] == 1 and list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------------------------------- one table, many runs
def test_runs_writing_one_poses_table_at_once_keep_every_row(tmp_path):
    """Four runs merge their rows into a 20,000-row table at once: every earlier and new row is kept."""
    earlier = [{"name": f"old{k:05d}", "height_m": 10 + k % 7, "pitch_deg": -40, "roll_deg": 1, "fov_deg": 70}
               for k in range(20_000)]
    write_poses(tmp_path, earlier)
    before = (tmp_path / "poses.csv").read_text().splitlines()
    start = threading.Barrier(4)
    errors = []

    def run(k):
        rows = [{"name": f"run{k}_{i:02d}", "height_m": 50.0 + i, "pitch_deg": -30.0, "roll_deg": 0.5,
                 "fov_deg": 80.0} for i in range(32)]
        start.wait()
        try:
            write_poses(tmp_path, rows)
        except Exception as error:  # noqa: BLE001
            errors.append(error)

    threads = [threading.Thread(target=run, args=(k,)) for k in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    lines = (tmp_path / "poses.csv").read_text().splitlines()
    assert lines[:len(before)] == before  # every earlier row, unchanged and in order
    names = [line.split(",")[0] for line in lines[len(before):]]
    assert sorted(names) == sorted(f"run{k}_{i:02d}" for k in range(4) for i in range(32))
    with (tmp_path / "poses.csv").open(newline="") as handle:
        table = list(csv.DictReader(handle))
    assert [row["name"] for row in json.loads((tmp_path / "poses.json").read_text())] == [r["name"] for r in table]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["poses.csv", "poses.json"]  # no lock or temporary file


def test_poses_json_keeps_names_that_look_like_numbers_as_names(tmp_path):
    """Frames named 000123 or by their time (20230514_101502, which float() reads as a number) keep their names in
    poses.json, merged rows included; the pose values stay numbers."""
    rows = [{"name": name, "height_m": 50.0, "pitch_deg": -30.0, "roll_deg": 0.5, "fov_deg": 80.0,
             "height_m_source": "telemetry", "height_m_provenance": "1e3", "height_m_network": 48.0}
            for name in ("000123", "20230514_101502", "nan")]
    write_poses(tmp_path, rows[:2])
    write_poses(tmp_path, rows[2:])  # the first two merged back from poses.csv, as text
    table = json.loads((tmp_path / "poses.json").read_text())
    assert [row["name"] for row in table] == ["000123", "20230514_101502", "nan"]
    assert {row["height_m_provenance"] for row in table} == {"1e3"}
    assert all(row["pitch_deg"] == -30.0 and row["height_m_network"] == 48.0 for row in table)
    write_poses(tmp_path, [{"name": "frame", "time_s": 1.5, "height_m": 40.0, "pitch_deg": -20.0, "roll_deg": 0.0,
                            "fov_deg": 70.0}])  # a video frame without telemetry beside images with it
    table = json.loads((tmp_path / "poses.json").read_text())
    assert len({tuple(row) for row in table}) == 1  # every row has every column, as poses.csv
    assert table[-1]["height_m_provenance"] == "" and table[-1]["height_m_source"] == "network"
    assert table[0]["time_s"] is None and table[-1]["time_s"] == 1.5  # an empty number is null, not ""


def test_a_telemetry_row_gives_the_networks_own_pose_beside_the_pose_used():
    from dapm_lightning.inference.poses_table import pose_row
    from dapm_lightning.inference.postprocess import CameraPose, Prediction

    used, own = CameraPose(45.5, -35.0, 2.5, 70.0), CameraPose(38.25, -31.0, 1.0, 66.5)
    row = pose_row(Prediction(None, None, used, name="a", pose_network=own,
                              pose_source={"height": "telemetry", "pitch": "fused", "roll": "network",
                                           "fov": "network"}, pose_provenance={"height": "f.csv line 2"}))
    assert [row[k] for k in ("height_m", "height_m_network", "pitch_deg", "pitch_deg_network")] == [
        45.5, 38.25, -35.0, -31.0]
    assert row["height_m_source"] == "telemetry" and row["height_m_provenance"] == "f.csv line 2"
    assert row["roll_deg_source"] == "network" and row["roll_deg_provenance"] == ""


# --------------------------------------------------------------------------------------------------- a full disk
def test_a_full_disk_fails_the_run_naming_the_file_and_keeps_the_table(checkpoint, flight, small_disk, capsys,
                                                                        monkeypatch):
    """48 images into a disk with room for a few: exit 1 naming the file, no empty file, the earlier rows kept and
    the images written before the failure added where the disk still takes the table."""
    if small_disk is None:  # no tmpfs here: the encoder's False return stands for the full disk
        out = flight.parent / "out"
        calls, encode = [0], cv2.imencode  # the encoder itself, not this stand-in once it is patched in

        def refuse_after_ten(ext, image, *args):
            calls[0] += 1
            return (False, None) if calls[0] > 10 else encode(ext, image, *args)

        monkeypatch.setattr(files_module.cv2, "imencode", refuse_after_ten)
    else:
        out = small_disk / "out"
    out.mkdir()
    earlier = "name,height_m,pitch_deg,roll_deg,fov_deg\n" + "".join(f"old{k},50,-40,1,70\n" for k in range(100))
    (out / "poses.csv").write_text(earlier)
    code, err = run_main(["predict", str(flight), "--ckpt_path", str(checkpoint), "--out", str(out),
                          "--device", "cpu", "--batch_size", "8", "--exist_ok"], capsys)
    lines = err.splitlines()
    message = lines[next(k for k, line in enumerate(lines) if line.startswith("error: ")):]
    assert code == 1 and message[0].startswith(f"error: {out}/im") and ": cannot be written (" in message[0]
    assert message[1].startswith("Fix: ") and "--out" in message[1]
    if small_disk is not None:
        assert "No space left on device" in message[0] and "free space" in message[1]
    kept = lines[lines.index(message[0]) - 1]  # what the run kept, and what the disk refused
    assert kept.startswith("stopped early by the error below: predicted ") and f"in {out}/" in kept
    names = assert_whole(out)
    assert 1 < len(names) < 48 * 7  # some images were written, whole; the run stopped at the first failure
    assert "predicted" not in capsys.readouterr().out
    table = (out / "poses.csv").read_text()
    assert table.startswith(earlier)  # every earlier row kept, in order
    if small_disk is None or table != earlier:  # the disk took the table: it names the images written, no others
        written = {p.name[:-len("_camera.json")] for p in out.glob("*_camera.json")}
        if not (out / "poses.json").exists():  # poses.csv fitted, poses.json not: the run says so
            assert "could not be updated: the poses tables (poses.csv, poses.json)" in kept, kept
            assert set(re.findall(r"^(im\w+?),", table, re.MULTILINE)) == written
        else:
            assert table != earlier and table_describes_the_files(out)[0].keys() - {
                f"old{k}" for k in range(100)} == written


def test_a_depth_only_model_into_a_full_disk_raises_and_lists_nothing(flight, small_disk, monkeypatch):
    torch.manual_seed(0)
    predictor = DAPMPredictor(DAPMModule(net=DAPMConfig(**TINY, use_pose=False, use_igd_feature=False)),
                              image_width=32, batch_size=8)
    if small_disk is None:  # no tmpfs here: the encoder refuses after a few images' files, as the disk would
        calls, encode = [0], cv2.imencode

        def refuse_after_ten(ext, image, *args):
            calls[0] += 1
            return (False, None) if calls[0] > 10 else encode(ext, image, *args)

        monkeypatch.setattr(files_module.cv2, "imencode", refuse_after_ten)
        out = flight.parent / "out"
    else:
        fill(small_disk, leave=64 * 1024)  # room for a few images' files
        out = small_disk / "out"
    files = PredictionFiles(out, ["depth16", "sky"])
    with pytest.raises(WriteError, match="cannot be written") as info, files:
        for prediction in predictor.predict_source(flight, keep_rgb=True):
            files.add(prediction)
        files.finish()
    assert info.value.path.parent == out and info.value.path.suffix == ".png"
    assert_whole(out)


def test_an_image_whose_files_cannot_all_be_written_leaves_none_of_them(flight, monkeypatch):
    """A disk full after an image's first file: that file goes again, so every image has all its files or none (an
    image's partial files were left, not in poses.csv, and a later run read them back as drone images)."""
    torch.manual_seed(0)
    predictor = DAPMPredictor(DAPMModule(net=DAPMConfig(**TINY, use_pose=False, use_igd_feature=False)),
                              image_width=32, batch_size=8)
    calls, encode = [0], cv2.imencode

    def refuse_after_eleven(ext, image, *args):  # five images' two files, then the sixth image's first
        calls[0] += 1
        return (False, None) if calls[0] > 11 else encode(ext, image, *args)

    monkeypatch.setattr(files_module.cv2, "imencode", refuse_after_eleven)
    out = flight.parent / "out"
    files = PredictionFiles(out, ["depth16", "sky"])
    with pytest.raises(WriteError, match="_sky.png: cannot be written"), files:
        for prediction in predictor.predict_source(flight, keep_rgb=True):
            files.add(prediction)
        files.finish()
    images = Counter(name.rsplit("_", 1)[0] for name in assert_whole(out) if name.endswith(".png"))
    assert len(images) == 5 and set(images.values()) == {2}, images


def test_a_run_whose_first_write_fails_leaves_no_folder(checkpoint, flight, small_disk, capsys, monkeypatch):
    if small_disk is None:
        monkeypatch.setattr(files_module.cv2, "imencode", lambda *args: (False, None))
        parent = flight.parent
    else:
        fill(small_disk)
        parent = small_disk
    out = parent / "new" / "out"
    code, err = run_main(["predict", str(flight), "--ckpt_path", str(checkpoint), "--out", str(out),
                          "--device", "cpu", "--outputs", "depth16"], capsys)
    assert code == 1 and "im00_depth16.png: cannot be written" in err
    assert not (parent / "new").exists()  # the folders the run made went again


# ----------------------------------------------------------------------------------- runs that fail before writing
@pytest.mark.parametrize(("table", "problem"), [
    (b"\x1f\x8b\x08\x00\xb2\x9a\x00 random bytes", "not UTF-8 text (byte 0x8b on line 1)"),
    (b"name,height_m,pitch_deg,roll_deg,fov_deg\r\nold0,50,-40,1,70\r\nold1,5", "damaged or cut short (line 3: 2 "
     "cells, its header 5)"),
    (b"name,height_m,pitch_deg,roll_deg,fov_deg\r\nold0,50,-40,1,70", "cut short (no line end after its last row)"),
    (b"id,value\n1,2\n", "not a poses table (its header 'id,value' lacks the columns name,height_m,pitch_deg,"
     "roll_deg,fov_deg)"),
    (b"", "empty (cut short?)")], ids=["random bytes", "cut mid-row", "no line end", "another table", "empty"])
def test_an_earlier_poses_table_that_is_damaged_or_foreign_stops_the_run_before_anything_is_written(
        tmp_path, capsys, table, problem):
    """--exist_ok into a folder whose poses.csv is damaged: the run failed after writing its images with "'utf-8'
    codec can't decode byte 0xb2", naming no file; a table cut short, or another table, was replaced (rows lost)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "poses.csv").write_bytes(table)
    (out / "old0_camera.json").write_text("{}")
    images = tmp_path / "images"
    images.mkdir()
    cv2.imwrite(str(images / "old0.png"), np.zeros((40, 60, 3), np.uint8))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    code, err = run_main(["predict", str(images), "--ckpt_path", "missing.ckpt", "--out", str(out), "--exist_ok"],
                         capsys)  # refused before the model loads
    assert code == 1 and err.splitlines()[:2] == [
        f"error: {out / 'poses.csv'}: {problem}; this run would replace that table and lose its rows",
        "Fix: move it out of the folder (or put back an intact copy), or give another --out"]
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # nothing written
    with pytest.raises(ValueError, match="--trainer.callbacks.output_dir$"):
        PredictionWriter(str(out), exist_ok=True)
    with pytest.raises(ValueError, match="this run would replace that table"):  # damaged while a run was under way
        write_poses(out, [{"name": "new", "height_m": 50.0, "pitch_deg": -30.0, "roll_deg": 0.5, "fov_deg": 80.0}])
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    (out / "poses.csv").write_bytes(b"\xef\xbb\xbfname,height_m,pitch_deg,roll_deg,fov_deg\r\nold0,50,-40,1,70\r\n")
    PredictionFiles(out)  # an intact table (a spreadsheet's byte-order mark allowed) is added to


def test_a_failed_run_leaves_no_output_folder(checkpoint, flight, tmp_path, capsys):
    out = tmp_path / "out"
    base = ["--ckpt_path", str(checkpoint), "--out", str(out), "--device", "cpu"]
    code, err = run_main(["predict", str(tmp_path / "missing"), *base], capsys)
    assert code == 1 and "no such file or folder" in err
    table = tmp_path / "flight.csv"
    table.write_text("name,height_m\nim00.png,tall\n")
    code, err = run_main(["predict", str(flight), *base, "--telemetry", str(table)], capsys)
    assert code == 1 and "flight.csv" in err
    damaged = tmp_path / "damaged"
    damaged.mkdir()
    (damaged / "a.png").write_bytes(b"not a png")
    code, err = run_main(["predict", str(damaged), *base], capsys)
    assert code == 1 and "a.png: cannot be decoded" in err
    assert not out.exists()


def table_describes_the_files(out):
    """``poses.csv`` and ``poses.json`` hold one row per ``NAME_camera.json`` in ``out``, with its pose."""
    with (out / "poses.csv").open(newline="") as handle:
        table = {row["name"]: row for row in csv.DictReader(handle)}
    assert [row["name"] for row in json.loads((out / "poses.json").read_text())] == list(table)
    cameras = {p.name[:-len("_camera.json")]: json.loads(p.read_text()) for p in out.glob("*_camera.json")}
    assert set(cameras) <= set(table)
    for name, camera in cameras.items():
        assert float(table[name]["height_m"]) == pytest.approx(camera["pose"]["height_m"]["value"], abs=1e-3), name
    return table, cameras


def test_a_damaged_image_mid_run_keeps_the_tables_true_to_the_files(checkpoint, tmp_path, capsys):
    """A PNG cut short (its header whole, so found only when its batch is decoded) stops an --exist_ok run after
    four images were rewritten: the tables and the contact sheet are brought up to date for those four."""
    images, out = tmp_path / "imgs", tmp_path / "out"
    images.mkdir()
    rng = np.random.default_rng(5)
    for k in range(4):
        cv2.imwrite(str(images / f"im{k}.png"), rng.integers(0, 255, (40, 60, 3), np.uint8))
    base = ["predict", str(images), "--ckpt_path", str(checkpoint), "--out", str(out), "--device", "cpu",
            "--batch_size", "2"]
    from dapm_lightning.cli import main

    main(base)
    capsys.readouterr()
    sheet = (out / "contact_sheet.png").read_bytes()
    whole = cv2.imencode(".png", rng.integers(0, 255, (40, 60, 3), np.uint8))[1].tobytes()
    (images / "zz.png").write_bytes(whole[:len(whole) // 2])
    telemetry = tmp_path / "flight.csv"  # the second run's heights differ from the first's, and are known
    telemetry.write_text("name,height_m\n" + "".join(f"im{k}.png,{123.5 + k}\n" for k in range(4)))
    code, err = run_main([*base, "--exist_ok", "--telemetry", str(telemetry)], capsys)
    lines = err.splitlines()
    error = next(k for k, line in enumerate(lines) if line.startswith("error: "))
    assert code == 1 and lines[error] == (f"error: {images / 'zz.png'}: cannot be decoded as an image (damaged, cut "
                                          "short, or not an image)")
    assert lines[error + 1].startswith("Fix: replace it with an intact copy, or move it out of the source")
    assert lines[error - 1] == (f"stopped early by the error below: predicted 4 images: depth_color, sky, camera per "
                                f"image; poses.csv, contact_sheet.png in {out}/")
    table, cameras = table_describes_the_files(out)
    assert sorted(table) == sorted(cameras) == [f"im{k}" for k in range(4)]
    assert [float(table[f"im{k}"]["height_m"]) for k in range(4)] == [123.5, 124.5, 125.5, 126.5]
    assert (out / "contact_sheet.png").read_bytes() != sheet  # the sheet shows this run's predictions
    assert_whole(out)


def sigterm_after_images(monkeypatch, count):
    """A SIGTERM to this process once the output files hold ``count`` images (a job scheduler's time limit)."""
    add = PredictionFiles.add

    def add_then_sigterm(self, prediction):
        add(self, prediction)
        if self.images == count:
            os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(PredictionFiles, "add", add_then_sigterm)


def test_sigterm_mid_run_writes_the_tables_of_the_images_written_and_exits_143(checkpoint, flight, tmp_path,
                                                                             capsys, monkeypatch):
    """A job scheduler's SIGTERM (a time limit) stops the run as Ctrl-C does: the tables and the sheet take the
    images written, one line says so, exit status 143 (before: killed at once, their files without a poses.csv)."""
    out = tmp_path / "out"
    sigterm_after_images(monkeypatch, 3)

    def unhandled(signum, frame):  # what the command's own handler replaces (else SIGTERM would end pytest)
        raise RuntimeError("SIGTERM reached the handler from before the run")

    previous = signal.signal(signal.SIGTERM, unhandled)
    try:
        code, err = run_main(["predict", str(flight), "--ckpt_path", str(checkpoint), "--out", str(out),
                              "--device", "cpu", "--batch_size", "1", "--outputs", "camera"], capsys)
        assert code == 143 and signal.getsignal(signal.SIGTERM) is unhandled  # the handler from before, back
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert err.splitlines()[-1] == (f"stopped by SIGTERM: predicted 3 images: camera per image; poses.csv, "
                                    f"contact_sheet.png in {out}/")
    table, cameras = table_describes_the_files(out)
    assert len(table) == len(cameras) == 3 and (out / "contact_sheet.png").is_file()


@pytest.mark.parametrize("number, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_stop_while_an_image_is_written_waits_for_its_row(checkpoint, flight, tmp_path, capsys, monkeypatch,
                                                            number, code):
    """SIGTERM or Ctrl-C arriving after an image's files were written but before its row was kept: the stop waits
    for the row (before: the tables lacked the image whose ``_camera.json`` was in the folder; seen once in CI)."""
    import dapm_lightning.inference.writers as writers

    out, write, count = tmp_path / "out", writers.prediction_files, []

    def write_then_signal(*args, **kwargs):
        written = write(*args, **kwargs)
        count.append(1)
        if len(count) == 3:
            os.kill(os.getpid(), number)
        return written

    monkeypatch.setattr(writers, "prediction_files", write_then_signal)
    previous = signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a stray one must not end pytest
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        got, err = run_main(["predict", str(flight), "--ckpt_path", str(checkpoint), "--out", str(out),
                             "--device", "cpu", "--batch_size", "1", "--outputs", "camera"], capsys)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert got == code, err[-2000:]
    table, cameras = table_describes_the_files(out)
    assert len(table) == len(cameras) == 3, (sorted(table), sorted(cameras))


@pytest.mark.slow
def test_sigterm_to_the_whole_job_with_loader_workers_stops_cleanly(checkpoint, tmp_path):
    """A scheduler's SIGTERM reaches the loader workers too (the process group): they leave the stop to the main
    process, which writes the tables and exits 143 without a traceback (before: each worker died of it and the
    loader's shutdown printed 'RuntimeError: DataLoader worker (pid N) is killed by signal: Terminated')."""
    import sys
    import time

    images = tmp_path / "flight"
    images.mkdir()
    rng = np.random.default_rng(5)
    for k in range(1500):
        cv2.imwrite(str(images / f"im{k:04d}.png"), rng.integers(0, 255, (24, 32, 3), np.uint8))
    out = tmp_path / "out"
    process = subprocess.Popen(
        [sys.executable, "-m", "dapm_lightning", "predict", str(images), "--ckpt_path", str(checkpoint), "--out",
         str(out), "--device", "cpu", "--batch_size", "1", "--num_workers", "2", "--outputs", "camera"],
        cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 240
    while len(list(out.glob("*_camera.json"))) < 5 and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert process.poll() is None, "the run ended before the signal"
    os.killpg(process.pid, signal.SIGTERM)
    try:
        _, err = process.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        pytest.fail(f"still running 120 s after SIGTERM:\n{process.communicate()[1][-3000:]}")
    assert process.returncode == 143 and "Traceback" not in err, err[-3000:]
    assert err.splitlines()[-1].startswith("stopped by SIGTERM: predicted "), err[-3000:]
    table, cameras = table_describes_the_files(out)
    assert 5 <= len(table) == len(cameras) < 1500


def test_the_lightning_form_stops_at_sigterm_after_the_batch_with_the_tables_and_143(checkpoint, flight, tmp_path,
                                                                                   capsys, monkeypatch):
    """Lightning's predict loop notes SIGTERM and runs on (before: all 48 images, exit status 0, so a scheduler's
    kill after its grace period left files without tables). Now it stops after the batch being written: the tables
    take those images, exit status 143."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "out"
    sigterm_after_images(monkeypatch, 3)
    code, _ = run_main(["predict", "--config", "configs/predict.yaml", "--ckpt_path", str(checkpoint),
                        "--data.init_args.source", str(flight), "--data.init_args.num_workers", "0",
                        "--data.init_args.batch_size", "2", "--trainer.accelerator", "cpu",
                        "--trainer.callbacks.output_dir", str(out)], capsys)
    assert code == 143
    table, cameras = table_describes_the_files(out)
    assert len(table) == len(cameras) == 4 and (out / "contact_sheet.png").is_file()  # the batch it was writing


def camera_prediction(name, height=30.0):
    return make_prediction(name, (20, 30), torch.full((1, 8, 8), 30.0), torch.zeros(1, 8, 8),
                           torch.tensor([height, -40.0, 2.0, 70.0]), IGDSpec())


@pytest.fixture()
def ctrl_c_at(monkeypatch):
    """``ctrl_c_at(module, name)``: a Ctrl-C to this process as ``module.name`` is called (Python's own handler)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)

    def install(module, name):
        function = getattr(module, name)

        def interrupted(*args, **kwargs):
            os.kill(os.getpid(), signal.SIGINT)
            return function(*args, **kwargs)

        monkeypatch.setattr(module, name, interrupted)

    yield install
    signal.signal(signal.SIGINT, previous)


def test_ctrl_c_while_an_image_is_written_by_the_library_waits_for_its_row(tmp_path, ctrl_c_at):
    """The Lightning form's writer (no handler of the command's): a KeyboardInterrupt raised between an image's files
    and its row left a ``_camera.json`` the tables written on stopping did not describe."""
    import dapm_lightning.inference.writers as writers

    out = tmp_path / "out"
    files = PredictionFiles(out, ["camera"], exist_ok=True)
    files.add(camera_prediction("im0"))
    ctrl_c_at(writers, "remove_stale_files")  # the image's files written, its row not yet kept
    with pytest.raises(KeyboardInterrupt):
        files.add(camera_prediction("im1"))
    files.close()
    table, cameras = table_describes_the_files(out)
    assert sorted(table) == sorted(cameras) == ["im0", "im1"]


@pytest.mark.parametrize("stage", ["finish", "close"])
def test_ctrl_c_while_the_tables_are_written_leaves_them_whole(tmp_path, ctrl_c_at, stage):
    """Ctrl-C (or SIGTERM) as the run writes its tables, at the end (finish) or after an earlier stop (close, a
    second Ctrl-C): they are written, then the stop goes on (before: at finish no table at all, the run marked as
    finished; at close the table left as it was)."""
    import dapm_lightning.inference.writers as writers

    out = tmp_path / "out"
    files = PredictionFiles(out, ["camera"], exist_ok=True)
    for k in range(3):
        files.add(camera_prediction(f"im{k}", 30.0 + k))
    ctrl_c_at(writers, "write_poses")
    with pytest.raises(KeyboardInterrupt):
        files.finish() if stage == "finish" else files.close()
    files.close()
    table, cameras = table_describes_the_files(out)
    assert sorted(table) == sorted(cameras) == ["im0", "im1", "im2"]
    assert (out / "poses.json").is_file() and (out / "contact_sheet.png").is_file()


def test_a_writer_closed_without_finishing_writes_the_tables_of_what_it_wrote(tmp_path):
    """The Lightning form's writer after a failed batch: the rows of the images written, the sheet of them."""
    from types import SimpleNamespace

    out = tmp_path / "out"
    writer = PredictionWriter(str(out), outputs=["camera"], exist_ok=True)
    for k, height in enumerate((30.0, 40.0)):
        writer.files.add(make_prediction(f"im{k}", (20, 30), torch.full((1, 8, 8), 30.0), torch.zeros(1, 8, 8),
                                         torch.tensor([height, -40.0, 2.0, 70.0]), IGDSpec()))
    writer.on_exception(SimpleNamespace(is_global_zero=True), None, ValueError("a damaged image"))
    table, cameras = table_describes_the_files(out)
    assert sorted(table) == ["im0", "im1"] and (out / "contact_sheet.png").is_file()
    files = PredictionFiles(tmp_path / "none")
    files.close()  # nothing written: no table, no folder
    assert not (tmp_path / "none").exists()


# ------------------------------------------------------------------------------------- where the output folder is
def test_an_output_folder_in_the_source_is_refused_before_the_model_loads(checkpoint, flight, capsys, monkeypatch):
    def no_model(*args, **kwargs):
        raise AssertionError("the model was loaded")

    monkeypatch.setattr(DAPMPredictor, "from_checkpoint", no_model)
    nested = flight / "sub"
    (flight / "day1").mkdir()
    cv2.imwrite(str(flight / "day1" / "a.png"), np.zeros((8, 8), np.uint8))
    for source, out, root in ((flight, flight, flight), (flight, flight / "pred", flight),
                              (f"{flight}/**/*.png", nested, flight), (f"{flight}/*.png", flight, flight),
                              (f"{flight}/*/*.png", nested, flight)):
        code, err = run_main(["predict", str(source), "--ckpt_path", str(checkpoint), "--out", str(out)], capsys)
        lines = err.splitlines()
        assert code == 1 and lines[0] == (f"error: --out {out} {'is' if out == root else 'lies inside'} the source "
                                          f"{root}, so its files would be read back as images: give an output "
                                          "folder outside the source"), err
        assert not nested.exists() and not (flight / "pred").exists()
    # a glob reaches only the folders its components match: the default --out beside '*.png' is apart
    assert source_holding(flight.parent / "predictions", f"{flight.parent}/*.png") is None
    assert source_holding(flight / "pred", f"{flight}/day*/*.png") is None
    assert source_holding(flight / "pred", flight / "im00.png") is None  # an image holds nothing
    assert source_holding(flight.parent / "out", flight) is None


def test_an_output_folder_in_a_folder_a_list_names_is_refused(flight, tmp_path, capsys, monkeypatch):
    """A .txt list naming flight/ with --out flight/pred is refused as the folder itself is (before: accepted, and
    the next run into that folder, --exist_ok, read its depth and sky PNGs back as drone images)."""
    monkeypatch.setattr(DAPMPredictor, "from_checkpoint", lambda *a, **k: pytest.fail("the model was loaded"))
    todo = tmp_path / "todo.txt"
    todo.write_text("# the flight\nflight\n")
    out = flight / "pred"
    code, err = run_main(["predict", str(todo), "--ckpt_path", "model.ckpt", "--out", str(out)], capsys)
    assert code == 1 and err.splitlines()[0] == (f"error: --out {out} lies inside the source {flight} (line 2 of "
                                                 f"{todo}), so its files would be read back as images: give an "
                                                 "output folder outside the source"), err
    assert not out.exists()
    todo.write_text("flight/im0*.png\n")  # a pattern's root holds what the pattern reaches
    with pytest.raises(ValueError, match=f"--out {flight} is the source {flight} \\(line 1 of"):
        check_output_outside_source(flight, [todo])
    check_output_outside_source(tmp_path / "out", todo)  # beside the flight: apart


def test_the_lightning_form_refuses_an_output_folder_in_the_source(checkpoint, flight, tmp_path, capsys,
                                                                     monkeypatch):
    monkeypatch.chdir(tmp_path)
    before = sorted(p.name for p in flight.iterdir())
    code, err = run_main(["predict", "--config", "configs/predict.yaml", "--ckpt_path", str(checkpoint),
                          "--data.init_args.source", str(flight), "--data.init_args.num_workers", "0",
                          "--trainer.callbacks.output_dir", str(flight)], capsys)
    assert code == 1 and err.splitlines()[0].startswith(f"error: --trainer.callbacks.output_dir {flight} is the "
                                                        f"source {flight}")
    assert sorted(p.name for p in flight.iterdir()) == before


def test_an_unwritable_output_folder_is_refused_before_the_model_loads(checkpoint, flight, tmp_path, capsys,
                                                                        monkeypatch):
    monkeypatch.setattr(DAPMPredictor, "from_checkpoint", lambda *a, **k: pytest.fail("the model was loaded"))
    afile = tmp_path / "afile"
    afile.write_text("x")
    code, err = run_main(["predict", str(flight), "--ckpt_path", str(checkpoint), "--out", str(afile / "out")],
                         capsys)
    assert code == 1 and err.splitlines()[:2] == [
        f"error: {afile}/out: cannot be written (it lies under {afile}, which is a file, not a folder)",
        "Fix: give another output folder (--out)"]
    code, err = run_main(["predict", str(flight), "--ckpt_path", str(checkpoint), "--out", str(afile)], capsys)
    assert code == 1 and "it is a file, not a folder" in err
    with pytest.raises(WriteError, match=r"--trainer.callbacks.output_dir"):
        PredictionWriter(output_dir=str(afile / "out"))
    read_only = tmp_path / "ro"
    if mount_tmpfs(read_only, "ro,size=64k"):  # a read-only file system stops root too
        try:
            code, err = run_main(["predict", str(flight), "--ckpt_path", str(checkpoint), "--out",
                                  str(read_only / "out")], capsys)
            assert code == 1 and f"{read_only} is read-only or not yours" in err
        finally:
            subprocess.run(["umount", "-l", str(read_only)], capture_output=True)
    with pytest.raises(WriteError):
        check_folder_writable(afile / "a" / "b")


# ---------------------------------------------------------------------------------------- extreme aspects and sizes
@pytest.mark.parametrize("size", [(10, 30000), (30000, 10), (45, 70), (40, 160), (40, 161), (1, 1)])
def test_contact_sheet_tiles_are_bounded_for_any_aspect(size):
    depth = torch.full((1, 16, 16), 30.0)
    prediction = make_prediction("x", size, depth, torch.zeros(1, 16, 16), torch.tensor([40.0, -20.0, 3.0, 70.0]),
                                 IGDSpec())
    prediction.rgb = np.full((*size, 3), 120, np.uint8)
    row = contact_row(prediction)
    natural = max(1, round(size[1] * CONTACT_TILE / size[0]))
    tile = row.shape[1] - 2 * CONTACT_TILE
    assert row.shape[0] == CONTACT_TILE and row.shape[1] <= ROW_MAX_WIDTH
    if CONTACT_TILE // CONTACT_MAX_ASPECT <= natural <= CONTACT_MAX_ASPECT * CONTACT_TILE:
        assert tile == 3 * natural  # ordinary aspects: the tiles as they always were
    else:
        assert tile == 3 * min(max(natural, CONTACT_TILE // CONTACT_MAX_ASPECT), CONTACT_MAX_ASPECT * CONTACT_TILE)
    sheet = contact_sheet([row] * CONTACT_MAX_IMAGES)
    assert sheet.shape[1] <= ROW_MAX_WIDTH and sheet.shape[0] == CONTACT_MAX_IMAGES * (CONTACT_TILE + 4)
    sheet = contact_sheet([contact_tiles(prediction)] * CONTACT_MAX_IMAGES)  # aligned, under headings
    assert sheet.shape == (CONTACT_HEADING + CONTACT_MAX_IMAGES * (CONTACT_TILE + 4), row.shape[1], 3)


def test_thin_and_wide_images_through_the_command(checkpoint, tmp_path, capsys):
    from dapm_lightning.cli import main

    folder = tmp_path / "thin"
    folder.mkdir()
    rng = np.random.default_rng(1)
    cv2.imwrite(str(folder / "wide.png"), rng.integers(0, 255, (8, 1200, 3), np.uint8))
    cv2.imwrite(str(folder / "tall.png"), rng.integers(0, 255, (1200, 8, 3), np.uint8))
    out = tmp_path / "out"
    main(["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(out), "--device", "cpu",
          "--image_width", "64", "--outputs", "depth16", "sky"])
    summary = capsys.readouterr().out.strip().splitlines()[-1]
    assert summary == f"predicted 2 images: depth16, sky per image; poses.csv, contact_sheet.png in {out}/"
    sheet = cv2.imread(str(out / "contact_sheet.png"))
    assert sheet.shape[:2] == (CONTACT_HEADING + 2 * (CONTACT_TILE + 4), ROW_MAX_WIDTH)
    assert cv2.imread(str(out / "wide_depth16.png"), cv2.IMREAD_UNCHANGED).shape == (8, 1200)
    with pytest.warns(UserWarning, match=f"at most {CONTACT_MAX_IMAGES} images"):
        assert PredictionFiles(tmp_path / "x", contact_sheet=1000).contact_images == CONTACT_MAX_IMAGES
    assert not (tmp_path / "x").exists()


def test_the_summary_names_only_what_was_written(tmp_path, capsys):
    torch.manual_seed(0)
    pose_only = DAPMPredictor(DAPMModule(net=DAPMConfig(**TINY, use_depth=False, use_igd_feature=False)),
                              image_width=32)
    out = tmp_path / "out"
    with PredictionFiles(out, contact_sheet=0) as files:  # every kind asked for; a pose model gives a camera
        result = pose_only(np.zeros((36, 48, 3), np.uint8))
        files.add(result)
        summary = files.finish()
    assert summary == f"predicted 1 image: camera per image; poses.csv in {out}/"
    assert sorted(p.name for p in out.iterdir()) == [".dapm_predict", f"{result.name}_camera.json", "poses.csv",
                                                     "poses.json"]
    with PredictionFiles(tmp_path / "none") as files:
        assert files.finish() == "predicted 0 images: nothing written"
    assert not (tmp_path / "none").exists()


def test_a_failed_finish_writes_the_tables_once_and_keeps_no_early_stop_summary(tmp_path, monkeypatch):
    """Every image written, then the contact sheet refused: the run's files are not attempted a second time when
    the failure closes the files, and nothing claims the run stopped early."""
    from dapm_lightning.inference import writers

    torch.manual_seed(0)
    pose_only = DAPMPredictor(DAPMModule(net=DAPMConfig(**TINY, use_depth=False, use_igd_feature=False)),
                              image_width=32)
    written = []

    def counted_write_poses(folder, rows):
        written.append(len(rows))
        return write_poses(folder, rows)

    def refused_image(path, image):
        raise WriteError(path, "no space left on device", "free some space")

    monkeypatch.setattr(writers, "write_poses", counted_write_poses)
    monkeypatch.setattr(writers, "write_image", refused_image)
    with PredictionFiles(tmp_path / "out") as files:
        files.add(pose_only(np.zeros((36, 48, 3), np.uint8)))
        with pytest.raises(WriteError, match="contact_sheet.png"):
            files.finish()
    assert written == [1] and files.kept is None


def test_empty_folders_made_in_several_calls_are_removed_past_a_sibling_that_holds_a_file(tmp_path):
    """A writer or a render joins the folders of several make_folder calls: one sibling that holds a file keeps
    itself and its parents, and every empty folder of the others is still removed."""
    made = make_folder(tmp_path / "out" / "a" / "rgb") + make_folder(tmp_path / "out" / "b" / "rgb")
    (tmp_path / "out" / "b" / "rgb" / "kept.png").write_bytes(b"x")
    remove_empty_folders(made)
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == [
        "out", "out/b", "out/b/rgb", "out/b/rgb/kept.png"]
