"""Sources as users have them: an SD card's folders, .JPG, several SOURCE arguments, .txt lists, videos among them."""

import codecs
import json
import os
import shutil
import struct
import subprocess
import sys
import time
import warnings
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from dapm_lightning.cli import main
from dapm_lightning.inference.sources import _unique_names, case_free, resolve_sources
from tests.inference.test_predict import write_video


def write_image(path, shape=(30, 40), seed=0):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.random.default_rng(seed).integers(0, 255, (*shape, 3), np.uint8))
    return path


@pytest.fixture()
def sd_card(tmp_path):
    """A DJI card: photos in DCIM/100MEDIA and 101MEDIA (numbering restarted), a video, macOS and system junk."""
    card = tmp_path / "card"
    write_image(card / "DCIM" / "100MEDIA" / "DJI_0001.JPG", seed=1)
    write_image(card / "DCIM" / "100MEDIA" / "DJI_0002.JPG", (36, 36), seed=2)
    write_image(card / "DCIM" / "101MEDIA" / "DJI_0001.JPG", seed=3)
    write_video(card / "DCIM" / "100MEDIA" / "DJI_0003.AVI", frames=3)
    (card / "DCIM" / "100MEDIA" / "._DJI_0001.JPG").write_bytes(b"AppleDouble")  # would not decode
    write_image(card / ".Trashes" / "old.jpg")
    return card


def test_a_card_folder_is_searched_recursively_with_traceable_names(sd_card):
    files, notes = resolve_sources(sd_card)
    assert [(f.name, f.kind) for f in files] == [("DCIM_100MEDIA_DJI_0001", "image"),
                                                 ("DCIM_100MEDIA_DJI_0002", "image"),
                                                 ("DCIM_101MEDIA_DJI_0001", "image")]
    assert len(notes) == 1 and "1 video(s) not predicted (DCIM/100MEDIA/DJI_0003.AVI)" in notes[0]


def test_patterns_match_extensions_in_any_case(sd_card):
    assert case_free("a/B/*.jpg") == "a/B/*.[jJ][pP][gG]" and case_free("x/[ab]*.png") == "x/[ab]*.[pP][nN][gG]"
    files, _ = resolve_sources(f"{sd_card}/**/*.jpg")  # quoted as the docs say; DJI writes .JPG
    assert [f.name for f in files] == ["DCIM_100MEDIA_DJI_0001", "DCIM_100MEDIA_DJI_0002", "DCIM_101MEDIA_DJI_0001"]
    files, _ = resolve_sources(f"{sd_card}/DCIM/*/*.avi")  # a pattern may name videos
    assert [(f.name, f.kind) for f in files] == [("100MEDIA_DJI_0003", "video")]
    with pytest.raises(FileNotFoundError, match=r"\*\.gif: the pattern matches no image or video"):
        resolve_sources(f"{sd_card}/*.gif")
    files, _ = resolve_sources(f"{sd_card}/DCIM/10[1]MEDIA/DJI_0001.JPG")  # a bracket alone makes a pattern
    assert [f.name for f in files] == ["101MEDIA_DJI_0001"]  # named below the pattern's root, as any pattern


def test_several_sources_and_lists_keep_names_unique(sd_card, tmp_path):
    media = sd_card / "DCIM"
    one, two = media / "100MEDIA" / "DJI_0001.JPG", media / "101MEDIA" / "DJI_0001.JPG"
    files, _ = resolve_sources([one, two, one, media / "100MEDIA" / "DJI_0003.AVI"])  # a file twice: once
    assert [(f.name, f.kind) for f in files] == [("100MEDIA_DJI_0001", "image"), ("101MEDIA_DJI_0001", "image"),
                                                 ("DJI_0003", "video")]
    listing = sd_card / "survey.txt"
    listing.write_text("# today's flight\nDCIM/100MEDIA/DJI_0002.JPG\n\nDCIM/100MEDIA/DJI_0003.AVI\n")
    files, _ = resolve_sources(listing)  # paths relative to the list's folder
    assert [(f.path, f.name) for f in files] == [(media / "100MEDIA" / "DJI_0002.JPG", "DJI_0002"),
                                                 (media / "100MEDIA" / "DJI_0003.AVI", "DJI_0003")]
    listing.write_text("DCIM/100MEDIA/DJI_0002.JPG\nDCIM/100MEDIA/DJI_9999.JPG\n")
    with pytest.raises(FileNotFoundError, match=r"survey.txt line 2: .*DJI_9999.JPG: no such file or folder"):
        resolve_sources(listing)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ValueError, match="no images .*any case, sub-folders included\\)\nFix: give a folder that"):
        resolve_sources(empty)
    (empty / "FLIGHT.MP4").write_bytes(b"")
    with pytest.raises(ValueError, match=r"holds video\(s\) FLIGHT.MP4\)\nFix: give the video file itself, e.g. "):
        resolve_sources(empty)


