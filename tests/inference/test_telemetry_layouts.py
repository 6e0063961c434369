"""Every real DJI layout, written here field for field (the layouts are facts; no file is copied), read by value.

The layouts are those of ../shared/real_telemetry (PROVENANCE.md names the drone of each); the values are made up.
"""

from __future__ import annotations

import math
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.inference.telemetry import (
    FIELD_MEANINGS,
    PoseTelemetry,
    TelemetryError,
    TelemetryWarning,
    horizontal_fov_from_focal_35mm,
    image_metadata,
    read_srt,
    srt,
    srt_text,
    telemetry_from_image,
)
from dapm_lightning.inference.telemetry import fields as meaning

NAN = math.nan
FOV_24_UHD = horizontal_fov_from_focal_35mm(24.0, 3840, 2160)  # 71.6: the 4:3 sensor's width
DOCS = Path(__file__).resolve().parents[2] / "docs" / "conventions.md"


def assert_pose(t: PoseTelemetry, expected) -> None:
    np.testing.assert_allclose(t.values(), np.asarray(expected, float), atol=1e-3, equal_nan=True)


def record(fn, *args, **kwargs):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = fn(*args, **kwargs)
    return out, [str(w.message) for w in caught if issubclass(w.category, TelemetryWarning)]


def timing(k: int, seconds: float) -> str:
    def clock(t: float) -> str:
        ms = round(t * 1000)
        return f"{ms // 3_600_000:02d}:{ms // 60_000 % 60:02d}:{ms // 1000 % 60:02d},{ms % 1000:03d}"

    return f"{clock((k - 1) * seconds)} --> {clock(k * seconds)}"


def write_srt(path: Path, bodies: list[str], seconds: float = 1 / 30, first: int = 1) -> Path:
    """Subtitles numbered from ``first``, each ``seconds`` long, with the given bodies."""
    path.write_text("".join(f"{first + i}\n{timing(first + i, seconds)}\n{body}\n\n" for i, body in enumerate(bodies)))
    return path


# ------------------------------------------------------------------------------ per-frame layouts


def dji_multiline(k: int, rel_alt: float, gb_pitch: float) -> str:
    """M300 RTK / DJI.SRT (ruz76): fields over several lines, then an empty line and `0` inside the subtitle."""
    return (f'<font size="28">FrameCnt: {k}, DiffTime: 33ms\n2024-04-23 14:04:07.002\n'
            "[iso: 110] [shutter: 1/200.0] [fnum: 2.8] [ev: 0] [focal_len: 24.00] [dzoom: 1.00] \n"
            f"[latitude: 49.379442] [longitude: 15.032166] [rel_alt: {rel_alt:.3f} abs_alt: 758.949] \n"
            "[drone_speedx: 0.0 drone_speedy: 0.0 drone_speedz: 0.0] \n"
            "[drone_yaw: -0.7 drone_pitch: -1.2 drone_roll: 2.7] \n"
            f"[gb_yaw: -8.6 gb_pitch: {gb_pitch} gb_roll: 0.0] \n\n0\n"
            "[ae_meter_md : 0] [dzoom_ratio: 10000, delta:0] [color_md : default] [ct : 5256] \n"
            "[af cnn:1,4,1,0,env:0,move:6,laser:267569,8,0]\n</font>")


def test_subtitles_with_an_empty_line_and_a_zero_inside_are_read(tmp_path):
    path = write_srt(tmp_path / "DJI.SRT", [dji_multiline(1, 43.225, -86.7), dji_multiline(2, 43.223, -86.5)])
    frames, caught = record(read_srt, path, 3840, 2160)
    assert sorted(frames) == [0, 1] and not caught
    assert_pose(frames[0], [43.225, -86.7, 0.0, FOV_24_UHD])  # the gimbal's pitch, not drone_pitch -1.2
    assert_pose(frames[1], [43.223, -86.5, 0.0, FOV_24_UHD])
    assert frames[1].provenance == ("DJI.SRT subtitle 2 rel_alt", "DJI.SRT subtitle 2 gb_pitch",
                                    "DJI.SRT subtitle 2 gb_roll", "DJI.SRT subtitle 2 focal_len")


