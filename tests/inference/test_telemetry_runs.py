"""Telemetry in a run: one bad file costs only itself, --strict_telemetry, the summary, provenance in the outputs."""

from __future__ import annotations

import json
import math
import warnings

import cv2
import numpy as np
import pytest
import torch
from PIL import Image, PngImagePlugin

from dapm_lightning.cli import main
from dapm_lightning.inference.inputs import PredictSource, source_dataset, source_datasets
from dapm_lightning.inference.predictor import DAPMPredictor
from dapm_lightning.inference.prior import as_prior, prior_rows
from dapm_lightning.inference.telemetry import (
    PoseTelemetry,
    TelemetryError,
    TelemetryWarning,
    images_telemetry,
    video_telemetry,
)
from tests.conftest import run_main

NAN = math.nan


def dji_jpeg(path, **tags):
    attrs = " ".join(f'drone-dji:{k}="{v}"' for k, v in tags.items())
    packet = ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
              f'<rdf:Description xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" {attrs}/></rdf:RDF></x:xmpmeta>')
    Image.new("RGB", (60, 40), (90, 120, 60)).save(path, xmp=packet.encode())
    return path


def broken_jpeg(path):
    Image.new("RGB", (60, 40), (90, 120, 60)).save(path, xmp=b"<x:xmpmeta><rdf:RDF>")
    return path