def test_a_missing_list_entry_is_fixed_from_the_lists_folder(sd_card, tmp_path, capsys, monkeypatch):
    """A .txt list's relative entries start from the list's folder: the fix says so, not "the current directory"."""
    monkeypatch.chdir(tmp_path)
    listing = sd_card / "survey.txt"
    for line in ("DCIM/100MEDIA/DJI_9999.JPG", "DCIM/9*MEDIA/*.JPG"):
        listing.write_text(f"DCIM/100MEDIA/DJI_0002.JPG\n{line}\n")
        with pytest.raises(SystemExit) as stop:
            main(["predict", "card/survey.txt", "--ckpt_path", "missing.ckpt"])  # refused before the model loads
        lines = capsys.readouterr().err.splitlines()
        assert stop.value.code == 1 and lines[0].startswith(f"error: card/survey.txt line 2: card/{line}: "), lines
        assert lines[1] == ("Fix: correct or remove line 2 of card/survey.txt; a relative path in a list starts from "
                            f"the list's folder ({sd_card.resolve()}), not the current directory."), lines


def test_one_line_predict_takes_an_unquoted_glob_a_list_and_a_video(checkpoint, sd_card, tmp_path, capsys,
                                                                    monkeypatch):
    media = sd_card / "DCIM" / "100MEDIA"
    out = tmp_path / "out"
    # the shell expanded 'DCIM/*/DJI_0001.JPG' into two paths; options before, between and after SOURCE
    main(["predict", str(sd_card / "DCIM" / "100MEDIA" / "DJI_0001.JPG"), "--ckpt_path", str(checkpoint),
          str(sd_card / "DCIM" / "101MEDIA" / "DJI_0001.JPG"), str(media / "DJI_0003.AVI"), "--out", str(out),
          "--device", "cpu", "--outputs", "camera"])
    assert "predicted 5 images" in capsys.readouterr().out
    names = sorted(p.name for p in out.glob("*_camera.json"))
    assert names == ["100MEDIA_DJI_0001_camera.json", "101MEDIA_DJI_0001_camera.json",
                     *(f"DJI_0003_f{k:06d}_camera.json" for k in range(3))]

    listing = tmp_path / "list.txt"
    listing.write_text(f"{media / 'DJI_0002.JPG'}\n{media / 'DJI_0003.AVI'}\n")
    one_line, lightning = tmp_path / "one_line", tmp_path / "lightning"
    main(["predict", str(listing), "--ckpt_path", str(checkpoint), "--out", str(one_line), "--device", "cpu",
          "--outputs", "camera", "depth_npy"])
    monkeypatch.chdir(tmp_path)
    main(["predict", "--config", "configs/predict.yaml", "--ckpt_path", str(checkpoint),
          "--data.init_args.source", f"[{listing}]", "--data.init_args.num_workers", "0",
          "--trainer.callbacks.output_dir", str(lightning), "--trainer.callbacks.outputs", "[camera, depth_npy]"])
    expected = {p.name: p.read_bytes() for p in one_line.iterdir()}
    assert len([n for n in expected if n.endswith("_camera.json")]) == 4  # an image and the video's 3 frames
    assert {p.name: p.read_bytes() for p in lightning.iterdir()} == expected
    assert [r["name"] for r in json.loads((one_line / "poses.json").read_text())][:2] == ["DJI_0002",
                                                                                          "DJI_0003_f000000"]