def test_subtitles_need_no_empty_line_between_them(tmp_path):
    text = "".join(f"{k}\n{timing(k, 1 / 30)}\n[rel_alt: {10 + k}.0 abs_alt: 99]\n" for k in range(1, 4))
    (tmp_path / "tight.srt").write_text(text)
    frames = read_srt(tmp_path / "tight.srt")
    assert [frames[f].height_m for f in range(3)] == [11.0, 12.0, 13.0]


def mavic2(k: int, altitude: str) -> str:
    """Mavic 2 Zoom / Enterprise (DJI GO 4): fixed point, `longtitude`, `altitude` above sea level."""
    return (f'<font size="36">FrameCnt : {k}, DiffTime : 33ms\n2024-05-20 15:21:15,591,499\n'
            "[iso : 100] [shutter : 1/1250.0] [fnum : 280] [ev : 0.3] [ct : 5421] [color_md : default] "
            f"[focal_len : 240] [latitude : 49.128078] [longtitude : 14.635573] [altitude: {altitude}] </font>")


def air2s(k: int, altitude: str) -> str:
    """Air 2 / Air 2S (DJI Fly): `SrtCnt`, fixed point, `altitude` above the take-off point."""
    return (f'<font size="36">SrtCnt : {k}, DiffTime : 33ms\n2022-08-07 13:40:40,774,808\n'
            "[iso : 100] [shutter : 1/80.0] [fnum : 280] [ev : 0] [ct : 5744] [color_md : default] "
            f"[focal_len : 240] [latitude: 41.424724] [longitude: 2.234156] [altitude: {altitude}] </font>")


def test_an_altitude_above_sea_level_is_never_a_height(tmp_path):
    path = write_srt(tmp_path / "DJI_MAVIC_2_ZOOM.SRT", [mavic2(1, "457.871002"), mavic2(2, "458.000000")])
    frames, caught = record(read_srt, path, 3840, 2160)
    assert_pose(frames[0], [NAN, NAN, NAN, FOV_24_UHD])  # the FoV is still read
    assert len(caught) == 1 and "2 subtitle(s) give `altitude` in the Mavic 2 layout" in caught[0]
    assert "above sea level" in caught[0] and "--telemetry CSV" in caught[0] and "DJI_0005_f000012" in caught[0]


def test_an_altitude_in_the_air_2s_layout_is_the_height_above_take_off(tmp_path):
    frames, caught = record(read_srt, write_srt(tmp_path / "air2s.srt", [air2s(1, "117.000000")]), 3840, 2160)
    assert_pose(frames[0], [117.0, NAN, NAN, FOV_24_UHD])
    assert frames[0].provenance[0] == "air2s.srt subtitle 1 altitude"
    assert len(caught) == 1 and "Air 2 / Air 2S layout (`SrtCnt`)" in caught[0]