def record(fn, *args, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = fn(*args, **kwargs)
    return out, [str(w.message) for w in caught if issubclass(w.category, TelemetryWarning)]


@pytest.fixture()
def flight(tmp_path):
    folder = tmp_path / "flight"
    folder.mkdir()
    dji_jpeg(folder / "a.jpg", RelativeAltitude="+40.0", GimbalPitchDegree="-60.0", FlightPitchDegree="5.0")
    broken_jpeg(folder / "b.jpg")
    cv2.imwrite(str(folder / "c.png"), np.full((40, 60, 3), 90, np.uint8))
    table = tmp_path / "flight.csv"
    table.write_text("name,height_m,pitch_deg,roll_deg,fov_deg\nc.png,30,,,\n")
    return folder, table


def test_one_bad_image_falls_back_alone_with_one_warning(flight):
    folder, table = flight
    paths = sorted(folder.iterdir())
    (a, b, c), caught = record(lambda: images_telemetry(paths, table)[0])
    assert a.values()[:2].tolist() == [40.0, -60.0] and b == PoseTelemetry() and c.height_m == 30.0
    assert a.provenance[:2] == ("a.jpg XMP drone-dji:RelativeAltitude", "a.jpg XMP drone-dji:GimbalPitchDegree")
    assert c.provenance[0] == "flight.csv line 2"
    assert len(caught) == 1
    assert "b.jpg" in caught[0] and "not well-formed" in caught[0] and "--no_metadata" in caught[0]
    assert "--telemetry CSV" in caught[0] and "--strict_telemetry" in caught[0]
    with pytest.raises(TelemetryError, match=r"b.jpg.*not well-formed.*--strict_telemetry"):
        images_telemetry(paths, table, strict=True)
    report, _ = record(lambda: images_telemetry(paths, table)[1])
    assert report.summary() == ("telemetry: 2 of 3 image(s) with telemetry (height 2, pitch 1) from XMP 1, "
                                "flight.csv 1; telemetry unreadable, network pose used: b.jpg")


def test_an_image_whose_metadata_pillow_refuses_falls_back_alone_naming_it(tmp_path):
    """A PNG whose XMP text chunk inflates past Pillow's MAX_TEXT_CHUNK (1 MiB; Photoshop's DocumentAncestors bloat
    XMP so) is readable pixels with unreadable metadata (before: 'ValueError: Decompressed data too large for
    PngImagePlugin.MAX_TEXT_CHUNK', naming no file, stopped the run)."""
    good = dji_jpeg(tmp_path / "a.jpg", RelativeAltitude="+40.0")
    info = PngImagePlugin.PngInfo()
    info.add_itxt("XML:com.adobe.xmp", f"<x:xmpmeta xmlns:x='adobe:ns:meta/'><!-- {'a' * (2 << 20)} --></x:xmpmeta>",
                  zip=True)
    bloated = tmp_path / "b.png"
    Image.new("RGB", (60, 40)).save(bloated, pnginfo=info)
    (a, b), caught = record(lambda: images_telemetry([good, bloated])[0])
    assert a.height_m == 40.0 and b == PoseTelemetry()
    assert len(caught) == 1 and f"{bloated}: its metadata cannot be read (ValueError: Decompressed" in caught[0]
    assert "--no_metadata" in caught[0] and "this image's telemetry is not used" in caught[0]
    with pytest.raises(TelemetryError, match=r"b.png: its metadata cannot be read.*--strict_telemetry"):
        images_telemetry([good, bloated], strict=True)


def test_a_png_cut_short_is_its_decode_error_not_a_broken_exif_block(checkpoint, tmp_path, capsys):
    """Pillow reads a PNG's EXIF by decoding it, so a PNG cut short raised 'image file is truncated' there: it was
    warned about as an EXIF block to strip, and --strict_telemetry stopped on that alone, never saying to replace
    the file. Now its metadata is none and the image reader's error (the file and the fix) is what is shown."""
    images = tmp_path / "bad"
    images.mkdir()
    whole = cv2.imencode(".png", np.random.default_rng(3).integers(0, 255, (40, 60, 3), np.uint8))[1].tobytes()
    cut = images / "trunc.png"
    cut.write_bytes(whole[:len(whole) // 2])
    (telemetry,), caught = record(lambda: images_telemetry([cut], strict=True)[0])
    assert telemetry == PoseTelemetry() and caught == []
    for strict in ([], ["--strict_telemetry"]):
        code, err = run_main(["predict", str(images), "--ckpt_path", str(checkpoint), "--out", str(tmp_path / "x"),
                              "--device", "cpu", *strict], capsys)
        assert code == 1 and "EXIF" not in err, err
        lines = err.splitlines()
        error = next(k for k, line in enumerate(lines) if line.startswith("error: "))
        assert lines[error] == f"error: {cut}: cannot be decoded as an image (damaged, cut short, or not an image)"
        assert lines[error + 1].startswith("Fix: replace it with an intact copy, or move it out of the source")


def write_video(path, frames=9, size=(36, 48), fps=10.0):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (size[1], size[0]))
    for k in range(frames):
        writer.write(np.full((*size, 3), 20 * k, np.uint8))
    writer.release()
    return path


def per_frame_srt(path, count, first_height=20.0):
    path.write_text("".join(f"{k}\n00:00:00,{100 * (k - 1):03d} --> 00:00:00,{100 * k:03d}\n"
                            f"[focal_len: 24.00] [rel_alt: {first_height + k:.3f} abs_alt: 300.000] "
                            "[gb_yaw: 1.0 gb_pitch: -45.0 gb_roll: 0.0]\n\n" for k in range(1, count + 1)))
    return path


def test_an_srt_with_fewer_subtitles_than_frames_warns_once_and_a_csv_names_frames(tmp_path):
    video = write_video(tmp_path / "v.avi")
    srt = per_frame_srt(tmp_path / "v.SRT", 5)
    (frames, _), caught = record(video_telemetry, video, range(9), srt, size=(48, 36), fps=10.0)
    assert sorted(frames) == [0, 1, 2, 3, 4] and frames[4].provenance[0] == "v.SRT subtitle 5 rel_alt"
    assert len(caught) == 1 and "cover frames up to 4 of v.avi; 4 of the 9 frame(s) predicted (the first: 5)" in \
        caught[0]
    table = tmp_path / "frames.csv"
    table.write_text("name,height_m,fov_deg\nv_f000002,55.5,\nframes/v_f000007.png,60,70\nother,1,\n")  # folders:
    # a frame is named by its output name, so a folder in the row's name does not count
    (frames, report), caught = record(video_telemetry, video, range(9), srt, table, size=(48, 36), fps=10.0)
    assert frames[2].height_m == 55.5 and frames[2].provenance[0] == "frames.csv line 2"
    assert frames[2].pitch_deg == -45.0 and frames[2].provenance[1] == "v.SRT subtitle 3 gb_pitch"  # SRT fills in
    assert frames[7].values().tolist()[::3] == [60.0, 70.0] and math.isnan(frames[7].pitch_deg)
    assert any("1 of 3 name(s) match no frame of v.avi" in m for m in caught)
    assert report.total == 9 and report.with_telemetry == 6


def test_a_subtitle_that_knows_nothing_still_covers_its_frame(tmp_path):
    """The coverage warning is about frames no subtitle covers (a wrong or cut SRT), not frames whose subtitle left
    everything unknown (the drone on the ground): those have the on-ground warning alone."""
    srt = tmp_path / "v.SRT"  # subtitle 1: rel_alt 0, on the ground, and no other field
    srt.write_text("".join(f"{k}\n00:00:00,{100 * (k - 1):03d} --> 00:00:00,{100 * k:03d}\n"
                           f"[rel_alt: {20 * (k - 1)}.000 abs_alt: 300.000]\n\n" for k in range(1, 10)))
    (frames, _), caught = record(video_telemetry, tmp_path / "v.avi", range(9), srt, fps=10.0)
    assert sorted(frames) == list(range(1, 9)) and frames[1].height_m == 20.0
    assert len(caught) == 1 and "height <= 0" in caught[0] and "cover frames" not in caught[0]


def test_frames_named_only_by_the_csv_are_given_when_the_frame_count_is_unknown(tmp_path):
    srt = per_frame_srt(tmp_path / "v.SRT", 3)
    table = tmp_path / "frames.csv"
    table.write_text("name,height_m\nv_f000001,55.5\nv_f000040,70\n")
    (frames, report), _ = record(video_telemetry, tmp_path / "v.avi", None, srt, table, fps=10.0)
    assert sorted(frames) == [0, 1, 2, 40] and frames[40].height_m == 70.0 and frames[1].height_m == 55.5
    assert report.total == 4


def test_a_python_api_prior_wins_over_the_csv_row_and_the_csv_fills_in(tmp_path):
    Image.new("RGB", (60, 40)).save(tmp_path / "a.png")
    table = tmp_path / "flight.csv"
    table.write_text("name,height_m,pitch_deg,roll_deg,fov_deg\na.png,30,-40,,\n")
    prior = PoseTelemetry(height_m=50.0, source="API")
    (telemetry,), _ = images_telemetry([tmp_path / "a.png"], table, priors=[prior])
    assert telemetry.values()[:3].tolist()[:2] == [50.0, -40.0] and math.isnan(telemetry.roll_deg)
    assert telemetry.provenance[:2] == ("API", "flight.csv line 2")


def test_a_broken_srt_falls_back_and_strict_stops(tmp_path):
    video = write_video(tmp_path / "v.avi")
    srt = tmp_path / "v.SRT"
    srt.write_text("this is not a subtitle file\n")
    (frames, report), caught = record(video_telemetry, video, range(9), srt, size=(48, 36), fps=10.0)
    assert frames == {} and report.fell_back == ["v.SRT"]
    assert len(caught) == 1 and "v.SRT, line 1: expected a subtitle number" in caught[0]
    assert "this video's telemetry is not used" in caught[0]
    with pytest.raises(TelemetryError, match="expected a subtitle number.*--strict_telemetry"):
        video_telemetry(video, range(9), srt, size=(48, 36), fps=10.0, strict=True)
    per_frame_srt(srt, 9)
    dataset = source_dataset(PredictSource(video, frame_step=2), 32)
    assert sorted(dataset.priors) == [0, 2, 4, 6, 8] and dataset.provenance[8][0] == "v.SRT subtitle 9 rel_alt"
    assert dataset.telemetry_report.summary().startswith("telemetry: 5 of 5 frame(s) with telemetry (height 5")


@pytest.mark.parametrize(("prior", "match"), [
    ({"height_m": -5}, "height_m = -5 must be > 0 m"),
    ({"fov_deg": 250}, r"fov_deg = 250 must be within \(0, 180\)"),
    ({"pitch": 1000}, r"pitch_deg = 1000 must be within \[-180, 180\]"),
    ({"height": math.inf}, "height_m = inf is not finite"),
    ([40.0, -30.0, 0.0, -math.inf], "fov_deg = -inf is not finite"),
    ({"roll_deg": "left"}, "roll_deg = 'left' is not a number"),
])
def test_python_api_priors_are_checked_as_the_csv_is(prior, match):
    with pytest.raises(TelemetryError, match=match):
        as_prior([prior])


def test_python_api_priors_carry_their_provenance():
    rows, provenance = prior_rows([{"height_m": 30.0, "pitch": NAN}, None, torch.tensor([NAN, -50.0, NAN, 70.0]),
                                   PoseTelemetry(height_m=12.0, source="x.csv line 3")])
    assert np.isnan(rows[0, 1]) and rows[2, 3] == 70.0
    assert provenance == [("Python API prior", "", "", ""), ("", "", "", ""),
                          ("", "Python API prior", "", "Python API prior"), ("x.csv line 3", "", "", "")]


def test_the_outputs_name_where_each_component_came_from(checkpoint, flight, tmp_path, capsys):
    folder, table = flight
    out = tmp_path / "out"
    _, caught = record(main, ["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(out),
                              "--device", "cpu", "--telemetry", str(table), "--outputs", "camera"])
    assert len(caught) == 1 and "b.jpg" in caught[0] and "--no_metadata" in caught[0]

    def provenance(name):
        return json.loads((out / f"{name}_camera.json").read_text())["pose_provenance"]

    assert provenance("a") == {"height_m": "a.jpg XMP drone-dji:RelativeAltitude",
                               "pitch_deg": "a.jpg XMP drone-dji:GimbalPitchDegree", "roll_deg": None, "fov_deg": None}
    assert set(provenance("b").values()) == {None}
    assert provenance("c")["height_m"] == "flight.csv line 2"
    with pytest.raises(SystemExit) as info:
        main(["predict", str(folder), "--ckpt_path", str(checkpoint), "--out", str(tmp_path / "strict"),
              "--device", "cpu", "--telemetry", str(table), "--strict_telemetry"])
    assert info.value.code == 1 and "b.jpg" in capsys.readouterr().err


def test_api_and_video_predictions_carry_provenance(checkpoint, tmp_path):
    predictor = DAPMPredictor.from_checkpoint(checkpoint, image_width=32)
    rgb = np.random.default_rng(0).integers(0, 255, (40, 60, 3), np.uint8)
    result = predictor(rgb, prior={"height_m": 33.0})
    assert result.pose_provenance == {"height": "Python API prior"}
    assert result.camera_dict()["pose_provenance"]["height_m"] == "Python API prior"
    with pytest.raises(TelemetryError, match="must be > 0"):
        predictor(rgb, prior={"height_m": 0.0})
    video = write_video(tmp_path / "clip.avi", frames=6)
    per_frame_srt(tmp_path / "clip.SRT", 4)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        results = list(predictor.predict_source(video))
    assert [r.pose_provenance for r in results][3:] == [{"height": "clip.SRT subtitle 4 rel_alt",
                                                        "pitch": "clip.SRT subtitle 4 gb_pitch",
                                                        "roll": "clip.SRT subtitle 4 gb_roll",
                                                        "fov": "clip.SRT subtitle 4 focal_len"}, None, None]
    assert sum("cover frames up to 3" in str(w.message) for w in caught) == 1


def test_an_image_path_given_to_the_api_takes_its_own_metadata_under_the_given_prior(checkpoint, tmp_path):
    """``predictor("DJI_0001.JPG")`` read the pixels only (the command line and ``predict_source`` read the XMP)."""
    predictor = DAPMPredictor.from_checkpoint(checkpoint, image_width=32)
    photo = dji_jpeg(tmp_path / "DJI_0001.JPG", RelativeAltitude="+41.20", GimbalPitchDegree="-35.5")
    result = predictor(photo, prior={"height_m": 30.0})
    assert result.pose["height"] == pytest.approx(30.0) and result.pose["pitch"] == pytest.approx(-35.5)
    assert result.pose_provenance == {"height": "Python API prior",
                                      "pitch": "DJI_0001.JPG XMP drone-dji:GimbalPitchDegree"}
    assert predictor([str(photo)])[0].pose["height"] == pytest.approx(41.2)
    assert predictor(photo, read_metadata=False).pose_provenance is None
    _, caught = record(predictor, broken_jpeg(tmp_path / "broken.jpg"))  # unreadable: the network's pose, warned
    assert len(caught) == 1 and "broken.jpg" in caught[0]


def test_the_api_warns_only_of_metadata_left_unknown_that_the_prior_does_not_give(checkpoint, tmp_path):
    """A prior's height with an XMP height below 1 m warned 'height left unknown' (the prior's 30 m was used)."""
    predictor = DAPMPredictor.from_checkpoint(checkpoint, image_width=32)
    photo = dji_jpeg(tmp_path / "DJI_0001.JPG", RelativeAltitude="+0.20", GimbalPitchDegree="-35.5")
    result, caught = record(predictor, photo, prior={"height_m": 30.0})
    assert result.pose["height"] == pytest.approx(30.0) and result.pose["pitch"] == pytest.approx(-35.5)
    assert caught == []
    _, caught = record(predictor, photo)  # no prior: the height is left unknown, and said so
    assert len(caught) == 1 and "height left unknown" in caught[0]


def test_the_api_call_takes_strict_telemetry_as_its_fall_back_warning_says(checkpoint, tmp_path):
    """The warning for an image path's unreadable metadata says 'strict_telemetry=True in Python', which
    ``predictor(path, ...)`` refused with a TypeError (only predict_source took it)."""
    predictor = DAPMPredictor.from_checkpoint(checkpoint, image_width=32)
    broken = broken_jpeg(tmp_path / "broken.jpg")
    _, caught = record(predictor, broken)
    assert len(caught) == 1 and "strict_telemetry=True in Python" in caught[0]
    with pytest.raises(TelemetryError, match="broken.jpg"):
        predictor(broken, strict_telemetry=True)
    assert predictor(broken, prior=[40.0, -60.0, 0.0, 70.0], strict_telemetry=True).pose["height"] == \
        pytest.approx(40.0)  # all known: the metadata is not read


def test_the_srt_coverage_warning_counts_the_frames_its_timing_covers(tmp_path):
    srt = tmp_path / "v.SRT"  # subtitle 2 lasts 2 frames at 10 fps: 3 subtitles cover frames 0-3
    srt.write_text("".join(f"{k}\n00:00:00,{a:03d} --> 00:00:00,{b:03d}\n[rel_alt: {20 + k}.000 abs_alt: 300.0]\n\n"
                           for k, (a, b) in enumerate([(0, 100), (100, 300), (300, 400)], 1)))
    (frames, _), caught = record(video_telemetry, tmp_path / "v.avi", range(9), srt, fps=10.0)
    assert [frames[f].provenance[0] for f in sorted(frames)] == [
        "v.SRT subtitle 1 rel_alt", "v.SRT subtitle 2 rel_alt", "v.SRT subtitle 2 rel_alt", "v.SRT subtitle 3 rel_alt"]
    assert len(caught) == 1 and "cover frames up to 3 of v.avi; 5 of the 9 frame(s) predicted (the first: 4)" in \
        caught[0]


def test_a_csv_shared_by_several_inputs_is_read_once_and_warns_once_about_rows_none_uses(tmp_path):
    a, b = write_video(tmp_path / "a.avi"), write_video(tmp_path / "b.avi")
    image = dji_jpeg(tmp_path / "c.jpg", RelativeAltitude="+40.0")
    table = tmp_path / "flight.csv"
    table.write_text("name,height_m,pitch_deg,roll_deg,fov_deg,note\na_f000000,70,,,,\nb_f000000,90,,,,\n"
                     "c.jpg,30,,,,\nstray,5,,,,\n")
    (first, second), caught = record(source_datasets, PredictSource([str(a), str(b)], telemetry=table), 32)
    assert first.priors[0][0] == 70.0 and second.priors[0][0] == 90.0
    assert caught == [f"{table}: column(s) note ignored (the telemetry columns are name,height_m,pitch_deg,roll_deg,"
                      "fov_deg)",
                      f"{table}: 2 of 4 name(s) match no frame of a.avi or b.avi (frames are named as their outputs: "
                      "a_f000012): c, stray; names are matched by file name with or without extension "
                      "(case-sensitive; folders in a name must be the image's), those rows are unused"]
    (images, video), caught = record(source_datasets, PredictSource([str(image), str(b)], telemetry=table), 32)
    assert images.priors[0][0] == 30.0 and video.priors[0][0] == 90.0
    assert [m for m in caught if "match no" in m] == [
        f"{table}: 2 of 4 name(s) match no image or frame of b.avi (frames are named as their outputs: b_f000012): "
        "a_f000000, stray; names are matched by file name with or without extension (case-sensitive; folders in a "
        "name must be the image's), those rows are unused"]


def test_an_srt_given_with_images_serves_its_video_and_the_images_keep_their_metadata(checkpoint, tmp_path):
    image = dji_jpeg(tmp_path / "c.jpg", RelativeAltitude="+40.0")
    (tmp_path / "clips").mkdir()
    video, other = write_video(tmp_path / "clips" / "v.avi"), write_video(tmp_path / "clips" / "w.avi")
    srt = per_frame_srt(tmp_path / "flight.SRT", 9)
    (images, clip), caught = record(source_datasets, PredictSource([str(image), str(video)], telemetry=srt), 32)
    assert images.provenance[0][0] == "c.jpg XMP drone-dji:RelativeAltitude" and not caught
    assert clip.provenance[8][0] == "flight.SRT subtitle 9 rel_alt"
    out = tmp_path / "out"
    main(["predict", str(image), str(video), "--ckpt_path", str(checkpoint), "--out", str(out), "--device", "cpu",
          "--telemetry", str(srt), "--frame_step", "4", "--outputs", "camera"])
    assert json.loads((out / "c_camera.json").read_text())["pose_provenance"]["height_m"] == \
        "c.jpg XMP drone-dji:RelativeAltitude"
    assert json.loads((out / "v_f000004_camera.json").read_text())["pose_provenance"]["height_m"] == \
        "flight.SRT subtitle 5 rel_alt"
    with pytest.raises(ValueError, match=r"--telemetry .*flight.SRT: one SRT for 2 videos \(v.avi, w.avi\); predict "
                                         r"its video alone with it, leave each video's .SRT beside it"):
        source_datasets(PredictSource([str(image), str(video), str(other)], telemetry=srt), 32)
    with pytest.raises(TelemetryError, match="flight.SRT: a DJI SRT gives the telemetry of the video"):
        source_datasets(PredictSource([str(image)], telemetry=srt), 32)


def test_a_csv_names_the_frames_of_videos_found_by_a_pattern_as_their_outputs_are_named(tmp_path):
    """Two flights' DJI_0005 in 100MEDIA/ and 101MEDIA/: outputs 100MEDIA_DJI_0005_f..., 101MEDIA_DJI_0005_f...; each
    video takes the rows naming its own frames (before: the rows named DJI_0005_f..., the same for both videos)."""
    for folder in ("100MEDIA", "101MEDIA"):
        (tmp_path / folder).mkdir()
        write_video(tmp_path / folder / "DJI_0005.avi", frames=3)
    table = tmp_path / "flight.csv"
    table.write_text("name,height_m\n100MEDIA_DJI_0005_f000000,40\n101MEDIA_DJI_0005_f000001,80\nDJI_0005_f000002,9\n")
    (first, second), caught = record(source_datasets,
                                     PredictSource(str(tmp_path / "*" / "DJI_0005.avi"), telemetry=table), 32)
    assert (first.name, second.name) == ("100MEDIA_DJI_0005", "101MEDIA_DJI_0005")
    assert {f: p[0] for f, p in first.priors.items()} == {0: 40.0}
    assert {f: p[0] for f, p in second.priors.items()} == {1: 80.0}
    assert first.provenance[0][0] == "flight.csv line 2"
    assert len(caught) == 1 and "1 of 3 name(s) match no frame of DJI_0005.avi or DJI_0005.avi (frames are named " \
        "as their outputs: 100MEDIA_DJI_0005_f000012): DJI_0005_f000002" in caught[0]


def test_a_drone_video_s_frames_get_their_own_pose_camera_and_ground_from_its_srt(checkpoint, tmp_path, monkeypatch):
    """The numbers of `predict FLIGHT.MP4` end to end, at 29.97 fps (DJI's millisecond timings), every 3rd frame, 3 of
    them: each frame's row, K and point cloud come from its own subtitle (height, pitch, roll and the digital zoom
    change every frame), on a non-square video; with the network's depth replaced by "far" and the IGD bound at margin
    0, the depth is the flat ground of the SRT's pose, so every point lies on z = 0."""
    from dapm_lightning.models import dapm
    from tests.inference.test_predict import read_ply_independently

    height_px, width_px, frames = 36, 60, 8
    write_video(tmp_path / "DJI_0007.avi", frames=frames, size=(height_px, width_px), fps=29.97)
    subtitles, truth = [], {}
    for f in range(frames):
        start, end = (round(k * 1001 / 30) for k in (f, f + 1))
        height, pitch, roll, zoom = 30.0 + 1.5 * f, -55.0 + 0.8 * f, -9.0 + 2.4 * f, 1.0 + 0.05 * f
        width_mm = math.hypot(36, 24) * 0.8  # 5:3, wider than 3:2: cut from the width of a 4:3 sensor
        truth[f] = (height, pitch, roll, math.degrees(2 * math.atan(width_mm / (2 * 24.0 * zoom))))
        subtitles.append(f"{f + 1}\n00:00:00,{start:03d} --> 00:00:00,{end:03d}\n<font size=\"28\">FrameCnt: {f + 1}\n"
                         f"[fnum : 280] [focal_len : 240] [dzoom_ratio: {round(zoom * 10000)}, delta:0],"
                         f"[latitude: 49.1] [rel_alt: {height:.3f} abs_alt: 500.000] "
                         f"[gb_yaw: 1.0 gb_pitch: {pitch:.1f} gb_roll: {roll:.1f}] </font>\n")
    (tmp_path / "DJI_0007.SRT").write_text("\n".join(subtitles))
    network = dapm.DAPMOutput.inference_outputs

    def far(self, spread=False):
        out = network(self, spread)
        return out.replace(depth_m=torch.full_like(out.depth_m, 999.0), sky_prob=torch.zeros_like(out.sky_prob))

    monkeypatch.setattr(dapm.DAPMOutput, "inference_outputs", far)
    out = tmp_path / "out"
    main(["predict", str(tmp_path / "DJI_0007.avi"), "--ckpt_path", str(checkpoint), "--out", str(out), "--device",
          "cpu", "--frame_step", "3", "--max_frames", "3", "--image_width", str(width_px), "--igd_bound", "0",
          "--points_stride", "1", "--outputs", "camera,points"])
    rows = json.loads((out / "poses.json").read_text())
    assert [r["name"] for r in rows] == ["DJI_0007_f000000", "DJI_0007_f000003", "DJI_0007_f000006"]
    for row in rows:
        f = int(row["name"][-6:])
        assert [row[k] for k in ("height_m", "pitch_deg", "roll_deg", "fov_deg")] == pytest.approx(truth[f], abs=1e-4)
        assert row["height_m_provenance"] == f"DJI_0007.SRT subtitle {f + 1} rel_alt"
        zoomed = " x dzoom_ratio" if f else ""  # frame 0: dzoom_ratio 10000, 1x
        assert row["fov_deg_provenance"] == f"DJI_0007.SRT subtitle {f + 1} focal_len{zoomed}"
        assert row["time_s"] == pytest.approx(f / 29.97, abs=2e-3)
        camera = json.loads((out / f"{row['name']}_camera.json").read_text())
        # the SRT's values as it wrote them, not their float32 storage (-55.0, not -55.000003814697266)
        assert camera["pose"]["pitch_deg"]["value"] == float(f"{truth[f][1]:.1f}")
        assert camera["pose"]["height_m"]["value"] == float(f"{truth[f][0]:.3f}")
        fx = width_px / (2 * math.tan(math.radians(truth[f][3]) / 2))
        assert np.array(camera["K"]) == pytest.approx(np.array([[fx, 0, width_px / 2], [0, fx, height_px / 2],
                                                                [0, 0, 1]]), abs=1e-3)
        points = read_ply_independently(out / f"{row['name']}_points.ply")
        xyz = np.stack([points["x"], points["y"], points["z"]], 1).astype(np.float64)
        assert len(xyz) == height_px * width_px
        distance = np.linalg.norm(xyz - [0.0, 0.0, truth[f][0]], axis=1)
        assert np.abs(xyz[:, 2]).max() < 1e-5 * distance.max()
