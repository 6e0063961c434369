"""Telemetry -> project pose conventions, on real files: JPEG XMP/EXIF written by Pillow, CSVs, DJI SRTs."""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import ExifTags, Image
from PIL.TiffImagePlugin import IFDRational, ImageFileDirectory_v2

from dapm_lightning.geometry.camera import camera_rays
from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.inference.telemetry import (
    PoseTelemetry,
    TelemetryError,
    TelemetryWarning,
    horizontal_fov_from_focal,
    horizontal_fov_from_focal_35mm,
    read_srt,
    read_telemetry_csv,
    srt,
    telemetry_for_images,
    telemetry_from_image,
)

NAN = math.nan
FOV_24MM_4_3 = 71.5915  # 2 atan(43.267 * 4/5 / 48) = 2 atan(34.613 / 48): f35 = 24 mm on a 4:3 image
FOV_24MM_3_2 = 73.740  # 2 atan(36 / 48): on 3:2 the diagonal definition gives exactly 36 mm of width

RDF = "http://www.w3.org/1999/02/22-rdf-syntax-ns#"
DJI = "http://www.dji.com/drone-dji/1.0/"


def xmp_attributes(**tags: str) -> bytes:
    attrs = " ".join(f'drone-dji:{k}="{v}"' for k, v in tags.items())
    return (f'<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>'
            f'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="{RDF}">'
            f'<rdf:Description rdf:about="DJI Meta Data" xmlns:drone-dji="{DJI}" {attrs}/>'
            f'</rdf:RDF></x:xmpmeta><?xpacket end="w"?>').encode()


def xmp_elements(**tags: str) -> bytes:
    children = "".join(f"<drone-dji:{k}>{v}</drone-dji:{k}>" for k, v in tags.items())
    return (f'<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="{RDF}">'
            f'<rdf:Description rdf:about="" xmlns:drone-dji="{DJI}">{children}</rdf:Description>'
            f'</rdf:RDF></x:xmpmeta>').encode() + b"\x00" * 8


def write_jpeg(path: Path, size=(400, 300), xmp: bytes | None = None, f35: int | None = None,
               focal: IFDRational | None = None) -> Path:
    exif = Image.Exif()
    exif[ExifTags.Base.Make] = "DJI"
    ifd = exif.get_ifd(ExifTags.IFD.Exif)
    if f35 is not None:
        ifd[ExifTags.Base.FocalLengthIn35mmFilm] = f35
    if focal is not None:
        ifd[ExifTags.Base.FocalLength] = focal
    kwargs = {"exif": exif} | ({"xmp": xmp} if xmp is not None else {})
    Image.new("RGB", size, (90, 120, 60)).save(path, **kwargs)
    return path


def assert_pose(t: PoseTelemetry, expected) -> None:
    np.testing.assert_allclose(t.values(), np.asarray(expected, float), atol=1e-3, equal_nan=True)