def test_fixed_point_focal_length_and_digital_zoom(tmp_path):
    m2ea = ('<font size="36">FrameCnt: {k}, DiffTime: 33ms\n2024-05-20 15:00:18,945,360\n'
            "[iso : 100] [shutter : 1/800.0] [fnum : 280] [ev : 0] [ct : 5867] [color_md : default] "
            "[focal_len : 240] [dzoom_ratio: {zoom}, delta:746],[latitude: 49.128048] [longtitude: 14.635630] "
            "[rel_alt: 4.134 abs_alt: 485.386] [Drone: Yaw:17.9, Pitch:-1.4, Roll:1.1] </font>")
    path = write_srt(tmp_path / "M2EA.SRT", [m2ea.format(k=1, zoom=10746), m2ea.format(k=2, zoom=10000)])
    frames = read_srt(path, 3840, 2160)
    assert frames[0].fov_deg == pytest.approx(horizontal_fov_from_focal_35mm(24.0 * 1.0746, 3840, 2160))
    assert frames[0].fov_deg == pytest.approx(67.7, abs=0.05) and frames[1].fov_deg == pytest.approx(71.6, abs=0.05)
    assert frames[0].provenance[3] == "M2EA.SRT subtitle 1 focal_len x dzoom_ratio"
    assert_pose(frames[0], [4.134, NAN, NAN, frames[0].fov_deg])  # `Drone: Pitch` is the aircraft's: not read
    mavic_2_pro = ('<font size="36">FrameCnt : 218, DiffTime : 40ms\n2019-09-27 10:28:08,438,904\n'
                   "[iso : 110] [shutter : 1/1250.0] [fnum : 280] [ev : 0] [ct : 5174] [color_md : default] "
                   "[focal_len : 280] [latitude : -35.080155] [longtitude : -60.286702] </font>")
    path = tmp_path / "m2pro.SRT"
    path.write_bytes(b"\xef\xbb\xbf" + write_srt(path, [mavic_2_pro]).read_bytes())  # with its UTF-8 BOM
    assert read_srt(path, 3840, 2160)[0].fov_deg == pytest.approx(horizontal_fov_from_focal_35mm(28, 3840, 2160))
    m3t = ('<font size="28">FrameCnt: 1, DiffTime: 33ms\n2024-05-23 17:36:01.877\n[iso: 140] [shutter: 1/239.89] '
           "[fnum: 4.4] [ev: 0] [color_md : default] [ae_meter_md: 1] [focal_len: 643.30] [dzoom_ratio: 4.00], "
           "[latitude: 50.106373] [longitude: 14.495168] [rel_alt: 80.504 abs_alt: 327.094] "
           "[gb_yaw: -107.3 gb_pitch: -10.7 gb_roll: 0.0] </font>")
    frames = read_srt(write_srt(tmp_path / "M3T.SRT", [m3t]), 3840, 2160)  # decimal: the zoom is in focal_len
    assert_pose(frames[0], [80.504, -10.7, 0.0, horizontal_fov_from_focal_35mm(643.3, 3840, 2160)])


def test_heights_on_the_ground_are_unknown_with_one_warning(tmp_path):
    neo2 = ('<font size="28">FrameCnt: {k}, DiffTime: 33ms\n2026-05-15 08:24:18.623\n[iso: 400] [shutter: 1/640.0] '
            "[fnum: 2.2] [ev: 0] [ct: 5631] [color_md: default] [ae_meter_md: 0] [latitude: 45.607181] "
            "[longitude: 13.753860] [rel_alt: {h} abs_alt: 113.900] [vsync: 1602] [eis: normal] "
            "[pp_target:0.996, -0.004, -0.053, -0.075] [pp_imu_td:0]</font>")
    path = write_srt(tmp_path / "neo2.SRT", [neo2.format(k=1, h="0.000"), neo2.format(k=2, h="0.100"),
                                             neo2.format(k=3, h="1.500")])
    frames, caught = record(read_srt, path)
    assert [f.height_m for f in frames.values()][:2] == pytest.approx([NAN, NAN], nan_ok=True)
    assert frames[2].height_m == 1.5
    assert len(caught) == 1 and "1 subtitle(s) with a height <= 0" in caught[0]
    assert "1 subtitle(s) with a height below 1 m" in caught[0]
    at_the_limit = read_srt(write_srt(tmp_path / "one.SRT", [neo2.format(k=1, h="1.000")]))
    assert at_the_limit[0].height_m == 1.0  # 1 m itself is a height: only below it is "on the ground"


def test_a_360_degree_video_gets_no_pinhole_fov(tmp_path):
    avata = ('<font size="28">FrameCnt: 1, DiffTime: 41ms, FrameId: 4787\n2026-05-27 13:10:00.015\n[iso: 200] '
             "[shutter: 1/6400.0] [fnum: 1.9] [ev: 0] [ct: 5845] [color_md: dlog_m] [ae_meter_md: 0] "
             "[focal_len: 28.00] [dzoom_ratio: 1.00], [latitude: 53.365080] [longitude: 6.460739] "
             "[rel_alt: 5.400 abs_alt: -124.744] [gb_yaw: -162.8 gb_pitch: 0.0 gb_roll: 0.0] [vsync: 0] "
             "[eis: close] [shift x: 0.00, y: 0.00] [pp_vsync:0]</font>")
    path = write_srt(tmp_path / "clip.SRT", [avata], seconds=0.041)
    frames, caught = record(read_srt, path, 3840, 1920)
    assert_pose(frames[0], [5.4, 0.0, 0.0, NAN])
    assert len(caught) == 1 and "360-degree" in caught[0]
    assert read_srt(path, 3840, 2160)[0].fov_deg == pytest.approx(horizontal_fov_from_focal_35mm(28, 3840, 2160))


