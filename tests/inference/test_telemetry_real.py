"""The real DJI files in ../shared/real_telemetry (not part of the project), against a table of expected values.

Skipped where the folder is not there. Every SRT is read as a 3840 x 2160 video at 30 frames/s (the Avata 360's as
a 3840 x 1920 equirectangular one); every XMP packet inside a JPEG written here. PROVENANCE.md names each file's
drone; docs/conventions.md ("What each DJI field means") the reasons for each value.
"""

from __future__ import annotations

import math
import os
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dapm_lightning.inference.telemetry import (
    TelemetryWarning,
    horizontal_fov_from_focal_35mm,
    read_srt,
    telemetry_from_image,
)

REPO = Path(__file__).resolve().parents[2]
PLACES = (Path(os.environ.get("DAPM_REAL_TELEMETRY", REPO / "missing")),
          *(up / "shared" / "real_telemetry" for up in REPO.parents[:2]))
REAL = next((p for p in PLACES if p.is_dir()), REPO / "missing")
pytestmark = pytest.mark.skipif(not REAL.is_dir(), reason="../shared/real_telemetry is not on this machine")

NAN = math.nan
UHD = (3840, 2160)
F24, F28 = horizontal_fov_from_focal_35mm(24, *UHD), horizontal_fov_from_focal_35mm(28, *UHD)

SRT_EXPECTED = {  # file: (frame, [height, pitch, roll, fov] there, the file's one warning says ... / None)
    "callmarcus__Avata360_clip.SRT": (0, [5.4, 0.0, 0.0, NAN], "360-degree"),
    "callmarcus__Mini5PRO_clip.SRT": (0, [6.0, NAN, NAN, F24], None),
    "callmarcus__air3S_clip.SRT": (0, [NAN, NAN, NAN, F24], "height <= 0"),
    "callmarcus__neo2_clip.SRT": (4, [NAN, NAN, NAN, NAN], "no usable telemetry"),  # rel_alt 0.100: on the ground
    "juanirache__MAVIC3.srt": (0, [NAN, NAN, NAN, F24], "height <= 0"),  # rel_alt -2.400
    "juanirache__air2s.srt": (0, [117.0, NAN, NAN, F24], "(`SrtCnt`)"),
    "juanirache__m2zoom.SRT": (0, [NAN, NAN, NAN, F24], "above sea level"),  # altitude 213.98: Lahore
    "juanirache__matrice_300.srt": (150, [8.4, NAN, NAN, NAN], "below 1 m"),  # BAROMETER:0.3M before take-off
    "juanirache__mavic_2_style.SRT": (None, None, "no usable telemetry"),  # no timing lines, no field read
    "juanirache__mavic_2pro_new.SRT": (0, [NAN, NAN, NAN, F28], None),  # focal_len : 280 = 28 mm
    "juanirache__mavic_air.SRT": (0, [NAN, NAN, NAN, NAN], "no usable telemetry"),
    "juanirache__mavic_air2.srt": (1, [28.6, NAN, NAN, F24], "(`SrtCnt`)"),
    "juanirache__mavic_mini.SRT": (0, [200.7, NAN, NAN, NAN], None),
    "juanirache__mavic_pro.SRT": (30, [1.9, NAN, NAN, NAN], None),  # its first subtitle starts at 1 s
    "juanirache__old_format.SRT": (30, [1.9, NAN, NAN, NAN], None),
    "juanirache__p4_rtk.SRT": (0, [85.8, -24.4, 0.0, NAN], None),
    "juanirache__p4p_sample.SRT": (0, [45.6, NAN, NAN, NAN], None),
    "ruz76__DJI.SRT": (0, [43.225, -86.7, 0.0, F24], None),
    "ruz76__DJI_M300RTK.SRT": (0, [54.821, -12.5, 0.0, horizontal_fov_from_focal_35mm(47, *UHD)], None),
    "ruz76__DJI_MAVIC.SRT": (0, [NAN, NAN, NAN, F24], "height <= 0"),  # `Drone: Pitch` is not the gimbal
    "ruz76__DJI_MAVIC_2_ZOOM.SRT": (0, [NAN, NAN, NAN, F24], "above sea level"),  # altitude 457.87
    "ruz76__DJI_MAVIC_3T.SRT": (0, [80.504, -10.7, 0.0, horizontal_fov_from_focal_35mm(643.3, *UHD)], None),
    "ruz76__DJI_MAVIC_ENTERPRISE.SRT": (0, [NAN, NAN, NAN, F24], "above sea level"),  # altitude 499.41
    "ruz76__DJI_MAVIC_ENTERPRISE_ADVANCED.SRT": (0, [4.134, NAN, NAN, horizontal_fov_from_focal_35mm(
        24 * 1.0746, *UHD)], None),  # dzoom_ratio 10746: 67.7 degrees
}

XMP_EXPECTED = {  # packet: (image size, [height, pitch, roll, fov])
    "thermal_parser__images_DJI_H20T.xmp": ((640, 512), [16.508, -10.5, 0.0, NAN]),
    "thermal_parser__images_DJI_XT2.xmp": ((640, 512), [1.9, 0.0, 0.0, NAN]),
    "thermal_parser__images_DJI_XTR.xmp": ((640, 512), [1.5, -8.3, 0.0, NAN]),
    "thermal_parser__images_DJI_XTS.xmp": ((640, 512), [37.7, 19.9, 0.0, NAN]),  # xmlns:DJI declared twice
}