def test_a_jpeg_cut_short_is_read_with_a_warning_naming_it(tmp_path):
    """OpenCV decodes a truncated JPEG, the missing rows grey, saying so only in a libjpeg line naming no file."""
    import warnings

    from dapm_lightning.inference.pixels import jpeg_cut_short, read_image

    rng = np.random.default_rng(0)
    ok, data = cv2.imencode(".jpg", rng.integers(0, 255, (64, 64, 3), dtype=np.uint8))
    whole, cut = tmp_path / "whole.jpg", tmp_path / "cut.jpg"
    whole.write_bytes(data.tobytes() + b"\x00\x00")  # padding after the end marker is not a cut
    cut.write_bytes(data.tobytes()[: len(data) // 2])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert read_image(whole).shape == (64, 64, 3) and read_image(cut).shape == (64, 64, 3)
    messages = [str(w.message) for w in caught]
    assert len(messages) == 1 and messages[0].startswith(f"{cut}: the JPEG stops before its end marker")
    png = tmp_path / "p.png"
    cv2.imwrite(str(png), np.zeros((8, 8, 3), np.uint8))
    assert not jpeg_cut_short(whole) and jpeg_cut_short(cut) and not jpeg_cut_short(png)


def test_a_telemetry_file_that_is_not_there_is_named_as_the_telemetry(tmp_path):
    from dapm_lightning.inference.inputs import PredictSource
    from dapm_lightning.tools.errors import describe

    for given, what in ((tmp_path / "nosuch.csv", "no such file"), (tmp_path, "a folder, not a file")):
        with pytest.raises(FileNotFoundError) as info:
            PredictSource([str(tmp_path)], telemetry=given)
        message, expected = describe(info.value)
        assert message.startswith(f"--telemetry {given}: {what}") and expected
        assert message.count("Fix:") == 1 and "or leave --telemetry out" in message


def test_names_of_a_large_survey_are_made_unique_in_linear_time():
    """60,000 photos (a mapping survey over many cards): their names were checked for clashes by counting each
    name in the whole list, 60,000 x 60,000 comparisons (~50 s before the model loaded, twice over). Now counted
    once; the clashing pair still gets its folders' names."""
    found = [(Path(f"/survey/card{k // 1000:02d}/DJI_{k:05d}.JPG"), f"DJI_{k:05d}") for k in range(60_000)]
    found += [(Path("/a/day1/X.JPG"), "X"), (Path("/a/day2/X.JPG"), "X")]
    start = time.perf_counter()
    named = _unique_names(found)
    assert time.perf_counter() - start < 5.0
    assert [name for _, name in named[-3:]] == ["DJI_59999", "day1_X", "day2_X"]


def test_names_alike_in_their_folder_take_the_folder_above_it_too():
    found = [(Path("/cards/A/100MEDIA/DJI_0001.JPG"), "DJI_0001"), (Path("/cards/B/100MEDIA/DJI_0001.JPG"), "DJI_0001"),
             (Path("/cards/A/100MEDIA/DJI_0002.JPG"), "DJI_0002")]
    assert [name for _, name in _unique_names(found)] == ["A_100MEDIA_DJI_0001", "B_100MEDIA_DJI_0001", "DJI_0002"]


def test_an_image_named_as_a_video_frame_is_refused_beside_that_video(tmp_path):
    """``clip_f000000.png`` beside ``clip.mp4``: the image and the video's first frame wrote the same files."""
    for name in ("clip.mp4", "clip_f000000.png", "clip_f12.png", "other_f000001.png"):
        (tmp_path / name).touch()
    sources = [str(tmp_path / n) for n in ("clip.mp4", "clip_f000000.png")]
    with pytest.raises(ValueError, match=r"clip_f000000.png and a frame of .*clip.mp4 would write the same"):
        resolve_sources(sources)
    files, _ = resolve_sources([str(tmp_path / n) for n in ("clip.mp4", "clip_f12.png", "other_f000001.png")])
    assert [f.name for f in files] == ["clip", "clip_f12", "other_f000001"]  # no frame of clip.mp4 has those names


def test_a_run_written_inside_the_images_folder_is_not_read_back_as_images(sd_card, checkpoint, capsys, caplog):
    """Photos given one by one (a shell-expanded glob) may write next to themselves; a later run on the card
    leaves that run's pictures out with one note naming its folder, and the folder alone is refused with a fix."""
    media = sd_card / "DCIM" / "100MEDIA"
    out = media / "pred"
    main(["predict", str(media / "DJI_0001.JPG"), str(media / "DJI_0002.JPG"), "--ckpt_path", str(checkpoint),
          "--out", str(out), "--device", "cpu"])
    capsys.readouterr()
    assert (out / "DJI_0001_depth_color.png").is_file() and (out / ".dapm_predict").is_file()
    files, notes = resolve_sources(sd_card)
    assert [f.name for f in files] == ["DCIM_100MEDIA_DJI_0001", "DCIM_100MEDIA_DJI_0002", "DCIM_101MEDIA_DJI_0001"]
    note = (f"{out}: a predict output folder, its 5 picture(s) written by predict left out (depth maps, not drone "
            "images); name them one by one to predict them anyway")
    assert [n for n in notes if "output folder" in n] == [note]
    with pytest.raises(FileNotFoundError, match="Fix: .*pred is a predict output folder"):  # only its PNGs match
        resolve_sources(f"{sd_card}/**/*.png")

    main(["predict", str(sd_card / "DCIM"), "--ckpt_path", str(checkpoint), "--out", str(sd_card.parent / "run2"),
          "--device", "cpu", "--outputs", "camera"])
    assert "predicted 3 images" in capsys.readouterr().out
    assert [r.message for r in caplog.records if "output folder" in r.message] == [note]
    assert sorted(p.name for p in (sd_card.parent / "run2").glob("*_camera.json")) == [
        "100MEDIA_DJI_0001_camera.json", "100MEDIA_DJI_0002_camera.json", "101MEDIA_DJI_0001_camera.json"]

    (out / ".dapm_predict").unlink()  # a run from before the marker: its poses tables tell it
    with pytest.raises(ValueError, match="no images .*\nFix: .*pred is a predict output folder"):
        resolve_sources(out)
    assert resolve_sources(out / "DJI_0001_depth_color.png")[0][0].name == "DJI_0001_depth_color"  # named: kept


# ---------------------------------------------------------------------------------------- files predict cannot read
def png_header(path, width, height):
    """A PNG of one tiny IDAT whose header claims ``width x height`` pixels (its size is read, never decoded)."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\x00" * 8)) + chunk(b"IEND", b""))
    return path


def test_an_image_whose_header_claims_too_many_pixels_is_refused_by_name_without_decoding(tmp_path, monkeypatch):
    """A 68-byte PNG claiming 100000 x 100000 pixels: Pillow's decompression-bomb refusal fell back to OpenCV,
    whose own refusal ended in its assertion text, "error:" twice, no file named (and OpenCV decoded the images
    of 179M to 1.07G pixels whole just to read their size). Now the size comes from the header alone."""
    from dapm_lightning.inference.pixels import MAX_PIXELS, image_size, read_image
    from dapm_lightning.tools.errors import describe

    bomb, large = png_header(tmp_path / "bomb.png", 100_000, 100_000), png_header(tmp_path / "large.png", 11664, 8750)
    with pytest.raises(ValueError) as info:
        read_image(bomb)  # what OpenCV refuses to decode is named too
    assert str(info.value).startswith(f"{bomb}: more pixels than OpenCV decodes")
    monkeypatch.setattr(cv2, "imread", lambda *args: pytest.fail("decoded to read its size"))
    with pytest.raises(ValueError) as info:
        image_size(bomb)
    message, expected = describe(info.value)
    assert expected and message == (f"{bomb}: 10,000,000,000 pixels by its header, more than the {MAX_PIXELS:,} "
                                    "pixels predict reads (a damaged header, a decompression bomb, or a huge mosaic)\n"
                                    "Fix: downscale it or cut it into tiles below that size (predict sees each image "
                                    "at its network size anyway)")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a 100-megapixel mapping camera's photo: no decompression-bomb warning
        assert image_size(large) == (8750, 11664)


@pytest.mark.parametrize("encoding", ["utf-8-sig", "utf-16", "utf-16-be"])
def test_a_list_saved_as_unicode_with_a_byte_order_mark_is_read(tmp_path, encoding):
    write_image(tmp_path / "vue_été.png")
    listing = tmp_path / "list.txt"
    text = "# vol\nvue_été.png\n"
    listing.write_bytes((codecs.BOM_UTF16_BE + text.encode("utf-16-be")) if encoding == "utf-16-be"
                        else text.encode(encoding))
    assert [f.name for f in resolve_sources(listing)[0]] == ["vue_été"]


@pytest.mark.parametrize(("data", "line", "byte"), [("# vol\nvue_été.png\n".encode("latin-1"), 2, "0xe9"),
                                                    (bytes([0x17, 0x78, 0x62, 0x9a, 0x28, 0x1b]), 1, "0x9a")],
                         ids=["latin-1", "binary"])
def test_a_list_that_is_not_utf8_is_named_with_its_line_and_the_fix(tmp_path, capsys, data, line, byte):
    """A list saved as Latin-1 (or a binary file named .txt) ended in "'utf-8' codec can't decode byte 0xe9 in
    position 9", naming no file."""
    listing = tmp_path / "list.txt"
    listing.write_bytes(data)
    with pytest.raises(SystemExit) as stop:
        main(["predict", str(listing), "--ckpt_path", "missing.ckpt"])  # refused before the model loads
    lines = capsys.readouterr().err.splitlines()
    assert stop.value.code == 1 and lines[0] == (f"error: {listing} line {line}: not UTF-8 text (byte {byte}): a list "
                                                 "of paths is read as UTF-8 (or UTF-16 with its byte-order mark)")
    assert lines[1] == "Fix: save it as UTF-8 text (in an editor: Save as, encoding UTF-8), one path a line"


def test_a_broken_link_in_a_folder_is_warned_about_by_name(tmp_path):
    write_image(tmp_path / "flight" / "a.png")
    (tmp_path / "flight" / "b.png").symlink_to(tmp_path / "gone" / "b.png")
    (tmp_path / "flight" / "notes").symlink_to(tmp_path / "gone" / "notes")  # not an image: not a loss
    with pytest.warns(UserWarning) as caught:
        files, _ = resolve_sources(tmp_path / "flight")
    assert [f.name for f in files] == ["a"] and [str(w.message) for w in caught] == [
        f"{tmp_path / 'flight'}: 1 broken link(s) not predicted (the file each names is not there): b.png -> "
        f"{tmp_path / 'gone' / 'b.png'}. Fix: put the files back where the links point, or remove the links"]


UNREADABLE_CHECK = """
import sys, warnings
from pathlib import Path
from dapm_lightning.inference.inputs import VideoFramesDataset
from dapm_lightning.inference.pixels import image_size
from dapm_lightning.inference.sources import resolve_sources

warnings.simplefilter("always")
warnings.showwarning = lambda message, *args: print("warning:", message)
for source in sys.argv[1:]:
    try:
        files, _ = resolve_sources(source)
        for file in files:
            image_size(file.path) if file.kind == "image" else VideoFramesDataset(file.path)
        print("predicted", [file.name for file in files])
    except ValueError as error:
        print("error:", error)
"""


def run_where_permissions_hold(code, *args):
    """``python -c code ARGS``'s output where file permissions hold: as root, without the capabilities that let it
    read any file (``setpriv``); skipped where that cannot be done."""
    command = [sys.executable, "-c", code, *map(str, args)]
    if os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.skip("root, and no setpriv to drop the capabilities that read any file")
        command = ["setpriv", "--bounding-set=-dac_override,-dac_read_search", "--", *command]
    done = subprocess.run(command, capture_output=True, text=True, cwd=Path(__file__).parents[2])
    if done.returncode and done.stderr.startswith("setpriv"):
        pytest.skip(f"capabilities cannot be dropped here: {done.stderr.strip()}")
    assert done.returncode == 0, done.stderr
    return done.stdout.splitlines()


def test_unreadable_sources_are_named_as_such_with_the_fix(tmp_path):
    """Without read permission: a sub-folder of an input folder was skipped silently (exit 0), an image was called
    damaged ("replace it with an intact copy"), a list or a video ended in a message that did not say why."""
    flight, locked = tmp_path / "flight", tmp_path / "locked"
    write_image(flight / "a.png")
    write_image(flight / "day2" / "b.png")
    write_image(flight / ".hidden" / "c.png")  # hidden, left out: not warned about
    write_image(locked / "d.png")
    listing = tmp_path / "list.txt"
    listing.write_text("flight/a.png\n")
    video = write_video(tmp_path / "clip.avi", frames=2)
    for path in (flight / "day2", flight / ".hidden", locked, flight / "a.png", listing, video):
        path.chmod(0)
    try:
        lines = run_where_permissions_hold(UNREADABLE_CHECK, flight, locked, listing, video)
    finally:
        for path in (flight / "day2", flight / ".hidden", locked):
            path.chmod(0o755)

    def denied(path):
        how = "chmod -R u+rX" if path.is_dir() else "chmod u+r"
        return [f"error: {path}: cannot be read (permission denied)",
                f"Fix: make it readable ({how} {path}), or leave it out of the source"]

    assert lines == [f"warning: {flight / 'day2'}: this sub-folder of {flight} cannot be read (permission denied): "
                     f"its images are not predicted. Fix: make it readable (chmod -R u+rX {flight / 'day2'}) to "
                     "predict them", *denied(flight / "a.png"), *denied(locked), *denied(listing), *denied(video)]