def test_files_without_a_pose_field_give_one_warning_not_an_error(tmp_path):
    mavic_air = ('<font size="36">FrameCnt : 1, DiffTime : 39ms\n2018-02-19 08:04:51,265,847\n'
                 "[iso : 100] [shutter : 1/240.0] [fnum : 280] [ev : 0] [ct : 5627] </font>")
    frames, caught = record(read_srt, write_srt(tmp_path / "mavic_air.SRT", [mavic_air] * 2))
    assert frames == {0: PoseTelemetry(), 1: PoseTelemetry()}
    assert len(caught) == 1 and "mavic_air.SRT: no usable telemetry in the file" in caught[0]
    untimed = tmp_path / "mavic_2_style.SRT"  # 2017: no timing lines, no field read here
    untimed.write_text("".join(f"{k}\n2017.08.05 14:11:5{k},393,525\n[latitude : -20.2533] [longtitude : 149.0251] "
                               "[iso : 100] [shutter : 1/60.0] [ev : 0] [fnum : 220]\n\n" for k in range(1, 4)))
    frames, caught = record(read_srt, untimed)
    assert frames == {} and len(caught) == 1 and "no usable telemetry" in caught[0]
    assert "3 subtitle(s) without a timing line" in caught[0]


# ------------------------------------------------------------------------------ one subtitle per second


def p4_rtk(h: float, gimbal_pitch: float) -> str:
    return (f"F/5.6, SS 400, ISO 100, EV 0, GPS (-58.851745, -34.237922, 15), HOME (-58.847509, -34.232707, "
            f"-57.98m), D 698.70m, H {h:.2f}m, H.S 0.00m/s, V.S 0.00m/s, F.PRY (2.7°, -7.0°, 110.1°), "
            f"G.PRY ({gimbal_pitch}°, 0.0°, 110.4°)")


def test_per_second_captions_are_interpolated_onto_frames_by_their_timing(tmp_path):
    path = write_srt(tmp_path / "p4_rtk.SRT", [p4_rtk(85.80, -24.4), p4_rtk(86.80, -26.4), p4_rtk(86.00, -26.4)],
                     seconds=1.0)
    frames, caught = record(read_srt, path, 3840, 2160, fps=10.0)
    assert not caught and sorted(frames) == list(range(30))  # 3 s at 10 fps
    assert_pose(frames[0], [85.8, -24.4, 0.0, NAN])  # the gimbal (G.PRY), not the aircraft (F.PRY 2.7, -7.0)
    assert_pose(frames[2], [86.0, -24.8, 0.0, NAN])  # a fifth of the way: from subtitle 1 towards 2, not back
    assert_pose(frames[5], [86.3, -25.4, 0.0, NAN])  # half-way from subtitle 1 to 2
    assert_pose(frames[10], [86.8, -26.4, 0.0, NAN])
    assert_pose(frames[25], [86.0, -26.4, 0.0, NAN])  # the last subtitle is held to its end
    assert frames[0].provenance[:2] == ("p4_rtk.SRT subtitle 1 H", "p4_rtk.SRT subtitle 1 G.PRY")
    assert frames[5].provenance[0] == "p4_rtk.SRT subtitles 1-2 H at 0.500 s"
    with pytest.raises(ValueError, match="frame rate"):
        read_srt(path)


