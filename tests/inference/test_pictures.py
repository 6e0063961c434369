"""Readable pictures: each depth map in its own range with a colour bar in metres; an aligned contact sheet with
headings and poses; a video's frames beside their depth as an mp4."""

import subprocess

import cv2
import numpy as np
import pytest
import torch

from dapm_lightning.cli import main
from dapm_lightning.data.pictures import BAR_MIN_HEIGHT, SKY_RGB, depth_picture, depth_range
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.inference.contact_sheet import CONTACT_HEADING, CONTACT_TILE, contact_sheet, contact_tiles
from dapm_lightning.inference.postprocess import make_prediction
from tests.inference.test_outputs import mount_tmpfs
from tests.inference.test_predict import write_video


def scene(height=300, width=400, near=46.0, far=94.0, sky_rows=40):
    rows = np.linspace(near, far, height, dtype=np.float32)[:, None].repeat(width, axis=1)
    sky = np.zeros((height, width), bool)
    sky[:sky_rows] = True
    rows[sky] = 1000.0
    return rows, sky


def test_a_46_to_94_m_scene_uses_the_whole_palette_with_a_bar_in_metres():
    depth, sky = scene()
    depth[100, :5] = 0.5  # a few outliers do not stretch the range
    low, high = depth_range(depth, sky)
    assert 52 < low < 55 and 90 < high < 94  # the ground spans 52.4-94 m
    picture = depth_picture(depth, sky)
    assert picture.shape[0] == 300 and picture.shape[1] > 400  # the colour bar on the right
    ground = picture[sky.shape[0] - 1, :400].astype(int), picture[41, :400].astype(int)
    assert np.abs(ground[0] - ground[1]).sum(axis=1).min() > 200  # near and far far apart in colour
    assert (picture[:40, :400] == SKY_RGB).all() and not (picture[40:, :400] == SKY_RGB).all(axis=2).any()
    bar = picture[:, 400:]
    assert (bar == SKY_RGB).all(axis=2).any() and (bar.sum(axis=2) < 100).any()  # sky swatch, dark labels
    fixed = depth_picture(depth, sky, fixed_range=(1.0, 1000.0))  # comparable maps: one range for all
    assert np.abs(fixed[41:, :400].astype(int) - fixed[299, :400].astype(int)).sum(axis=2).max() < \
        np.abs(picture[41:, :400].astype(int) - picture[299, :400].astype(int)).sum(axis=2).max()
    small = depth_picture(*scene(BAR_MIN_HEIGHT - 1, 50, sky_rows=5))
    assert small.shape == (BAR_MIN_HEIGHT - 1, 50, 3)  # too low for legible labels: no bar


def test_the_contact_sheet_has_headings_aligned_columns_and_poses():
    pose = torch.tensor([40.0, -30.0, 2.0, 70.0])
    rows = []
    for size in ((300, 400), (400, 300), (100, 600)):
        prediction = make_prediction("x", size, torch.full((1, 16, 16), 30.0), torch.zeros(1, 16, 16), pose,
                                     IGDSpec())
        prediction.rgb = np.full((*size, 3), 120, np.uint8)
        rows.append(contact_tiles(prediction))
    widths = [max(r[k].shape[1] for r in rows) for k in range(4)]
    sheet = contact_sheet(rows)
    assert sheet.shape == (CONTACT_HEADING + 3 * (CONTACT_TILE + 4), sum(widths), 3)
    assert (sheet[:CONTACT_HEADING] < 128).any()  # the headings' text
    text = sheet[CONTACT_HEADING:CONTACT_HEADING + CONTACT_TILE, sum(widths[:3]):]
    assert (text < 128).sum() > 500  # name and four pose lines


def test_a_video_gives_an_mp4_of_its_frames_beside_their_depth(checkpoint, tmp_path, capsys):
    video = write_video(tmp_path / "flight.avi", frames=8, size=(120, 160))
    out = tmp_path / "out"
    main(["predict", str(video), "--ckpt_path", str(checkpoint), "--out", str(out), "--device", "cpu",
          "--frame_step", "2", "--depth_range", "5", "500"])
    assert "flight_depth.mp4" in capsys.readouterr().out
    preview = cv2.VideoCapture(str(out / "flight_depth.mp4"))
    frames = []
    while True:
        ok, frame = preview.read()
        if not ok:
            break
        frames.append(frame)
    assert len(frames) == 4 and preview.get(cv2.CAP_PROP_FPS) == pytest.approx(5.0)
    assert frames[0].shape[0] == 120 and frames[0].shape[1] > 2 * 160  # frame | depth | colour bar
    assert [p.name for p in out.glob(".*")] == [".dapm_predict"]  # no partial file left, the run marked its folder


def test_a_preview_the_disk_cuts_short_is_an_error_naming_it_not_a_file_listed(tmp_path, monkeypatch):
    """OpenCV's video writer reports no failed write: a full disk left an mp4 without its index (no player opens
    it) that the summary listed as written. Now it is read back: the error names it and the fix, nothing is left."""
    from dapm_lightning.data.files import WriteError
    from dapm_lightning.inference import video_preview
    from dapm_lightning.inference.postprocess import Prediction
    from dapm_lightning.inference.video_preview import VideoPreviews

    out = tmp_path / "disk"
    mounted = mount_tmpfs(out, "size=384k")
    if not mounted:  # no tmpfs here: the writer's file holds fewer frames than it was given
        monkeypatch.setattr(video_preview, "_frames_readable", lambda path: 0)
    rng = np.random.default_rng(0)
    previews = VideoPreviews()
    for k in range(60):  # ~16 KB a frame of noise: more than the 384 KiB disk holds
        rgb = rng.integers(0, 255, (120, 160, 3), np.uint8)
        previews.add(out, Prediction(np.full((120, 160), 40.0, np.float32), None, None, name=f"clip_f{k:06d}",
                                     size=(120, 160), rgb=rgb, time_s=k / 25), rgb)
    try:
        with pytest.raises(WriteError) as raised:
            previews.finish()
        files = list(out.iterdir())
    finally:
        if mounted:
            subprocess.run(["umount", "-l", str(out)], capture_output=True)
    assert str(raised.value).startswith(f"{out / 'clip_depth.mp4'}: cannot be written (")
    assert "Fix: free space on that disk" in str(raised.value)
    assert not files  # neither the preview nor its partial file