def test_the_table_covers_every_real_file():
    assert {p.name for p in (REAL / "srt").iterdir()} == set(SRT_EXPECTED)
    assert {p.name for p in (REAL / "xmp").iterdir()} == set(XMP_EXPECTED)


@pytest.mark.parametrize("name", sorted(SRT_EXPECTED))
def test_every_real_srt_is_read_as_expected(name):
    frame, expected, warning = SRT_EXPECTED[name]
    size = (3840, 1920) if "360" in name else UHD
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        frames = read_srt(REAL / "srt" / name, *size, fps=30.0)
    messages = [str(w.message) for w in caught if issubclass(w.category, TelemetryWarning)]
    assert len(messages) == (warning is not None), messages
    if warning is not None:
        assert warning in messages[0] and name in messages[0]
    if frame is None:
        assert not any(any(t.known()) for t in frames.values())
        return
    np.testing.assert_allclose(frames[frame].values(), expected, atol=1e-3, equal_nan=True)


TIMING = r"\d+\r?\n\d\d:\d\d:\d\d[,.]\d+ --> "
SUBTITLE = re.compile(rf"(?:^|\n)(\d+)\r?\n\d\d:\d\d:\d\d[,.]\d+ --> [^\n]*\n(.*?)(?=\n{TIMING}|\Z)", re.S)


@pytest.mark.parametrize("name", sorted(n for n in SRT_EXPECTED  # read at collection: only when the files are here
                                        if REAL.is_dir() and "rel_alt" in (REAL / "srt" / n).read_text()))
def test_every_frame_matches_an_independent_reading_of_the_raw_text(name):
    """rel_alt, gb_pitch, gb_roll of each subtitle, found by a plain search in its raw text, are frame k - 1's (no
    frame rate given: placed by number)."""
    text = (REAL / "srt" / name).read_text(encoding="utf-8-sig")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frames = read_srt(REAL / "srt" / name, *UHD)
    blocks = SUBTITLE.findall(text)
    assert len(blocks) == len(frames) > 0
    for number, body in blocks:
        t = frames[int(number) - 1]
        height = float(re.search(r"rel_alt: (-?[\d.]+)", body).group(1))
        assert (t.height_m == height) if height >= 1 else math.isnan(t.height_m)
        for key, value in (("pitch", t.pitch_deg), ("roll", t.roll_deg)):
            found = re.search(rf"gb_{key}: (-?[\d.]+)", body)
            assert (value == float(found.group(1))) if found else math.isnan(value)


TIMED = re.compile(r"(?:^|\n)(\d+)\r?\n(\d\d):(\d\d):(\d\d)[,.](\d{3}) --> (\d\d):(\d\d):(\d\d)[,.](\d{3})")


@pytest.mark.parametrize(("name", "fps", "some"), [
    # 56 of the Mavic 2 Pro's 200 subtitles last 80 ms, two frames (subtitle 2 the first), so subtitle 200 (10.200 s)
    # is frame 255, not 199
    ("juanirache__mavic_2pro_new.SRT", 25.0, {0: 1, 1: 2, 2: 2, 3: 3, 150: 119, 199: 155, 254: 199, 255: 200}),
    ("ruz76__DJI_MAVIC_3T.SRT", 30.0, {7: 8, 8: 9, 9: 9, 10: 9, 11: 9, 12: 10, 14: 12}),  # subtitle 9: 133 ms
])
def test_real_subtitles_are_placed_on_the_frames_their_timing_covers(name, fps, some):
    """Each frame gets the subtitle whose timing, read by a plain search in the raw text, holds its centre."""
    text = (REAL / "srt" / name).read_text(encoding="utf-8-sig")
    def seconds(h: str, m: str, s: str, ms: str) -> float:
        return int(h) * 3600 + int(m) * 60 + int(s) + int(ms) / 1000

    spans = [(int(found[0]), seconds(*found[1:5]), seconds(*found[5:])) for found in TIMED.findall(text)]
    expected = {f: n for n, start, end in spans for f in range(int(end * fps) + 1) if start <= (f + 0.5) / fps < end}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        frames = read_srt(REAL / "srt" / name, *UHD, fps=fps)
    assert {f: int(t.source.rsplit(" ", 1)[1]) for f, t in frames.items()} == expected
    assert {f: expected[f] for f in some} == some and sorted(frames) == list(range(max(some) + 1))
    assert frames[max(some)].provenance[3] == f"{name} subtitle {some[max(some)]} focal_len"


@pytest.mark.parametrize("name", sorted(XMP_EXPECTED))
def test_every_real_xmp_packet_is_read_as_expected(name, tmp_path):
    size, expected = XMP_EXPECTED[name]
    image = tmp_path / name.replace(".xmp", ".jpg")
    Image.new("RGB", size).save(image, xmp=(REAL / "xmp" / name).read_bytes())
    t = telemetry_from_image(image)
    np.testing.assert_allclose(t.values(), expected, atol=1e-3, equal_nan=True)
    assert t.provenance[0].startswith(f"{image.name} XMP ") and t.provenance[0].endswith(":RelativeAltitude")