def test_per_second_captions_apart_in_time_are_held_not_interpolated(tmp_path):
    """Two captions interpolate only when the second starts as the first ends; across a gap (the recording paused)
    or an overlap, each holds its own value over the frames it covers."""
    edges = [(0, 1000), (1500, 2500), (2300, 3300)]  # a 0.5 s gap, then a 0.2 s overlap
    heights = (80.0, 90.0, 100.0)
    (tmp_path / "gaps.SRT").write_text("".join(
        f"{k}\n00:00:0{a // 1000},{a % 1000:03d} --> 00:00:0{b // 1000},{b % 1000:03d}\n{p4_rtk(h, -30.0)}\n\n"
        for k, ((a, b), h) in enumerate(zip(edges, heights), 1)))
    frames = read_srt(tmp_path / "gaps.SRT", fps=10.0)
    assert [frames[f].height_m for f in (0, 5, 9)] == [80.0, 80.0, 80.0]  # held to its end, across the gap
    assert 10 not in frames and 14 not in frames  # the gap: no subtitle
    assert frames[15].height_m == 90.0 and frames[19].height_m == 90.0  # not towards the overlapping third
    assert frames[9].provenance[0] == "gaps.SRT subtitle 1 H"


def test_a_caption_cut_short_at_the_end_of_a_clip_is_still_read(tmp_path):
    """The recording stopped 0.4 s into the last second: its caption lasts 0.4 s. Before, a subtitle of 0.5 s or
    less was read for per-frame fields only, and its frames were left without telemetry, with no warning."""
    (tmp_path / "cut.SRT").write_text(
        f"1\n00:00:00,000 --> 00:00:01,000\n{p4_rtk(45.6, -30.0)}\n\n"
        f"2\n00:00:01,000 --> 00:00:01,400\n{p4_rtk(47.6, -32.0)}\n\n")
    frames, caught = record(read_srt, tmp_path / "cut.SRT", fps=10.0)
    assert not caught and sorted(frames) == list(range(14))
    assert frames[10].height_m == 47.6 and frames[13].height_m == 47.6 and frames[13].pitch_deg == -32.0
    assert frames[5].height_m == pytest.approx(46.6)  # interpolated towards the short one, which starts as 1 ends


def test_srt_timings_with_fewer_fraction_digits_are_read_as_decimals(tmp_path):
    """`00:00:00,5` is half a second (the fraction is a decimal one, not milliseconds)."""
    (tmp_path / "cs.srt").write_text("".join(f"{k}\n00:00:0{k - 1},0 --> 00:00:0{k - 1},5\n[rel_alt: {10 * k}.0]\n\n"
                                             for k in (1, 2)))
    frames = read_srt(tmp_path / "cs.srt", fps=10.0)  # subtitle k from k - 1 s to k - 0.5 s: 5 frames each
    assert sorted(frames) == [0, 1, 2, 3, 4, 10, 11, 12, 13, 14]
    assert frames[4].height_m == 10.0 and frames[10].height_m == 20.0


def test_barometer_hb_and_h_captions(tmp_path):
    mavic_pro = ("HOME(149.0251,-20.2532) 2017.08.05 14:11:5{k}\nGPS(149.0251,-20.2533,16) BAROMETER:{h}\n"
                 "ISO:100 Shutter:60 EV: Fnum:2.2")
    text = "".join(f"{k}\n{timing(k + 1, 1.0)}\n{mavic_pro.format(k=k, h=h)}\n\n"
                   for k, h in ((1, "1.9"), (2, "4.8"), (3, "8.3")))  # starts at 1 s, as the Mavic Pro's does
    (tmp_path / "mavic_pro.SRT").write_text(text)
    frames = read_srt(tmp_path / "mavic_pro.SRT", fps=2.0)
    assert min(frames) == 2 and frames[2].height_m == 1.9 and frames[3].height_m == pytest.approx(3.35)
    old = "HOME(149.0251,-20.2532) 2017.8.5 14:11:51\nGPS(149.0251,-20.2533,16) Hb:{h} Hs:50.0\nISO:100 TV:60 EV: 0"
    frames = read_srt(write_srt(tmp_path / "old.SRT", [old.format(h=2.0)], seconds=1.0), fps=1.0)
    assert frames[0].height_m == 2.0 and frames[0].provenance[0] == "old.SRT subtitle 1 hb"  # Hb, never Hs
    m300 = "2022.06.21 16:06:17\nGPS(36.6146,-6.1120,0.0M) BAROMETER:{h}M"
    frames, caught = record(read_srt, write_srt(tmp_path / "m300.srt", [m300.format(h=0.3), m300.format(h=4.1)],
                                                seconds=1.0), fps=1.0)
    assert math.isnan(frames[0].height_m) and frames[1].height_m == 4.1
    assert len(caught) == 1 and "below 1 m" in caught[0]
    mini = "F/2.8, SS 30.15, ISO 260, EV -1.7, GPS (-121.7458, 48.0771, 17), D 221.21m, H {h}m, H.S n/a, V.S n/a "
    frames = read_srt(write_srt(tmp_path / "mini.SRT", [mini.format(h="200.70")], seconds=1.0), fps=1.0)
    assert_pose(frames[0], [200.7, NAN, NAN, NAN])  # H, not D