def record(fn, *args, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = fn(*args, **kwargs)
    return out, [w for w in caught if issubclass(w.category, TelemetryWarning)]


# ------------------------------------------------------------------------------------------------ FoV


def test_fov_from_35mm_uses_the_diagonal_definition():
    assert horizontal_fov_from_focal_35mm(24, 4000, 3000) == pytest.approx(71.6, abs=0.01)
    assert horizontal_fov_from_focal_35mm(24, 4000, 3000) == pytest.approx(
        math.degrees(2 * math.atan(43.27 * 4000 / math.hypot(4000, 3000) / 48)), abs=0.01)
    assert horizontal_fov_from_focal_35mm(24, 4000, 3000) == pytest.approx(FOV_24MM_4_3, abs=1e-3)
    assert horizontal_fov_from_focal_35mm(24, 5472, 3648) == pytest.approx(FOV_24MM_3_2, abs=1e-3)
    # only the aspect matters; a portrait image is narrower across its width
    assert horizontal_fov_from_focal_35mm(24, 400, 300) == pytest.approx(FOV_24MM_4_3, abs=1e-3)
    assert horizontal_fov_from_focal_35mm(24, 3000, 4000) == pytest.approx(
        math.degrees(2 * math.atan(43.2666 * 0.6 / 48)), abs=1e-3)


def test_a_frame_wider_than_3_2_is_cut_from_the_sensor_s_width():
    """DJI quotes one focal length (24 mm) for its photos and its 16:9 video, which uses the sensor's full width:
    before, the 16:9 frame's own diagonal was taken for the full frame's, putting a 4K video at 76.3 degrees, wider
    than the 4:3 photos of the same lens (71.6)."""
    assert horizontal_fov_from_focal_35mm(24, 3840, 2160) == pytest.approx(FOV_24MM_4_3, abs=1e-3)
    assert horizontal_fov_from_focal_35mm(24, 4096, 2160) == pytest.approx(FOV_24MM_4_3, abs=1e-3)  # DCI 4K
    assert horizontal_fov_from_focal_35mm(24, 3840, 2160, sensor_aspect=1.5) == pytest.approx(FOV_24MM_3_2, abs=1e-3)
    # a portrait 16:9 frame: the sensor's long side spans its height
    assert horizontal_fov_from_focal_35mm(24, 2160, 3840) == pytest.approx(
        math.degrees(2 * math.atan(43.2666 * 0.8 * 2160 / 3840 / 48)), abs=1e-3)
    # frames up to 3:2 fill their sensor, a thermal camera's 5:4 included
    assert horizontal_fov_from_focal_35mm(24, 640, 512) == pytest.approx(
        math.degrees(2 * math.atan(43.2666 * 640 / math.hypot(640, 512) / 48)), abs=1e-3)
    # the sensor's aspect given: a frame narrower than it is cut to its height (a 4:3 photo of a 3:2 sensor)
    assert horizontal_fov_from_focal_35mm(24, 4864, 3648, sensor_aspect=1.5) == pytest.approx(
        math.degrees(2 * math.atan(24 * 4 / 3 / 48)), abs=1e-3)
    assert horizontal_fov_from_focal_35mm(24, 4000, 3000, sensor_aspect=4 / 3) == pytest.approx(FOV_24MM_4_3, abs=1e-3)
    with pytest.raises(ValueError, match="sensor_aspect"):
        horizontal_fov_from_focal_35mm(24, 3840, 2160, sensor_aspect=0.5)


def test_fov_from_focal_and_sensor_width():
    assert horizontal_fov_from_focal(8.8, 13.2) == pytest.approx(FOV_24MM_3_2, abs=1e-3)  # Phantom 4 Pro
    assert horizontal_fov_from_focal(10.0, 20.0) == pytest.approx(90.0)


@pytest.mark.parametrize("args", [(0, 400, 300), (-24, 400, 300), (NAN, 400, 300), (24, 0, 300)])
def test_fov_from_35mm_rejects_impossible_input(args):
    with pytest.raises(ValueError):
        horizontal_fov_from_focal_35mm(*args)


def test_fov_from_focal_rejects_impossible_input():
    with pytest.raises(ValueError, match="focal"):
        horizontal_fov_from_focal(0, 13.2)
    with pytest.raises(ValueError, match="sensor"):
        horizontal_fov_from_focal(8.8, -1)


# -------------------------------------------------------------------------------------- PoseTelemetry


def test_pose_telemetry_values_known_and_merge():
    a = PoseTelemetry(height_m=45.2, roll_deg=-3.0, source="flight.csv line 2")
    b = PoseTelemetry(height_m=10.0, pitch_deg=-90.0, fov_deg=71.6, source="DJI_0001.JPG XMP/EXIF")
    assert a.values().dtype == np.float64 and a.values().shape == (4,)
    assert_pose(a, [45.2, NAN, -3.0, NAN])
    assert a.known() == (True, False, True, False)
    m = a.merged(b)
    assert_pose(m, [45.2, -90.0, -3.0, 71.6])  # own known components win
    assert m.source == "flight.csv line 2 (height, roll); DJI_0001.JPG XMP/EXIF (pitch, fov)"
    assert PoseTelemetry().merged(b) == b
    assert a.merged(PoseTelemetry()) == a
    assert PoseTelemetry().merged(PoseTelemetry()) == PoseTelemetry()
    assert PoseTelemetry(pitch_deg=float("nan")) == PoseTelemetry()  # NaN equals NaN here
    assert len({PoseTelemetry(), PoseTelemetry(fov_deg=float("nan"))}) == 1


@pytest.mark.parametrize("kwargs", [{"height_m": 0.0}, {"height_m": math.inf}, {"pitch_deg": 181.0},
                                    {"roll_deg": -200.0}, {"fov_deg": 180.0}, {"fov_deg": 0.0}])
def test_pose_telemetry_rejects_impossible_values(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        PoseTelemetry(**kwargs)


# ------------------------------------------------------------------------------------- image metadata


def test_dji_xmp_attributes_and_exif_35mm(tmp_path):
    path = write_jpeg(tmp_path / "DJI_0001.JPG", (400, 300), f35=24, xmp=xmp_attributes(
        RelativeAltitude="+45.20", AbsoluteAltitude="+120.50", GimbalPitchDegree="-90.00",
        GimbalRollDegree="+2.50", GimbalYawDegree="+10.30"))
    t = telemetry_from_image(path)
    assert_pose(t, [45.2, -90.0, 2.5, FOV_24MM_4_3])  # DJI pitch -90 = nadir = project -90; roll as is
    assert t.source == "DJI_0001.JPG XMP/EXIF"


def test_a_focal_length_written_in_the_main_ifd_is_read_too(tmp_path):
    """Some tools write the Exif focal lengths into IFD0 rather than the Exif sub-IFD: read there as well."""
    exif = Image.Exif()
    exif[ExifTags.Base.FocalLengthIn35mmFilm] = 24
    Image.new("RGB", (400, 300)).save(tmp_path / "ifd0.jpg", exif=exif)
    t = telemetry_from_image(tmp_path / "ifd0.jpg")
    assert t.fov_deg == pytest.approx(FOV_24MM_4_3) and t.provenance[3] == "ifd0.jpg EXIF FocalLengthIn35mmFilm"


def test_dji_xmp_child_elements(tmp_path):
    path = write_jpeg(tmp_path / "DJI_0002.jpg", (342, 228), f35=24, xmp=xmp_elements(
        RelativeAltitude="+30.0", GimbalPitchDegree="-45.0", GimbalRollDegree="-1.5"))
    assert_pose(telemetry_from_image(path), [30.0, -45.0, -1.5, FOV_24MM_3_2])


def test_focal_length_with_sensor_width_wins_over_35mm(tmp_path):
    path = write_jpeg(tmp_path / "p4p.jpg", (342, 228), f35=20, focal=IFDRational(88, 10))
    with_sensor = telemetry_from_image(path, sensor_width_mm=13.2)
    assert_pose(with_sensor, [NAN, NAN, NAN, FOV_24MM_3_2])  # 2 atan(13.2 / 17.6)
    assert with_sensor.source == "p4p.jpg EXIF"
    without = telemetry_from_image(path)
    assert without.fov_deg == pytest.approx(math.degrees(2 * math.atan(36 / 40)), abs=1e-3)  # from f35 = 20


def test_the_sensor_width_help_says_it_wins_over_the_35mm_equivalent(capsys):
    """As the code does (above): the help of --sensor_width_mm and data.init_args.sensor_width_mm said it served only
    images without a 35 mm equivalent."""
    from dapm_lightning.cli import main
    from dapm_lightning.inference.datamodule import PredictDataModule

    with pytest.raises(SystemExit):
        main(["predict", "--help"])
    help_text = " ".join(capsys.readouterr().out.split())
    assert "each image's EXIF FocalLength then gives its FoV, before its 35 mm equivalent" in help_text
    assert "without a 35 mm equivalent" not in help_text
    docstring = " ".join((PredictDataModule.__doc__ or "").split())
    assert "sensor_width_mm: sensor width in mm (of the area the images cover): each image's EXIF FocalLength then " \
           "gives its FoV, before its 35 mm equivalent" in docstring


def test_focal_length_without_sensor_width_or_35mm_is_unknown(tmp_path):
    path = write_jpeg(tmp_path / "f.jpg", focal=IFDRational(88, 10))
    assert telemetry_from_image(path) == PoseTelemetry()
    assert telemetry_from_image(write_jpeg(tmp_path / "zero.jpg", f35=0)) == PoseTelemetry()  # 0 = unknown


def test_image_without_metadata_and_non_image(tmp_path):
    Image.new("RGB", (40, 30)).save(tmp_path / "plain.png")
    assert telemetry_from_image(tmp_path / "plain.png") == PoseTelemetry()
    (tmp_path / "notes.jpg").write_text("not an image")
    assert telemetry_from_image(tmp_path / "notes.jpg") == PoseTelemetry()
    with pytest.raises(FileNotFoundError, match="missing.jpg"):
        telemetry_from_image(tmp_path / "missing.jpg")


@pytest.mark.parametrize(("tags", "match"), [
    ({"GimbalPitchDegree": "abc"}, r"GimbalPitchDegree = 'abc' is not a number"),
    ({"GimbalRollDegree": "200"}, r"GimbalRollDegree = 200 must be within \[-180, 180\]"),
    ({"RelativeAltitude": "nan"}, r"RelativeAltitude = nan is not finite"),
])
def test_malformed_xmp_values_are_errors_naming_the_file_and_tag(tmp_path, tags, match):
    path = write_jpeg(tmp_path / "DJI_0009.JPG", xmp=xmp_attributes(**tags))
    with pytest.raises(TelemetryError, match=match) as info:
        telemetry_from_image(path)
    assert "DJI_0009.JPG" in str(info.value) and "read_metadata=False" in str(info.value)


def test_a_focal_length_giving_an_impossible_fov_is_an_error_naming_the_file_and_tag(tmp_path):
    """A damaged EXIF block's FocalLength of 1e-300 mm (a DOUBLE where Exif has a RATIONAL) gives fov 180.0: a
    TelemetryError, so the image falls back alone (before: a plain ValueError from PoseTelemetry stopped the run)."""
    ifd = ImageFileDirectory_v2(prefix=b"II")
    ifd.tagtype[ExifTags.Base.FocalLength] = 12  # DOUBLE
    ifd[ExifTags.Base.FocalLength] = 1e-300
    path = tmp_path / "DJI_0010.JPG"
    Image.new("RGB", (64, 48)).save(path, exif=b"Exif\x00\x00II*\x00\x08\x00\x00\x00" + ifd.tobytes(8))
    with pytest.raises(TelemetryError, match=r"DJI_0010.JPG: EXIF FocalLength = 1e-300 mm gives a FoV that must be "
                                             r"within \(0, 180\).*--no_metadata"):
        telemetry_from_image(path, sensor_width_mm=13.2)
    assert math.isnan(telemetry_from_image(path).fov_deg)  # without a sensor width the focal length is not read


def test_broken_xmp_packet_is_an_error(tmp_path):
    path = write_jpeg(tmp_path / "broken.jpg", xmp=b"<x:xmpmeta><rdf:RDF>")
    with pytest.raises(TelemetryError, match="broken.jpg.*not well-formed"):
        telemetry_from_image(path)
    path = write_jpeg(tmp_path / "dtd.jpg", xmp=b'<!DOCTYPE x [<!ENTITY a "b">]><x>&a;</x>')
    with pytest.raises(TelemetryError, match="dtd.jpg.*DTD"):
        telemetry_from_image(path)


def test_relative_altitude_at_or_below_zero_is_unknown_with_a_warning(tmp_path):
    path = write_jpeg(tmp_path / "low.jpg", xmp=xmp_attributes(RelativeAltitude="-3.10", GimbalPitchDegree="-30"))
    t, caught = record(telemetry_from_image, path)
    assert_pose(t, [NAN, -30.0, NAN, NAN])
    assert len(caught) == 1 and "low.jpg" in str(caught[0].message) and "-3.10" in str(caught[0].message)
    one_metre = write_jpeg(tmp_path / "one.jpg", xmp=xmp_attributes(RelativeAltitude="+1.00"))
    t, caught = record(telemetry_from_image, one_metre)
    assert t.height_m == 1.0 and not caught  # only below 1 m is "on the ground", as in an SRT


def test_dji_roll_sign_equals_project_roll_sign(tmp_path):
    """DJI gimbal roll is aerospace roll: positive = right side down = clockwise seen from behind.

    Aerospace body axes (x forward, y right, z down): rolling by phi about x turns y into
    (0, cos phi, sin phi), so the right axis gains a *down* component sin(phi) > 0 for phi > 0.
    The project's camera with the same roll must also look down on its right edge (and up on its
    left edge): then the horizon's right end is up in the image, as docs/conventions.md ("Camera") says.
    """
    phi = 10.0
    aerospace_right_down_component = math.sin(math.radians(phi))
    assert aerospace_right_down_component > 0
    path = write_jpeg(tmp_path / "roll.jpg", xmp=xmp_attributes(GimbalPitchDegree="0.0", GimbalRollDegree=f"{phi}"))
    t = telemetry_from_image(path)
    assert t.roll_deg == phi
    h, w = 31, 41
    rays = camera_rays(torch.tensor([t.pitch_deg]), torch.tensor([t.roll_deg]), torch.tensor([60.0]), (h, w))[0]
    right, left = rays[h // 2, -1], rays[h // 2, 0]
    assert right[2] < 0 < left[2]  # right edge looks below the horizon, left edge above: right side down
    # the right axis R' (from the right-edge ray minus the centre ray) dips by exactly phi below the horizontal
    r_axis = right - rays[h // 2, w // 2]
    dip = math.degrees(math.atan2(-float(r_axis[2]), float(torch.linalg.norm(r_axis[:2]))))
    assert dip == pytest.approx(phi, abs=1e-4)


# ------------------------------------------------------------------------------------------------ CSV


def write_csv(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_csv_names_with_and_without_extension_empty_cells_and_missing_column(tmp_path):
    csv_path = write_csv(tmp_path / "flight.csv", "name,height_m,pitch_deg,roll_deg\n"
                                                  "DJI_0001.JPG,45.2,-90,\n"
                                                  "\n"
                                                  "DJI_0002, 30 ,,1.5\n"
                                                  "sub/dir/frame.001.png,12,-20,0\n"
                                                  "frame.002,,,\n")
    rows = read_telemetry_csv(csv_path)
    assert set(rows) == {"DJI_0001", "DJI_0002", "sub/dir/frame.001", "frame.002"}  # folders kept: they tell apart
    assert_pose(rows["DJI_0001"], [45.2, -90.0, NAN, NAN])  # no fov column: unknown
    assert_pose(rows["DJI_0002"], [30.0, NAN, 1.5, NAN])
    assert_pose(rows["sub/dir/frame.001"], [12.0, -20.0, 0.0, NAN])
    assert rows["frame.002"] == PoseTelemetry(source="flight.csv line 6")
    assert rows["DJI_0001"].source == "flight.csv line 2"
    assert rows["DJI_0002"].source == "flight.csv line 4"  # file line numbers, header = line 1


def test_csv_rows_named_by_folder_tell_apart_images_of_one_name(tmp_path):
    """A DJI card holds DCIM/100MEDIA/DJI_0001.JPG and DCIM/101MEDIA/DJI_0001.JPG, two photos: rows named by folder
    give each its own; a row of the bare name serving both is warned about; rows that cannot be told apart stop."""
    first = write_jpeg((tmp_path / "DCIM" / "100MEDIA").mkdir(parents=True) or tmp_path / "DCIM/100MEDIA/DJI_0001.JPG")
    second = write_jpeg((tmp_path / "DCIM" / "101MEDIA").mkdir() or tmp_path / "DCIM/101MEDIA/DJI_0001.JPG")
    by_folder = write_csv(tmp_path / "by_folder.csv", "name,height_m\n100MEDIA/DJI_0001.JPG,33\n"
                                                      "D:\\card\\DCIM\\101MEDIA\\DJI_0001.JPG,77\n")
    out, caught = record(telemetry_for_images, [first, second], by_folder, read_metadata=False)
    assert [t.height_m for t in out] == [33.0, 77.0] and not caught
    assert out[1].source == "by_folder.csv line 3"
    bare = write_csv(tmp_path / "bare.csv", "name,height_m\nDJI_0001,50\n")
    out, caught = record(telemetry_for_images, [first, second], bare, read_metadata=False)
    assert [t.height_m for t in out] == [50.0, 50.0]
    assert len(caught) == 1 and "1 row(s) serve several images of one name in different folders, e.g. `DJI_0001` " \
        "(bare.csv line 2)" in str(caught[0].message) and "100MEDIA/DJI_0001.JPG" in str(caught[0].message)
    third = write_jpeg((tmp_path / "other").mkdir() or tmp_path / "other" / "DJI_0001.JPG")
    out, _ = record(telemetry_for_images, [third], by_folder, read_metadata=False)  # rows of other folders
    assert out == [PoseTelemetry()]
    one_folder = write_csv(tmp_path / "one.csv", "name,height_m\n100MEDIA/DJI_0001.JPG,33\n")
    out, caught = record(telemetry_for_images, [first, second], one_folder, read_metadata=False)
    assert [t.height_m for t in out][0] == 33.0 and math.isnan(out[1].height_m) and not caught
    with_bare = write_csv(tmp_path / "with_bare.csv", "name,height_m\n100MEDIA/DJI_0001.JPG,33\nDJI_0001.JPG,50\n")
    out, caught = record(telemetry_for_images, [first, second, third], with_bare, read_metadata=False)
    assert [t.height_m for t in out] == [33.0, 50.0, 50.0]  # the folder's row first, the bare one for the rest
    alike = write_csv(tmp_path / "alike.csv", "name,height_m\na/100MEDIA/DJI_0001.JPG,33\nb/100MEDIA/DJI_0001,34\n")
    with pytest.raises(TelemetryError, match=r"100MEDIA/DJI_0001.JPG: the telemetry CSV has rows of different values "
                                             r"that fit this image equally \(`a/100MEDIA/DJI_0001` \(alike.csv line 2"
                                             r"\), `b/100MEDIA/DJI_0001` .*name the rows by more of their folders"):
        telemetry_for_images([first], alike, read_metadata=False)


def test_a_name_with_accents_matches_whichever_unicode_form_the_file_system_and_the_csv_use(tmp_path):
    """macOS writes `ö` as `o` + a combining diaeresis (NFD), a spreadsheet as one letter (NFC): before, the row
    matched no image (a warning listing two names that look the same) and its telemetry was not used."""
    import unicodedata

    folder = tmp_path / unicodedata.normalize("NFD", "flüge")
    folder.mkdir()
    image = write_jpeg(folder / unicodedata.normalize("NFD", "föto.jpg"))
    table = write_csv(tmp_path / "t.csv", "name,height_m\n" + unicodedata.normalize("NFC", "flüge/föto") + ",42\n")
    out, caught = record(telemetry_for_images, [image], table, read_metadata=False)
    assert [t.height_m for t in out] == [42.0] and not caught
    decomposed = write_csv(tmp_path / "d.csv", "name,height_m\n" + unicodedata.normalize("NFD", "föto") + ",43\n")
    out, caught = record(telemetry_for_images, [image], decomposed, read_metadata=False)
    assert [t.height_m for t in out] == [43.0] and not caught


def test_an_srt_given_as_the_images_csv_says_it_goes_with_a_video(tmp_path):
    srt = tmp_path / "DJI_0001.SRT"
    srt.write_text("1\n00:00:00,000 --> 00:00:00,033\n[rel_alt: 50.0 abs_alt: 120.0]\n\n")
    with pytest.raises(TelemetryError, match=r"DJI_0001.SRT: a DJI SRT gives the telemetry of the video .*"
                                             r"or give images a CSV: the first line must be the header `name,"):
        read_telemetry_csv(srt)


def test_csv_columns_in_any_order_bom_and_extra_column_warning(tmp_path):
    csv_path = tmp_path / "t.csv"
    csv_path.write_text("\ufefffov_deg, Name ,lat,pitch_deg\n71.6,a.jpg,22.5,-45\n", encoding="utf-8")
    rows, caught = record(read_telemetry_csv, csv_path)
    assert_pose(rows["a"], [NAN, -45.0, NAN, 71.6])
    assert len(caught) == 1 and "lat" in str(caught[0].message)


def test_csv_in_utf16_is_read_and_other_encodings_are_errors_naming_file_and_line(tmp_path):
    text = "name,height_m,pitch_deg\nvue_élevée.jpg,40,-45\n"
    utf16 = tmp_path / "excel_unicode.csv"
    utf16.write_bytes(text.encode("utf-16"))  # with its byte-order mark, as a spreadsheet's "Unicode text"
    assert_pose(read_telemetry_csv(utf16)["vue_élevée"], [40.0, -45.0, NAN, NAN])
    latin1 = tmp_path / "latin1.csv"
    latin1.write_bytes(text.encode("latin-1"))  # é is one byte 0xe9, not UTF-8
    with pytest.raises(TelemetryError, match=r"latin1.csv: not UTF-8 text \(byte 0xe9 on line 2\); save it as CSV "
                                             r"UTF-8"):
        read_telemetry_csv(latin1)


def test_a_spreadsheets_unicode_text_tab_separated_utf16_is_read(tmp_path):
    """Excel's "Unicode text" is UTF-16 with a byte-order mark and tabs between the columns (CRLF lines)."""
    unicode_text = tmp_path / "flight.txt"
    unicode_text.write_bytes("name\theight_m\tpitch_deg\tfov_deg\r\nvue_élevée.jpg\t40\t-45\t\r\n"
                             "b.jpg\t\t-30.5\t71.6\r\n".encode("utf-16"))
    rows = read_telemetry_csv(unicode_text)
    assert_pose(rows["vue_élevée"], [40.0, -45.0, NAN, NAN])
    assert_pose(rows["b"], [NAN, -30.5, NAN, 71.6])
    tabs_in_a_cell = write_csv(tmp_path / "t.csv", 'name,height_m\n"a\tb.jpg",40\n')  # commas: read by commas
    assert_pose(read_telemetry_csv(tabs_in_a_cell)["a\tb"], [40.0, NAN, NAN, NAN])


@pytest.mark.parametrize(("cell", "column", "match"), [
    ("abc", "pitch_deg", r"'abc' is not a number"),
    ("0", "height_m", "must be > 0 m"),
    ("-5", "height_m", "must be > 0 m"),
    ("inf", "height_m", "not finite"),
    ("nan", "roll_deg", "not finite"),
    ("-181", "pitch_deg", r"within \[-180, 180\]"),
    ("190", "roll_deg", r"within \[-180, 180\]"),
    ("180", "fov_deg", r"within \(0, 180\)"),
    ("0", "fov_deg", r"within \(0, 180\)"),
])
def test_csv_bad_values_are_errors_naming_file_line_column_and_fix(tmp_path, cell, column, match):
    values = {"height_m": "40", "pitch_deg": "-60", "roll_deg": "0", "fov_deg": "70", column: cell}
    csv_path = write_csv(tmp_path / "bad.csv", "name,height_m,pitch_deg,roll_deg,fov_deg\n"
                                               "ok.jpg,40,-60,0,70\n"
                                               f"img.jpg,{values['height_m']},{values['pitch_deg']},"
                                               f"{values['roll_deg']},{values['fov_deg']}\n")
    with pytest.raises(TelemetryError, match=match) as info:
        read_telemetry_csv(csv_path)
    message = str(info.value)
    assert str(csv_path) in message and "line 3" in message and f"column {column}" in message
    assert "leave the cell empty for unknown" in message


@pytest.mark.parametrize("rows, warned", [
    ("a,50,-0.7,0.1,1.2\nb,60,-1.5,-0.05,1.2\n", "every fov_deg lies within (0, pi] (1.2 to 1.2)"),
    ("a,50,-0.7,0.1,\nb,60,-1.5,-0.05,\n", "every pitch_deg lies within +-pi/2 (-1.5 to -0.7)"),
    ("a,50,-45,0.1,1.2\n", None),  # a telephoto's FoV at a real pitch
    ("a,50,-0.7,0.1,70\n", None),  # a camera level, its FoV in degrees
    ("a,50,-0.2,0.1,\nb,60,0.3,0,\n", None),  # level within half a degree all flight
])
def test_angles_that_look_like_radians_are_warned_about(tmp_path, rows, warned):
    """Radians in the degree columns were used as degrees without a word (a FoV of 1.2 degrees)."""
    path = write_csv(tmp_path / "t.csv", "name,height_m,pitch_deg,roll_deg,fov_deg\n" + rows)
    out, caught = record(read_telemetry_csv, path)
    assert out["a"].height_m == 50.0
    messages = [str(w.message) for w in caught]
    if warned is None:
        assert not messages
    else:
        assert len(messages) == 1 and messages[0].startswith(f"{path}: {warned}"), messages
        assert "if they are radians, convert them (degrees = radians x 57.2958)" in messages[0]
        keep = "a zoom camera that narrow (FoV of 3.14 degrees or less)" if "fov_deg" in warned else \
            "a camera held within 1.57 degrees of level all flight"  # the advice of the case, not the other's
        assert f"{keep} is degrees already: keep them" in messages[0] and messages[0].count("degrees already") == 1


@pytest.mark.parametrize("head, kind", [(b"PK\x03\x04\x14\x00\x08\x08\xff",
                                         "a zip archive (a PyTorch checkpoint is one)"),
                                        (b"\x89PNG\r\n\x1a\n\x00\xff", "a PNG image")])
def test_a_checkpoint_or_image_given_as_telemetry_says_what_it_is(tmp_path, head, kind):
    """Before: `not UTF-8 text (byte 0x.. on line 1); save it as CSV UTF-8`, for a file that is no table at all."""
    path = tmp_path / "given.ckpt"
    path.write_bytes(head + bytes(range(256)))
    with pytest.raises(TelemetryError, match=re.escape(f"{path}: {kind}, not a telemetry table; --telemetry takes a "
                                                       "CSV with the header name,height_m,pitch_deg")):
        read_telemetry_csv(path)


def test_csv_duplicates(tmp_path):
    same = write_csv(tmp_path / "same.csv", "name,height_m\na.jpg,40\na,40.0\n")
    assert_pose(read_telemetry_csv(same)["a"], [40.0, NAN, NAN, NAN])
    different = write_csv(tmp_path / "diff.csv", "name,height_m\na.jpg,40\nb.jpg,1\na,41\n")
    with pytest.raises(TelemetryError, match=r"diff.csv, line 4: `a` is already on line 2 with different values"):
        read_telemetry_csv(different)


def test_csv_header_errors(tmp_path):
    with pytest.raises(TelemetryError, match=r"nohdr.csv: no `name` column.*name,height_m,pitch_deg,roll_deg,fov_deg"):
        read_telemetry_csv(write_csv(tmp_path / "nohdr.csv", "DJI_0001.JPG,45,-90,0,70\n"))
    with pytest.raises(TelemetryError, match="';'-separated"):
        read_telemetry_csv(write_csv(tmp_path / "semi.csv", "name;height_m\na;4\n"))
    with pytest.raises(TelemetryError, match="empty.csv: the file is empty"):
        read_telemetry_csv(write_csv(tmp_path / "empty.csv", ""))
    with pytest.raises(TelemetryError, match="twice.csv, line 2: empty `name`"):
        read_telemetry_csv(write_csv(tmp_path / "twice.csv", "name,height_m\n,40\n"))
    # columns named otherwise ran every image without the telemetry asked for, exit 0 after two warnings
    with pytest.raises(TelemetryError, match=r"short.csv: none of the telemetry columns height_m, pitch_deg, roll_deg, "
                                             r"fov_deg in the header 'name,Height,pitch,roll,fov'; height: did you "
                                             r"mean height_m\?; pitch: did you mean pitch_deg\?.*the first line must"):
        read_telemetry_csv(write_csv(tmp_path / "short.csv", "name,Height,pitch,roll,fov\na,50,-40,0,80\n"))
    rows, caught = record(read_telemetry_csv, write_csv(tmp_path / "one.csv", "name,height_m,pitch\na,50,-40\n"))
    assert_pose(rows["a"], [50.0, NAN, NAN, NAN])  # one column known: the rest ignored, with the likely names
    assert [str(w.message) for w in caught] == [f"{tmp_path / 'one.csv'}: column(s) pitch ignored (the telemetry "
                                                "columns are name,height_m,pitch_deg,roll_deg,fov_deg); pitch: did "
                                                "you mean pitch_deg?"]



def test_a_csv_without_values_warns_and_a_row_longer_than_its_header_is_an_error(tmp_path):
    """A header-only CSV was accepted silently (an empty SRT warns); cells beyond the header were dropped silently."""
    for name, text, detail in (("header.csv", "name,height_m,pitch_deg,roll_deg,fov_deg\n", "no row under the header"),
                               ("names.csv", "name,height_m\na.jpg,\nb.jpg\n", "every value cell is empty")):
        rows, caught = record(read_telemetry_csv, write_csv(tmp_path / name, text))
        assert len(caught) == 1 and f"{name}: no usable telemetry in the file: {detail}" in str(caught[0].message)
    rows, caught = record(read_telemetry_csv, write_csv(tmp_path / "padded.csv", "name,height_m\na.jpg,40,,\n"))
    assert_pose(rows["a"], [40.0, NAN, NAN, NAN])  # empty cells beyond the header (a spreadsheet's): no error
    assert not caught
    with pytest.raises(TelemetryError, match=r"extra.csv, line 3: 6 cells but the header has 3 columns "
                                             r"\(name,height_m,pitch_deg\); remove the extra cells"):
        read_telemetry_csv(write_csv(tmp_path / "extra.csv", "name,height_m,pitch_deg\nb,40,-40\na,40,-40,1,2,3\n"))


# ---------------------------------------------------------------------------------- images + CSV


def test_telemetry_for_images_csv_first_metadata_per_component_and_unmatched_warning(tmp_path):
    a = write_jpeg(tmp_path / "DJI_0001.JPG", f35=24, xmp=xmp_attributes(
        RelativeAltitude="+45.20", GimbalPitchDegree="-90.0", GimbalRollDegree="0.0"))
    b = write_jpeg(tmp_path / "DJI_0002.JPG", f35=24)
    c = write_jpeg(tmp_path / "other.jpg")
    csv_path = write_csv(tmp_path / "flight.csv", "name,height_m,pitch_deg,roll_deg,fov_deg\n"
                                                  "DJI_0001,50,,,\n"        # height from CSV, rest from XMP/EXIF
                                                  "DJI_0002.JPG,,-60,2,\n"  # fov from EXIF
                                                  + "".join(f"ghost_{i}.jpg,10,,,\n" for i in range(7)))
    out, caught = record(telemetry_for_images, [a, b, c], csv_path)
    assert_pose(out[0], [50.0, -90.0, 0.0, FOV_24MM_4_3])
    assert out[0].source == "flight.csv line 2 (height); DJI_0001.JPG XMP/EXIF (pitch, roll, fov)"
    assert_pose(out[1], [NAN, -60.0, 2.0, FOV_24MM_4_3])
    assert out[2] == PoseTelemetry()
    assert len(caught) == 1
    message = str(caught[0].message)
    assert str(csv_path) in message and "7 of 9 name(s) match no image" in message
    assert "ghost_0, ghost_1, ghost_2, ghost_3, ghost_4 (and 2 more)" in message

    only_csv, caught = record(telemetry_for_images, [a, b], csv_path, read_metadata=False)
    assert_pose(only_csv[0], [50.0, NAN, NAN, NAN])
    assert_pose(only_csv[1], [NAN, -60.0, 2.0, NAN])
    assert len(caught) == 1  # the unmatched names again


def test_telemetry_for_images_without_csv_and_metadata_warnings_only_where_used(tmp_path):
    low = write_jpeg(tmp_path / "low.jpg", xmp=xmp_attributes(RelativeAltitude="0.0"))
    low2 = write_jpeg(tmp_path / "low2.jpg", xmp=xmp_attributes(RelativeAltitude="-1.0"))
    out, caught = record(telemetry_for_images, [low, low2])
    assert out == [PoseTelemetry(), PoseTelemetry()]
    assert len(caught) == 1 and "2 image(s)" in str(caught[0].message)
    csv_path = write_csv(tmp_path / "h.csv", "name,height_m\nlow,20\nlow2,25\n")
    out, caught = record(telemetry_for_images, [low, low2], csv_path)
    assert [t.height_m for t in out] == [20.0, 25.0] and not caught  # the CSV gives the heights


def test_telemetry_for_images_skips_metadata_when_the_csv_row_is_complete(tmp_path):
    csv_path = write_csv(tmp_path / "all.csv", "name,height_m,pitch_deg,roll_deg,fov_deg\ngone.jpg,40,-60,0,70\n")
    (out,) = telemetry_for_images([tmp_path / "gone.jpg"], csv_path)
    assert_pose(out, [40.0, -60.0, 0.0, 70.0])


# ------------------------------------------------------------------------------------------------ SRT

SRT_BLOCK = ("{k}\n00:00:00,{t0:03d} --> 00:00:00,{t1:03d}\n"
             '<font size="28">FrameCnt: {k}, DiffTime: 33ms\n2023-05-01 10:00:00.123\n'
             "[iso: 100] [shutter: 1/1000.0] [fnum: 2.8] [ev: 0] [focal_len: 24.00] [latitude: 22.5] "
             "[longitude: 113.9] {alt} {gb}</font>\n")


def srt_text(rows) -> str:
    return "\n".join(SRT_BLOCK.format(k=k, t0=33 * (k - 1), t1=33 * k, alt=alt, gb=gb) for k, alt, gb in rows)


def test_srt_per_frame_values(tmp_path):
    path = tmp_path / "DJI_0002.SRT"
    path.write_text(srt_text([
        (1, "[rel_alt: 45.200 abs_alt: 120.500]", "[gb_yaw: 10.0 gb_pitch: -45.0 gb_roll: 0.0]"),
        (2, "[rel_alt: 46.000 abs_alt: 121.300]", "[gb_yaw: 10.0 gb_pitch: -90.0 gb_roll: 1.5]"),
        (3, "[rel_alt: 47.5 abs_alt: 122.800]", ""),  # no gimbal fields
    ]).replace("\n", "\r\n"))
    frames, caught = record(read_srt, path, width=4000, height=3000)
    assert sorted(frames) == [0, 1, 2] and not caught
    assert_pose(frames[0], [45.2, -45.0, 0.0, FOV_24MM_4_3])
    assert_pose(frames[1], [46.0, -90.0, 1.5, FOV_24MM_4_3])
    assert_pose(frames[2], [47.5, NAN, NAN, FOV_24MM_4_3])
    assert frames[1].source == "DJI_0002.SRT subtitle 2"
    assert_pose(read_srt(path)[0], [45.2, -45.0, 0.0, NAN])  # no video size: fov unknown
    with pytest.raises(ValueError, match="both width and height"):
        read_srt(path, width=4000)


def timed_srt(path: Path, edges_ms: list[tuple[int, int]]) -> Path:
    """Per-frame subtitles 1, 2, ..., subtitle k shown from ``edges_ms[k - 1]`` (start, end in ms), height 10 + k."""
    def clock(ms: int) -> str:
        return f"{ms // 3_600_000:02d}:{ms // 60_000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"

    path.write_text("".join(f"{k}\n{clock(a)} --> {clock(b)}\n[rel_alt: {10 + k}.000 abs_alt: 300.0]\n\n"
                            for k, (a, b) in enumerate(edges_ms, 1)))
    return path


def subtitle_of_each_frame(frames: dict[int, PoseTelemetry]) -> dict[int, int]:
    """``{frame: the number of the subtitle its telemetry came from}``, read from the provenance."""
    return {f: int(t.provenance[0].split(" subtitle ")[1].split()[0]) for f, t in frames.items()}


def test_srt_per_frame_subtitles_are_placed_on_frames_by_their_timing(tmp_path):
    """At 30 fps with DJI's millisecond timings (as the Mavic 3T writes them): subtitle 4 lasts 2 frames, 5 lasts 3,
    nothing covers frames 10 and 11; each frame's centre (f + 0.5) / fps says which subtitle it shows."""
    path = timed_srt(tmp_path / "t.SRT", [(0, 33), (33, 66), (66, 99), (99, 166), (166, 266), (266, 299),
                                          (299, 333), (400, 433)])
    frames, caught = record(read_srt, path, fps=30.0)
    assert not caught
    assert subtitle_of_each_frame(frames) == {0: 1, 1: 2, 2: 3, 3: 4, 4: 4, 5: 5, 6: 5, 7: 5, 8: 6, 9: 7, 12: 8}
    assert frames[6].height_m == 15.0 and frames[6].source == "t.SRT subtitle 5"
    assert frames[6].provenance[0] == "t.SRT subtitle 5 rel_alt"
    assert subtitle_of_each_frame(read_srt(path)) == {k - 1: k for k in range(1, 9)}  # no frame rate: by number


@pytest.mark.parametrize("fps", [30.0, 30000 / 1001, 25.0])
@pytest.mark.parametrize("to_ms", [math.floor, round], ids=["truncated", "rounded"])
def test_srt_millisecond_timings_never_move_a_frame_to_its_neighbours_subtitle(tmp_path, fps, to_ms):
    """A subtitle per frame for 10 minutes, timed to the ms (33 / 34 ms at 29.97 fps): frame f shows subtitle f + 1."""
    count = int(600 * fps)
    edges = [to_ms(1000 * k / fps) for k in range(count + 1)]
    frames = read_srt(timed_srt(tmp_path / "ms.SRT", list(zip(edges, edges[1:]))), fps=fps)
    assert subtitle_of_each_frame(frames) == {f: f + 1 for f in range(count)}


def test_srt_fixed_point_format_altitude_and_ground_frames(tmp_path):
    """Air 2S style: `SrtCnt`, `focal_len: 240` (0.1 mm), `fnum: 280` (0.01), `altitude` instead of rel_alt."""
    blocks = []
    for k, alt in ((1, "0.000000"), (2, "117.000000")):
        blocks.append(f'{k}\n00:00:00,{33 * (k - 1):03d} --> 00:00:00,{33 * k:03d}\n'
                      f'<font size="36">SrtCnt : {k}, DiffTime : 33ms\n2022-08-07 13:40:40,774,808\n'
                      f'[iso : 100] [shutter : 1/80.0] [fnum : 280] [ev : 0] [ct : 5744] [color_md : default] '
                      f'[focal_len : 240] [latitude: 41.424724] [longitude: 2.234156] [altitude: {alt}] </font>\n')
    path = tmp_path / "air2s.srt"
    path.write_text("\n".join(blocks))
    frames, caught = record(read_srt, path, 3840, 2160)
    assert_pose(frames[0], [NAN, NAN, NAN, horizontal_fov_from_focal_35mm(24.0, 3840, 2160)])
    assert_pose(frames[1], [117.0, NAN, NAN, horizontal_fov_from_focal_35mm(24.0, 3840, 2160)])
    assert len(caught) == 1
    message = str(caught[0].message)
    assert "air2s.srt" in message and "1 subtitle(s) with a height <= 0" in message and "`altitude`" in message


def test_srt_integer_focal_without_integer_fnum_is_unknown(tmp_path):
    path = tmp_path / "x.srt"
    path.write_text("1\n00:00:00,000 --> 00:00:00,033\n[focal_len: 24] [rel_alt: 10.0 abs_alt: 50]\n")
    frames, caught = record(read_srt, path, 4000, 3000)
    assert_pose(frames[0], [10.0, NAN, NAN, NAN])
    assert len(caught) == 1 and "focal_len" in str(caught[0].message)


@pytest.mark.parametrize(("gb", "match"), [
    ("[gb_yaw: 1 gb_pitch: -4x5.0 gb_roll: 0.0]", r"subtitle 2 \(line \d+\): `gb_pitch` = '-4x5.0' is not a number"),
    ("[gb_yaw: 1 gb_pitch: -45 gb_roll: 270]", r"subtitle 2 \(line \d+\): `gb_roll` = 270 must be within"),
])
def test_srt_malformed_numbers_are_errors_naming_file_and_subtitle(tmp_path, gb, match):
    path = tmp_path / "bad.SRT"
    path.write_text(srt_text([(1, "[rel_alt: 45.2 abs_alt: 1]", ""), (2, "[rel_alt: 45.2 abs_alt: 1]", gb)]))
    with pytest.raises(TelemetryError, match=match) as info:
        read_srt(path)
    assert "bad.SRT" in str(info.value)


def test_srt_structure_errors(tmp_path):
    path = tmp_path / "dup.srt"
    path.write_text(srt_text([(1, "[rel_alt: 4]", ""), (1, "[rel_alt: 5]", "")]))
    with pytest.raises(TelemetryError, match="dup.srt, subtitle 1.*appears twice"):
        read_srt(path)
    path = tmp_path / "notiming.srt"
    path.write_text("1\n[rel_alt: 4]\n")
    with pytest.raises(TelemetryError, match="notiming.srt, subtitle 1.*timing line"):
        read_srt(path)
    path = tmp_path / "text.srt"
    path.write_text("hello\nworld\n")
    with pytest.raises(TelemetryError, match="text.srt, line 1: expected a subtitle number"):
        read_srt(path)
    path = tmp_path / "per_second.srt"  # Matrice-300 style timing, one subtitle per second
    path.write_text("1\n00:00:00,000 --> 00:00:01,000\n[rel_alt: 45.0 abs_alt: 80]\n")
    with pytest.raises(TelemetryError, match="per_second.srt, subtitle 1.*lasts 1.000 s"):
        read_srt(path)
    path = tmp_path / "m300.srt"  # no field read here: harmless, all unknown
    path.write_text("1\n00:00:00,000 --> 00:00:01,000\n2022.06.21 16:06:17\nGPS(36.6146,-6.1120,0.0M) "
                    "BAROMETER:0.3M\n")
    assert read_srt(path) == {0: PoseTelemetry()}


# ----------------------------------------------------------------------------- SRT tokenizer and table


@pytest.mark.parametrize(("text", "pairs"), [
    ('<font size="28">FrameCnt: 1, DiffTime: 33ms\n2024-04-23 14:04:07.002\n[iso: 110] [fnum: 2.8] '
     "[focal_len: 24.00] [rel_alt: 54.821 abs_alt: 535.407]</font>",
     [("framecnt", "1,"), ("difftime", "33ms"), ("iso", "110"), ("fnum", "2.8"), ("focal_len", "24.00"),
      ("rel_alt", "54.821"), ("abs_alt", "535.407")]),
    ("[gb_yaw: -8.6 gb_pitch: -86.7 gb_roll: 0.0]", [("gb_yaw", "-8.6"), ("gb_pitch", "-86.7"), ("gb_roll", "0.0")]),
    ("[fnum : 280] [focal_len : 240] [Altitude: 117.000000]",
     [("fnum", "280"), ("focal_len", "240"), ("altitude", "117.000000")]),
    ("GPS(149.0251,-20.2533,16) BAROMETER:1.9", [("barometer", "1.9"), ("GPS", "(149.0251,-20.2533,16)")]),
    ("F/2.8, SS 30.15, ISO 260, EV -1.7, GPS (-121.7458, 48.0771, 17), D 221.21m, H 200.70m, H.S n/a",
     [("SS", "30.15"), ("ISO", "260"), ("EV", "-1.7"), ("GPS", "(-121.7458, 48.0771, 17)"), ("D", "221.21m"),
      ("H", "200.70m")]),
    ("2022.06.21 16:06:17", []),
    ("ISO:100 Shutter:60 EV: Fnum:2.2", [("iso", "100"), ("shutter", "60"), ("ev", ""), ("fnum", "2.2")]),  # Mavic Pro
    ("[rel_alt:  abs_alt: 327.0] [gb_roll: ]", [("rel_alt", ""), ("abs_alt", "327.0"), ("gb_roll", "")]),
])
def test_srt_tokenizer_gives_field_name_and_value_text_pairs(text, pairs):
    assert srt.srt_field_pairs(text) == pairs


def test_srt_fields_keep_each_names_first_value_and_labels_apart_from_names():
    assert srt.srt_fields("[rel_alt: 5.0] [REL_ALT: 6.0] H 7m [h: 8]") == {"rel_alt": "5.0", "h": "8", "H": "7m"}
    assert srt.srt_fields("ISO:100 EV: Fnum:2.2") == {"iso": "100", "fnum": "2.2"}  # an empty field is left out


def test_srt_an_empty_field_is_unknown_and_the_next_field_is_read_as_itself(tmp_path):
    path = one_subtitle(tmp_path / "empty.srt", "[rel_alt:  abs_alt: 327.0] [gb_yaw: 1.0 gb_pitch: -30.0 gb_roll: ]")
    frames, caught = record(read_srt, path)
    assert_pose(frames[0], [NAN, -30.0, NAN, NAN])
    assert not caught


SRT_ROW_VALUES = {"height": ("12.5", 12.5), "pitch": ("-30.5", -30.5), "roll": ("2.5", 2.5),
                  "fov": ("24.00", FOV_24MM_4_3)}


def one_subtitle(path: Path, text: str) -> Path:
    path.write_text(f"1\n00:00:00,000 --> 00:00:00,033\n{text}\n")
    return path


def test_srt_table_names_the_fields_read():
    assert [(row.name, row.key) for row in srt.SRT_FIELDS] == [
        ("rel_alt", "height"), ("altitude", "height"), ("gb_pitch", "pitch"), ("gb_roll", "roll"), ("focal_len", "fov")]


@pytest.mark.parametrize("row", srt.SRT_FIELDS, ids=lambda row: row.name)
def test_srt_each_table_row_gives_its_component_and_only_it(tmp_path, row):
    text, value = SRT_ROW_VALUES[row.key]
    frames, _ = record(read_srt, one_subtitle(tmp_path / "one.srt", f"[{row.name}: {text}]"), 4000, 3000)
    expected = [value if key == row.key else NAN for key in POSE_KEYS]
    assert_pose(frames[0], expected)
    assert frames[0].source == "one.srt subtitle 1"


def test_srt_a_component_comes_from_its_first_row_that_is_there(tmp_path):
    frames, caught = record(read_srt, one_subtitle(tmp_path / "both.srt", "[altitude: 300.0] [rel_alt: 5.0]"))
    assert_pose(frames[0], [5.0, NAN, NAN, NAN])
    assert not caught  # rel_alt's row comes first: altitude is not read, no `altitude` note
    frames, caught = record(read_srt, one_subtitle(tmp_path / "low.srt", "[rel_alt: -1.0] [altitude: 300.0]"))
    assert_pose(frames[0], [NAN, NAN, NAN, NAN])  # rel_alt gave the height (unknown: on the ground)
    assert len(caught) == 1 and "height <= 0" in str(caught[0].message) and "`altitude`" not in str(caught[0].message)


def test_srt_table_drives_the_reading(tmp_path, monkeypatch):
    """A new DJI variant is one row: here the caption label `H 45.60m`, and the rows without `rel_alt`."""
    def metres(subtitle, name, key):
        return float(subtitle.fields[name].removesuffix("m"))

    path = one_subtitle(tmp_path / "caption.srt", "F/2.8, ISO 100, D 22.10m, H 45.60m [rel_alt: 40.0] [gb_roll: 1.0]")
    assert_pose(read_srt(path)[0], [40.0, NAN, 1.0, NAN])
    rows = [row for row in srt.SRT_FIELDS if row.name != "rel_alt"]
    monkeypatch.setattr(srt, "SRT_FIELDS", (srt.SrtField("H", "height", metres), *rows))
    frames, caught = record(read_srt, path)
    assert_pose(frames[0], [45.6, NAN, 1.0, NAN])
    assert not caught
    monkeypatch.setattr(srt, "SRT_FIELDS", ())
    monkeypatch.setattr(srt, "SRT_CAPTION_FIELDS", ())  # else `H` alone makes it a caption cut short
    assert read_srt(path) == {0: PoseTelemetry()}