def test_per_frame_fields_in_a_per_second_subtitle_are_still_an_error(tmp_path):
    path = write_srt(tmp_path / "retimed.srt", ["[rel_alt: 45.0 abs_alt: 80]"], seconds=1.0)
    with pytest.raises(TelemetryError, match="retimed.srt, subtitle 1.*lasts 1.000 s.*timing was changed"):
        read_srt(path, fps=30)


# ------------------------------------------------------------------------------ bounded memory, encodings


def test_the_srt_is_read_as_a_stream_in_bounded_memory(tmp_path):
    path = tmp_path / "one_block.srt"
    with path.open("w") as out:
        out.write(f"1\n{timing(1, 1 / 30)}\n")
        for _ in range(20_000):  # 2 MB in one subtitle: refused at 64 KiB, without reading the rest
            out.write("[iso: 110] [shutter: 1/200.0] [fnum: 2.8] [rel_alt: 43.225 abs_alt: 758.949]\n")
    start = time.perf_counter()
    with pytest.raises(TelemetryError, match=r"one_block.srt, subtitle 1 \(line 1\): more than 65536 characters"):
        read_srt(path)
    assert time.perf_counter() - start < 1.0
    path.write_text(f"1\n{timing(1, 1 / 30)}\n" + "x" * (srt_text.MAX_SUBTITLE_CHARS + 10) + "\n")
    with pytest.raises(TelemetryError, match="line 3: longer than 65536 characters"):
        read_srt(path)


def test_an_srt_in_utf16_is_read(tmp_path):
    path = tmp_path / "u16.srt"
    path.write_text(f"1\n{timing(1, 1 / 30)}\n[rel_alt: 12.5 abs_alt: 80] [gb_pitch: -30.0]\n", encoding="utf-16")
    assert_pose(read_srt(path)[0], [12.5, -30.0, NAN, NAN])


# ------------------------------------------------------------------------------------------- XMP


def xt_s_packet(**tags: str) -> bytes:
    """Zenmuse XT S: prefix `DJI:` bound to http://www.dji.com, declared twice; the wrapper's end damaged."""
    attrs = "\n".join(f'DJI:{k}="{v}"' for k, v in tags.items())
    return ('<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
            '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n'
            '<rdf:Description rdf:about="DJI Meta Data"\nxmlns:DJI="http://www.dji.com"\nxmlns:DJI="http://www.dji.com"\n'
            f"{attrs}>\n<DJI:BandName>\n<rdf:Seq>\n<rdf:li>LWIR</rdf:li>\n</rdf:Seq>\n</DJI:BandName>\n"
            '</rdf:Description>\n</rdf:RDF></x:xmpmeta>\n<?xpacket end="w"?').encode() + b"\x00\x00"


def jpeg(path: Path, xmp: bytes, size=(640, 512)) -> Path:
    Image.new("RGB", size, (60, 60, 60)).save(path, xmp=xmp)
    return path


def test_an_xmp_namespace_declared_twice_is_read(tmp_path):
    path = jpeg(tmp_path / "DJI_XTS.jpg", xt_s_packet(
        AbsoluteAltitude="-29.44", RelativeAltitude="+37.70", GimbalRollDegree="+0.00", GimbalYawDegree="+91.30",
        GimbalPitchDegree="+19.90", FlightRollDegree="-2.90", FlightPitchDegree="-0.20"))
    t = telemetry_from_image(path)
    assert_pose(t, [37.7, 19.9, 0.0, NAN])  # relative altitude and the gimbal's angles, not the aircraft's
    assert t.provenance[:3] == ("DJI_XTS.jpg XMP DJI:RelativeAltitude", "DJI_XTS.jpg XMP DJI:GimbalPitchDegree",
                                "DJI_XTS.jpg XMP DJI:GimbalRollDegree")
    clash = xt_s_packet(RelativeAltitude="5").replace(b'xmlns:DJI="http://www.dji.com"\n',
                                                      b'xmlns:DJI="http://other.example"\n', 1)
    with pytest.raises(TelemetryError, match="not well-formed.*--no_metadata.*read_metadata=False"):
        telemetry_from_image(jpeg(tmp_path / "clash.jpg", clash))


def test_a_thermal_camera_s_packet_with_the_flir_namespace_is_read(tmp_path):
    """Zenmuse XT2 / XTR: drone-dji attributes beside FLIR ones (bound to http://www.dji.com/FLIR/1.0/) and FLIR
    elements holding rdf:Seq lists; the gimbal's angles are read, the aircraft's and the camera's FLIR values not."""
    packet = ('<?xpacket begin="\ufeff" id="W5M0MpCehiHzreSzNTczkc9d"?>\n<x:xmpmeta xmlns:x="adobe:ns:meta/">\n'
              '<rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">\n<rdf:Description rdf:about=""\n'
              'xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/"\nxmlns:FLIR="http://www.dji.com/FLIR/1.0/"\n'
              'drone-dji:AbsoluteAltitude="52.5" drone-dji:RelativeAltitude="23.400000" '
              'drone-dji:GimbalRollDegree="0.300000" drone-dji:GimbalYawDegree="12.0" '
              'drone-dji:GimbalPitchDegree="-61.200001" drone-dji:FlightRollDegree="-4.0" '
              'drone-dji:FlightPitchDegree="7.5" FLIR:CentralTemperature="34" FLIR:TlinearGain="0">\n'
              "<FLIR:BandName>\n<rdf:Seq>\n<rdf:li>LWIR</rdf:li>\n</rdf:Seq>\n</FLIR:BandName>\n"
              "<FLIR:CentralWavelength>\n<rdf:Seq>\n<rdf:li>10000</rdf:li>\n</rdf:Seq>\n</FLIR:CentralWavelength>\n"
              '</rdf:Description>\n</rdf:RDF>\n</x:xmpmeta>\n<?xpacket end="w"?>').encode()
    t = telemetry_from_image(jpeg(tmp_path / "DJI_XT2.jpg", packet))
    assert_pose(t, [23.4, -61.2, 0.3, NAN])
    assert t.provenance[1] == "DJI_XT2.jpg XMP drone-dji:GimbalPitchDegree"


DTD_PACKET = ('<?xml version="1.0" encoding="{enc}"?><!DOCTYPE x [<!ENTITY h "45.2">]>'
              '<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
              '<rdf:Description xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" drone-dji:RelativeAltitude="&h;"/>'
              "</rdf:RDF></x:xmpmeta>")


@pytest.mark.parametrize("encoding", ["utf-8", "utf-16", "utf-16-le", "utf-16-be", "utf-32", "utf-7"])
def test_xmp_dtds_and_entities_are_refused_in_any_encoding(tmp_path, encoding):
    packet = DTD_PACKET.format(enc=encoding).encode(encoding)
    with pytest.raises(TelemetryError, match=r"x.jpg: its XMP packet declares a DTD"):
        telemetry_from_image(jpeg(tmp_path / "x.jpg", packet))


def test_an_xmp_packet_in_utf16_is_read(tmp_path):
    packet = DTD_PACKET.replace('<!DOCTYPE x [<!ENTITY h "45.2">]>', "").replace("&h;", "45.2")
    for encoding in ("utf-16", "utf-16-le", "utf-32"):
        t = telemetry_from_image(jpeg(tmp_path / "u.jpg", packet.format(enc=encoding).encode(encoding)))
        assert t.height_m == 45.2


def dji_packet(**tags: str) -> bytes:
    attrs = " ".join(f'drone-dji:{k}="{v}"' for k, v in tags.items())
    return ('<x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#">'
            '<rdf:Description xmlns:drone-dji="http://www.dji.com/drone-dji/1.0/" '
            'xmlns:GPano="http://ns.google.com/photos/1.0/panorama/" '
            f"{attrs}/></rdf:RDF></x:xmpmeta>").encode()


def test_xmp_on_the_ground_upside_down_other_namespaces_and_360(tmp_path):
    t, caught = record(telemetry_from_image, jpeg(tmp_path / "g.jpg", dji_packet(RelativeAltitude="0.500000",
                                                                             GimbalPitchDegree="-8.3")))
    assert_pose(t, [NAN, -8.3, NAN, NAN]) and len(caught) == 1 and "below 1 m" in caught[0]
    t, caught = record(telemetry_from_image, jpeg(tmp_path / "rev.jpg", dji_packet(
        RelativeAltitude="20", GimbalPitchDegree="30", GimbalRollDegree="1", GimbalReverse="1")))
    assert_pose(t, [20.0, NAN, NAN, NAN]) and len(caught) == 1 and "GimbalReverse = 1" in caught[0]
    for upright in ("0", "false", "False"):  # XMP writes a Boolean as True / False
        t, caught = record(telemetry_from_image, jpeg(tmp_path / "up.jpg", dji_packet(
            GimbalPitchDegree="30", GimbalRollDegree="1", GimbalReverse=upright, CamReverse=upright)))
        assert_pose(t, [NAN, 30.0, 1.0, NAN]) and not caught, upright
    other = dji_packet(RelativeAltitude="20").replace(b"http://www.dji.com/drone-dji/1.0/", b"http://example.org/")
    assert telemetry_from_image(jpeg(tmp_path / "other.jpg", other)) == PoseTelemetry()
    sphere = tmp_path / "pano.jpg"
    Image.new("RGB", (400, 200)).save(sphere, xmp=dji_packet(RelativeAltitude="30"), exif=exif_f35(24))
    t, caught = record(telemetry_from_image, sphere)
    assert_pose(t, [30.0, NAN, NAN, NAN]) and len(caught) == 1 and "360-degree" in caught[0]
    flat = tmp_path / "flat.jpg"
    Image.new("RGB", (400, 300)).save(flat, xmp=dji_packet(GPano_ProjectionType="x").replace(
        b'drone-dji:GPano_ProjectionType="x"', b'GPano:ProjectionType="equirectangular"'), exif=exif_f35(24))
    assert math.isnan(telemetry_from_image(flat).fov_deg)


def exif_f35(f35: int) -> Image.Exif:
    from PIL import ExifTags

    exif = Image.Exif()
    exif.get_ifd(ExifTags.IFD.Exif)[ExifTags.Base.FocalLengthIn35mmFilm] = f35
    return exif


# ------------------------------------------------------------------------------ the meaning table


def test_every_field_read_has_that_meaning_in_the_table():
    rows = [(row.name, row.key, "SRT") for row in srt.SRT_FIELDS]
    rows += [(row.name, row.key, "SRT caption") for row in srt.SRT_CAPTION_FIELDS]
    rows += [(f"drone-dji:{tag}", key, "XMP") for tag, key in image_metadata.XMP_POSE_TAGS.items()]
    for name, key, file in rows:
        label = {"barometer": "BAROMETER", "hb": "Hb"}.get(name, name)
        found = meaning.meanings(label, file)
        assert found, f"{label} ({file}) is read but not in FIELD_MEANINGS"
        assert any(key in m.component.split(", ") for m in found), f"{label} read as {key}, which it does not give"
    for m in FIELD_MEANINGS:  # what is above sea level or the aircraft's gives no pose component
        if m.reference in ("sea level", "aircraft"):
            assert m.component == "", m
        assert m.component == "" or set(m.component.split(", ")) <= set(POSE_KEYS), m


def test_the_conventions_show_every_field_of_the_table():
    text = DOCS.read_text()
    for m in FIELD_MEANINGS:
        assert f"`{m.name}`" in text or f"`{m.name.split(':')[-1]}`" in text, m.name
