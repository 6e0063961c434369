import json
import math
import struct
import warnings

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from dapm_lightning.geometry import depth_to_points, ideal_ground_depth, intrinsics_matrix
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.inference.inputs import (
    ImageFilesDataset,
    VideoFramesDataset,
    network_size,
    resolve_source,
    to_rgb8,
)
from dapm_lightning.inference.postprocess import make_prediction
from dapm_lightning.inference.predictor import DAPMPredictor
from dapm_lightning.inference.writers import DEPTH16_SCALE, OUTPUT_KINDS, PredictionWriter, write_prediction
from dapm_lightning.models import DAPMConfig, InferenceOutput
from dapm_lightning.training.lightning_cli import run_lightning_cli
from dapm_lightning.training.module import DAPMModule
from tests.conftest import CONFIGS

TINY = {"backbone": "resnet18", "decoder_channels": 16, "head_channels": 8, "igd_channels": 4, "pose_hidden": 16,
        "depth_bins": (2, 4), "pose_bins": (4,)}


def read_ply_independently(path):
    """A PLY reader written from the format's specification, independent of dapm_lightning.inference.ply."""
    data = path.read_bytes()
    header, _, body = data.partition(b"end_header\n")
    lines = header.decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    count = next(int(line.split()[2]) for line in lines if line.startswith("element vertex"))
    kinds = {"float": "<f4", "uchar": "u1", "double": "<f8"}
    props = [(line.split()[2], kinds[line.split()[1]]) for line in lines if line.startswith("property")]
    table = np.frombuffer(body, dtype=props, count=count)
    assert len(body) == table.nbytes  # nothing left over: the header tells the whole layout
    return table


@pytest.fixture()
def image_folder(tmp_path):
    folder = tmp_path / "images"
    folder.mkdir()
    rng = np.random.default_rng(0)
    cv2.imwrite(str(folder / "colour.jpg"), rng.integers(0, 255, (45, 70, 3), np.uint8))
    cv2.imwrite(str(folder / "grey.png"), rng.integers(0, 255, (30, 30), np.uint8))
    cv2.imwrite(str(folder / "rgba16.png"), rng.integers(0, 65535, (40, 52, 4), np.uint16))
    return folder


def write_video(path, frames=9, size=(36, 48)):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (size[1], size[0]))
    for k in range(frames):
        frame = np.full((*size, 3), 20 * k, np.uint8)
        frame[:, : 4 + 4 * k] = 255
        writer.write(frame)
    writer.release()
    return path


def test_any_input_kind_is_handled_or_refused(image_folder):
    ds = ImageFilesDataset(resolve_source(image_folder)[1], 64)
    for i in range(len(ds)):
        item = ds[i]
        assert item.image.dtype == torch.uint8 and item.image.shape[0] == 3
        height, width = item.size
        assert item.image.shape[2] == 64 and item.image.shape[1] == max(32, round(height * 64 / width))
    with pytest.raises(ValueError, match="float32"):
        to_rgb8(np.zeros((4, 4), np.float32), "x.tif")
    with pytest.raises(ValueError, match="channels"):
        to_rgb8(np.zeros((4, 4, 5), np.uint8), "x.tif")
    assert network_size(480, 640, 512) == (384, 512)
    assert network_size(480, 640, 512, multiple=32) == (384, 512) and network_size(45, 70, 64, 32) == (32, 64)


def test_sources_folder_glob_image_video_and_mistakes(image_folder, tmp_path):
    assert [p.name for p in resolve_source(image_folder)[1]] == ["colour.jpg", "grey.png", "rgba16.png"]
    assert [p.name for p in resolve_source(f"{image_folder}/*.png")[1]] == ["grey.png", "rgba16.png"]
    (image_folder / "sub").mkdir()
    cv2.imwrite(str(image_folder / "sub" / "deep.png"), np.zeros((8, 8), np.uint8))
    assert "deep.png" in [p.name for p in resolve_source(f"{image_folder}/**/*.png")[1]]
    assert resolve_source(image_folder / "grey.png") == ("images", [image_folder / "grey.png"])
    video = write_video(tmp_path / "v.avi")
    assert resolve_source(video) == ("video", [video])
    with pytest.raises(FileNotFoundError, match="no such file or folder.*glob pattern"):
        resolve_source(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="matches no image or video"):
        resolve_source(f"{tmp_path}/*.jpg")
    (tmp_path / "notes.md").write_text("x")
    with pytest.raises(ValueError, match="neither an image"):
        resolve_source(tmp_path / "notes.md")
    (tmp_path / "damaged.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="damaged.png: cannot be decoded"):
        ImageFilesDataset([tmp_path / "damaged.png"])[0]
    (tmp_path / "broken.mp4").write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match="broken.mp4: OpenCV cannot open it"):
        VideoFramesDataset(tmp_path / "broken.mp4")


def test_video_frames_in_order_with_step_limit_and_workers(tmp_path):
    video = write_video(tmp_path / "flight.avi", frames=9)
    frames = list(VideoFramesDataset(video, 32, frame_step=2, max_frames=4))
    assert [f.name for f in frames] == ["flight_f000000", "flight_f000002", "flight_f000004", "flight_f000006"]
    assert frames[0].size == (36, 48) and frames[0].prior.isnan().all()
    assert VideoFramesDataset(video, 32, frame_step=2, max_frames=4).expected_frames() == 4  # the progress bar's
    assert VideoFramesDataset(video, 32, frame_step=2).expected_frames() == 5
    # 2 workers, chunks of the batch size: the loader gives the frames back in video order
    loader = torch.utils.data.DataLoader(VideoFramesDataset(video, 32, chunk=2), batch_size=2, num_workers=2,
                                         collate_fn=lambda items: [i.name for i in items])
    assert [n for batch in loader for n in batch] == [f"flight_f{k:06d}" for k in range(9)]


def write_variable_rate_video(path, durations, size=(36, 48)):
    """An mp4 whose frames last ``durations`` (units of 1/10240 s; OpenCV writes 1024 a frame at 10 fps).

    Its time-to-sample table (``moov/trak/mdia/minf/stbl/stts``, after the frames) is rewritten and the boxes
    around it resized.
    """
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (size[1], size[0]))
    for k in range(len(durations)):
        writer.write(np.full((*size, 3), 20 * k, np.uint8))
    writer.release()
    data = bytearray(path.read_bytes())
    boxes, start, end = [], 0, len(data)
    for name in (b"moov", b"trak", b"mdia", b"minf", b"stbl", b"stts"):
        while struct.unpack(">4s", data[start + 4:start + 8])[0] != name:
            start += struct.unpack(">I", data[start:start + 4])[0]
            assert start < end, name
        boxes.append(start)
        start, end = start + 8, start + struct.unpack(">I", data[start:start + 4])[0]
    stts = boxes[-1]
    assert struct.unpack(">II", data[stts + 12:stts + 20]) == (1, len(durations))  # one run of equal frames
    table = struct.pack(">I", len(durations)) + b"".join(struct.pack(">II", 1, d) for d in durations)
    grow = len(table) - 12
    data[stts + 12:stts + 24] = table
    for box in boxes:
        data[box:box + 4] = struct.pack(">I", struct.unpack(">I", data[box:box + 4])[0] + grow)
    path.write_bytes(bytes(data))
    return path


def test_video_frames_of_a_variable_frame_rate_get_their_own_times(tmp_path):
    """A phone's video is recorded at a variable frame rate: each frame's time is its own timestamp (before: frame
    number / average rate, 0.3 s for a frame shown at 0.5 s)."""
    video = write_variable_rate_video(tmp_path / "phone.mp4", [1024, 1024, 3072, 512, 512, 512, 512, 1024])
    dataset = VideoFramesDataset(video, 32)
    assert dataset.fps == pytest.approx(10.0)  # the average: 8 frames in 0.8 s
    times = [0.0, 0.1, 0.2, 0.5, 0.55, 0.6, 0.65, 0.7]
    assert [f.time_s for f in dataset] == pytest.approx(times, abs=1e-3)
    assert [f.time_s for f in VideoFramesDataset(video, 32, frame_step=3)] == pytest.approx(times[::3], abs=1e-3)
    steady = [f.time_s for f in VideoFramesDataset(write_video(tmp_path / "steady.avi"), 32)]
    assert steady == pytest.approx([k / 10 for k in range(9)])  # a constant rate as before


def test_a_video_cut_short_is_predicted_as_far_as_it_goes_with_a_warning(tmp_path):
    """An AVI cut in half: its header still announces every frame; the frames read are predicted, with one warning
    naming the video and the frames read of those announced. A count off by a frame or two (containers whose count
    OpenCV estimates) is no warning."""
    whole = tmp_path / "whole.avi"
    writer = cv2.VideoWriter(str(whole), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (48, 36))
    rng = np.random.default_rng(0)
    for _ in range(30):  # noise: frames of some size, so that half the file is half the frames
        writer.write(rng.integers(0, 255, (36, 48, 3), np.uint8))
    writer.release()
    data = whole.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[:len(data) // 2])
    dataset = VideoFramesDataset(cut, 32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        frames = list(dataset)
    if not 0 < len(frames) < dataset.frame_count - 2:
        pytest.skip(f"this OpenCV reads {len(frames)} frames of the cut AVI and announces {dataset.frame_count}")
    messages = [str(w.message) for w in caught]
    assert messages == [f"{cut}: the video ends after {len(frames)} of the {dataset.frame_count} frames its header "
                        "announces (cut short while copying?): the frames after it are not predicted. Fix: copy the "
                        "file again."]
    for announced, warned in ((30, False), (31, False), (32, False), (33, True)):  # a whole video, a count off by...
        dataset = VideoFramesDataset(whole, 32, frame_step=3)
        dataset.frame_count = announced
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert len(list(dataset)) == 10
        assert bool(caught) == warned, (announced, [str(w.message) for w in caught])
    dataset = VideoFramesDataset(cut, 32, max_frames=4)  # stopped by max_frames before the cut: nothing to say
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert len(list(dataset)) == 4 and not caught


def test_cli_predict_writes_every_output(checkpoint, image_folder, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # LightningCLI saves its config.yaml into the working directory when logger: false
    out = tmp_path / "pred"
    cli = run_lightning_cli(["predict", "--config", str(CONFIGS / "predict.yaml"), "--ckpt_path", str(checkpoint),
                             "--data.init_args.source", str(image_folder), "--data.init_args.image_width", "64",
                             "--data.init_args.batch_size", "4", "--data.init_args.num_workers", "0",
                             "--trainer.callbacks.output_dir", str(out), "--trainer.callbacks.points_stride", "3",
                             "--trainer.callbacks.outputs", "all"])
    assert cli.trainer.predict_loop.predictions == []  # return_predictions off: nothing kept in memory
    poses = json.loads((out / "poses.json").read_text())
    assert [p["name"] for p in poses] == ["colour", "grey", "rgba16"]
    assert set(poses[0]) == {"name", "height_m", "pitch_deg", "roll_deg", "fov_deg"}
    assert (out / "poses.csv").read_text().splitlines()[0] == "name,height_m,pitch_deg,roll_deg,fov_deg"
    for (name, shape), row in zip((("colour", (45, 70)), ("grey", (30, 30)), ("rgba16", (40, 52))), poses):
        depth = np.load(out / f"{name}_depth.npy")
        assert depth.shape == shape and depth.dtype == np.float32 and (depth > 0).all() and (depth <= 1000).all()
        tiff = Image.open(out / f"{name}_depth.tif")  # a standard reader: 32-bit float TIFF ("F" mode)
        assert tiff.mode == "F"
        np.testing.assert_array_equal(np.asarray(tiff), depth)
        depth16 = cv2.imread(str(out / f"{name}_depth16.png"), cv2.IMREAD_UNCHANGED)
        assert depth16.dtype == np.uint16
        np.testing.assert_allclose(depth16 / DEPTH16_SCALE, depth, atol=0.5 / DEPTH16_SCALE + 1e-4)
        assert cv2.imread(str(out / f"{name}_depth_color.png")).shape == (*shape, 3)
        sky = cv2.imread(str(out / f"{name}_sky.png"), cv2.IMREAD_UNCHANGED)
        assert sky.shape == shape and sky.dtype == np.uint8
        camera = json.loads((out / f"{name}_camera.json").read_text())
        assert (camera["height"], camera["width"]) == shape
        fov = camera["pose"]["fov_deg"]["value"]
        assert camera["pose"]["fov_deg"] == {"value": pytest.approx(row["fov_deg"], abs=1e-3), "source": "network",
                                             "network": fov}
        k = np.array(camera["K"])
        assert k[0, 0] == pytest.approx(shape[1] / (2 * math.tan(math.radians(fov) / 2)))
        assert (k[0, 2], k[1, 2]) == (shape[1] / 2, shape[0] / 2)
        # the point cloud is the written depth lifted with the written pose, every 3rd pixel, coloured
        ply = read_ply_independently(out / f"{name}_points.ply")
        pose = torch.tensor([[camera["pose"][k]["value"] for k in ("height_m", "pitch_deg", "roll_deg", "fov_deg")]],
                            dtype=torch.float64)
        expected = depth_to_points(torch.from_numpy(depth).double()[None], pose)[0, ::3, ::3]
        seen = depth[::3, ::3] < 1000
        xyz = np.stack([ply["x"], ply["y"], ply["z"]], 1)
        np.testing.assert_allclose(xyz, expected[torch.from_numpy(seen)].numpy(), atol=2e-3, rtol=1e-5)
        assert ply["red"].dtype == np.uint8 and len(ply) == seen.sum()


def test_flat_ground_through_the_writer_lies_at_z_zero(tmp_path):
    """True pose and true IGD depth in: the written PLY's ground points sit at z = 0 (1e-3 of the range)."""
    for pose in ([50.0, -90.0, 0.0, 60.0], [35.0, -30.0, 14.0, 95.0], [80.0, -10.0, -20.0, 110.0]):
        pose_t = torch.tensor(pose)
        for depth_kind in ("range", "planar"):
            depth = ideal_ground_depth(pose_t[None], (30, 44), depth_kind=depth_kind)[0]
            prediction = make_prediction("flat", (30, 44), depth, None, pose_t, IGDSpec(depth_kind=depth_kind))
            write_prediction(tmp_path, prediction, outputs=["points", "camera"], points_stride=1)
            ply = read_ply_independently(tmp_path / "flat_points.ply")
            xyz = np.stack([ply["x"], ply["y"], ply["z"]], 1).astype(np.float64)
            distance = np.linalg.norm(xyz - [0.0, 0.0, pose[0]], axis=1)
            assert len(xyz) == (depth < 1000).sum() > 100
            assert (np.abs(xyz[:, 2]) <= 1e-3 * distance).all(), (pose, depth_kind, np.abs(xyz[:, 2]).max())
            camera = json.loads((tmp_path / "flat_camera.json").read_text())
            np.testing.assert_allclose(camera["K"], intrinsics_matrix(pose_t[3:].double(), (30, 44))[0].numpy())
            assert camera["camera_to_world"][2][3] == pytest.approx(pose[0])


def test_python_api_images_batches_and_tensors(checkpoint):
    predictor = DAPMPredictor.from_checkpoint(checkpoint, image_width=64, batch_size=2)
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 255, (50, 80, 3), np.uint8)
    a = predictor(rgb)
    b = predictor(Image.fromarray(rgb))
    assert a.depth_m.shape == (50, 80) and a.sky.shape == (50, 80) and a.sky_prob.shape == (50, 80)
    np.testing.assert_array_equal(a.depth_m, b.depth_m)
    assert set(a.pose) == {"height", "pitch", "roll", "fov"} and a.K.shape == (3, 3)
    # channel order: an RGB array is not read as BGR (swapping R and B changes the input)
    assert not np.array_equal(predictor(rgb[..., ::-1].copy()).depth_m, a.depth_m)
    others = [rng.integers(0, 255, (50, 80, 3), np.uint8) for _ in range(2)]
    batch = predictor([rgb, *others, rng.integers(0, 255, (30, 30, 3), np.uint8)])  # two sizes: two batches
    assert [r.depth_m.shape for r in batch] == [(50, 80)] * 3 + [(30, 30)]
    np.testing.assert_allclose(batch[0].depth_m, a.depth_m, rtol=1e-4, atol=1e-3)  # batched = one by one
    stacked = predictor(np.stack([rgb, *others]))
    tensor = predictor(torch.from_numpy(np.stack([rgb, *others])).permute(0, 3, 1, 2))
    floats = predictor(torch.from_numpy(rgb).permute(2, 0, 1).float() / 255)
    for r, s, t in zip(batch, stacked, tensor):
        np.testing.assert_allclose(s.depth_m, r.depth_m, rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(t.depth_m, r.depth_m, rtol=0.05)  # tensors are resized by torch, not OpenCV
    assert floats.depth_m.shape == (50, 80)
    with pytest.raises(ValueError, match=r"image 0: a float tensor must hold RGB in \[0, 1\], got values from 0 to "
                                         r"25\d; divide 0-255 values by 255"):  # the division forgotten
        predictor(torch.from_numpy(rgb).permute(2, 0, 1).float())
    with pytest.raises(ValueError, match="a tensor must be uint8 .0-255. or float RGB in .0, 1., got torch.int64"):
        predictor(torch.from_numpy(rgb).permute(2, 0, 1).long())
    bf16 = DAPMPredictor(predictor.module, image_width=64, precision="bf16")(rgb)
    assert bf16.depth_m.dtype == np.float32 and np.isfinite(bf16.depth_m).all()
    points = a.points(stride=2, rgb=rgb)
    assert points.xyz.shape[1] == 3 and points.rgb.shape == points.xyz.shape
    with pytest.raises(ValueError, match="precision"):
        DAPMPredictor(predictor.module, precision="8")
    with pytest.raises(FileNotFoundError, match="missing.ckpt"):
        DAPMPredictor.from_checkpoint("missing.ckpt")


def test_python_api_pil_images_of_palette_cmyk_and_1_bit_are_read_as_their_colours():
    """A PIL palette image's array holds palette indices, a CMYK one's inks: they were read as grey values and as
    RGB + alpha (a wrong picture, silently; a 1-bit one was refused as 'bool'). Now as their RGB colours, as the
    same file given by its path is."""
    torch.manual_seed(0)
    predictor = DAPMPredictor(DAPMModule(net=DAPMConfig(**TINY)), image_width=32)
    rgb = np.random.default_rng(2).integers(0, 255, (30, 40, 3), np.uint8)
    for mode in ("P", "CMYK", "1"):
        image = Image.fromarray(rgb).convert(mode)
        expected = predictor(np.asarray(image.convert("RGB")))
        got = predictor(image)
        np.testing.assert_array_equal(got.depth_m, expected.depth_m, err_msg=mode)
        assert got.pose == expected.pose, mode


def test_python_api_video_and_single_branch_models(tmp_path):
    video = write_video(tmp_path / "v.avi", frames=5)
    torch.manual_seed(0)
    depth_only = DAPMPredictor(DAPMModule(net=DAPMConfig(**TINY, use_pose=False, use_igd_feature=False)),
                               image_width=32, batch_size=2)
    results = list(depth_only.predict_source(video, keep_rgb=True))
    assert [r.name for r in results] == [f"v_f{k:06d}" for k in range(5)]
    r = results[0]
    assert r.depth_m.shape == (36, 48) and r.pose is None and r.K is None and r.rgb.shape == (36, 48, 3)
    with pytest.raises(ValueError, match="needs depth and pose"):
        r.points()
    assert {p.name for p in write_prediction(tmp_path, r)} == {f"{r.name}_{s}" for s in ("depth_color.png",
                                                                                         "sky.png")}  # default
    written = write_prediction(tmp_path, r, OUTPUT_KINDS)
    assert {p.name for p in written} == {f"{r.name}_{s}" for s in ("depth.npy", "depth.tif", "depth16.png",
                                                                    "depth_color.png", "sky.png")} | {f"{r.name}.npz"}
    pose_only = DAPMPredictor(DAPMModule(net=DAPMConfig(**TINY, use_depth=False, use_igd_feature=False)),
                              image_width=32)
    p = pose_only(np.zeros((36, 48, 3), np.uint8))
    assert p.depth_m is None and p.K.shape == (3, 3)
    p.name = "pose_only"
    assert {q.name for q in write_prediction(tmp_path, p)} == {"pose_only_camera.json"}
    with pytest.raises(ValueError, match="unknown output"):
        PredictionWriter(outputs=["depth_npy", "mesh"])


def test_cli_predict_honours_precision_and_a_video_source(checkpoint, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    video = write_video(tmp_path / "clip.avi", frames=6)
    out = tmp_path / "pred"
    run_lightning_cli(["predict", "--config", str(CONFIGS / "predict.yaml"), "--ckpt_path", str(checkpoint),
                       "--data.init_args.source", str(video), "--data.init_args.image_width", "64",
                       "--data.init_args.frame_step", "2", "--data.init_args.num_workers", "0",
                       "--trainer.precision", "bf16-mixed", "--trainer.callbacks.output_dir", str(out),
                       "--trainer.callbacks.outputs", "[depth_npy, camera]"])
    names = [p["name"] for p in json.loads((out / "poses.json").read_text())]
    assert names == ["clip_f000000", "clip_f000002", "clip_f000004"]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"{n}_{s}" for n in names for s in ("depth.npy", "camera.json")]
        + ["poses.csv", "poses.json", "contact_sheet.png", "clip_depth.mp4", ".dapm_predict"])  # the frames beside
    # their depth; the marker that keeps a later run from reading them back as images
    preview = cv2.VideoCapture(str(out / "clip_depth.mp4"))
    assert preview.get(cv2.CAP_PROP_FRAME_COUNT) == 3 and preview.get(cv2.CAP_PROP_FPS) == pytest.approx(5.0)
    assert preview.get(cv2.CAP_PROP_FRAME_WIDTH) == 96 and preview.get(cv2.CAP_PROP_FRAME_HEIGHT) == 36
    preview.release()
    fp32 = DAPMPredictor.from_checkpoint(checkpoint, image_width=64)(next(iter(
        VideoFramesDataset(video, None, keep_rgb=True))).rgb)
    bf16 = np.load(out / "clip_f000000_depth.npy")
    assert bf16.dtype == np.float32 and not np.array_equal(bf16, fp32.depth_m)  # bf16 ran, not float32
    np.testing.assert_allclose(bf16, fp32.depth_m, rtol=0.1)  # the bins-mode readout is continuous, as the head


@pytest.mark.slow
def test_python_api_onnxruntime_backend_matches_pytorch(tmp_path):
    torch.manual_seed(0)
    module = DAPMModule(net=DAPMConfig(**TINY))
    module.net.depth_pqb.blocks[0].body[-1].bias.data.fill_(-4.0)
    # 48x96 at width 64 is 32x64 for both paths (the ONNX path rounds its sides to multiples of 32, eager does not)
    rgb = np.random.default_rng(3).integers(0, 255, (48, 96, 3), np.uint8)
    eager = DAPMPredictor(module, image_width=64)(rgb)
    fast = DAPMPredictor(module, image_width=64, onnx_path=tmp_path / "m.onnx")
    assert (tmp_path / "m.onnx").is_file()
    for got in (fast(rgb), fast([rgb, rgb])[1]):
        np.testing.assert_allclose(got.depth_m, eager.depth_m, rtol=1e-4, atol=1e-3)
        assert max(abs(got.pose[k] - eager.pose[k]) for k in got.pose) < 1e-3


# ------------------------------------------------------------------------------------------------- sky at every size
def sky_outputs(net_size=(64, 64), sky_rows=24, seed=0):
    """Network outputs with sky in the top ``sky_rows`` rows (as a sky-override model writes it: depth at the
    limit where sky_prob > 0.5) and ground below."""
    rng = torch.Generator().manual_seed(seed)
    prob = torch.rand(1, 1, *net_size, generator=rng) * 0.4
    prob[..., :sky_rows, :] += 0.55
    depth = 20 + 80 * torch.rand(1, 1, *net_size, generator=rng)
    depth = torch.where(prob > 0.5, torch.full_like(depth, 1000.0), depth)
    return InferenceOutput(depth, prob, torch.tensor([[40.0, -20.0, 5.0, 70.0]]))


@pytest.mark.parametrize("size", [(64, 64), (30, 40), (200, 300), (120, 24), (7, 5)])
@pytest.mark.parametrize("sky_rows", [24, 61])  # a third sky, and a frame that is almost all sky
def test_sky_is_sky_at_every_output_size(size, sky_rows, tmp_path):
    from dapm_lightning.inference.postprocess import predictions_from_outputs

    (result,) = predictions_from_outputs(sky_outputs(sky_rows=sky_rows), ["f"], [size], IGDSpec())
    sky = result.sky_prob > 0.5
    np.testing.assert_array_equal(result.sky, sky)
    assert sky.any() and ((~sky).any() or size == (7, 5))  # 7 rows of a 61/64-sky frame: all sky
    assert (result.depth_m[sky] == 1000.0).all() and (result.depth_m[~sky] < 1000.0).all()
    assert (result.depth_m >= 1000.0).sum() == sky.sum()  # `depth >= max_depth` finds exactly the sky
    assert (result.depth_m[~sky] <= 100.0 + 1e-3).all()  # resizing mixes no sky into the ground
    written = {p.name: p for p in write_prediction(tmp_path, result, OUTPUT_KINDS, points_stride=1)}
    depth16 = cv2.imread(str(written["f_depth16.png"]), cv2.IMREAD_UNCHANGED)
    assert (depth16[sky] == 64000).all() and (depth16[~sky] < 64000).all()
    colour = cv2.imread(str(written["f_depth_color.png"]))[:, :size[1]]  # the picture, left of its colour bar
    sky_colour = colour[sky][0]
    assert (colour[sky] == sky_colour).all() and not (colour[~sky] == sky_colour).all(axis=1).any()
    assert len(read_ply_independently(written["f_points.ply"])) == (~sky).sum()  # no sky point in the cloud


def test_sky_through_the_real_network_at_other_sizes(checkpoint, tmp_path):
    predictor = DAPMPredictor.from_checkpoint(checkpoint, image_width=64)
    predictor.module.net.depth_pqb.blocks[0].body[-1].bias.data[0] = 0.0  # sky logits near 0: sky and ground
    rng = np.random.default_rng(5)
    for shape in ((37, 53, 3), (300, 180, 3), (64, 64, 3)):
        result = predictor(rng.integers(0, 255, shape, np.uint8))
        np.testing.assert_array_equal(result.sky, result.sky_prob > 0.5)
        assert (result.depth_m[result.sky] == 1000.0).all() and (result.depth_m[~result.sky] < 1000.0).all()
        assert len(result.points().xyz) == (~result.sky).sum()


# --------------------------------------------------------------------------------------------- the network size
def test_network_size_keeps_the_training_pixel_count_in_each_aspect():
    assert network_size(3000, 4000, (512, 512)) == (443, 591)  # 4:3 kept to the pixel: square pixels, true FoV
    assert network_size(4000, 3000, (512, 512)) == (591, 443)
    assert network_size(3000, 4000, (64, 64)) == (55, 74)
    assert network_size(45, 70, None) == (45, 70) and network_size(10, 20, None) == (32, 64)  # short side >= 32


def test_the_checkpoint_records_its_training_size(checkpoint, tiny_uapd):
    predictor = DAPMPredictor.from_checkpoint(checkpoint)
    height, width = cv2.imread(str(next((tiny_uapd / "train").rglob("*.png")))).shape[:2]
    assert predictor.module.train_image_size == (height, width) == predictor.target
    loaded = torch.load(checkpoint, weights_only=True)
    assert loaded["dapm_train_image_size"] == [height, width]
    older = tmp = checkpoint.with_name("older.ckpt")
    del loaded["dapm_train_image_size"]
    torch.save(loaded, tmp)
    with pytest.warns(UserWarning, match="does not record its training image size"):
        assert DAPMPredictor.from_checkpoint(older).target == (512, 512)


def test_tiny_inputs_are_warned_about(checkpoint):
    predictor = DAPMPredictor.from_checkpoint(checkpoint, image_width=64)
    with pytest.warns(UserWarning, match="5x7 pixels enlarged 13x to the network's 64x90"):
        result = predictor(np.zeros((7, 5, 3), np.uint8))
    assert result.depth_m.shape == (7, 5)


# ------------------------------------------------------------------------------------------------ one line to run
def test_one_line_predict_on_a_folder_of_mixed_sizes(checkpoint, image_folder, tmp_path, capsys):
    from dapm_lightning.cli import main

    out = tmp_path / "out"
    main(["predict", str(image_folder), "--ckpt_path", str(checkpoint), "--out", str(out), "--device", "cpu",
          "--outputs", "depth_npy", "points", "npz"])
    summary = capsys.readouterr().out.strip().splitlines()[-1]
    assert summary == (f"predicted 3 images: depth_npy, points, npz per image; poses.csv, contact_sheet.png "
                       f"in {out}/")
    for name, shape in (("colour", (45, 70)), ("grey", (30, 30)), ("rgba16", (40, 52))):
        packed = np.load(out / f"{name}.npz")
        assert set(packed.files) == {"depth", "sky_prob", "K", "pose", "pose_network", "pose_fields",
                                     "camera_to_world"}
        assert list(packed["pose_fields"]) == ["height_m", "pitch_deg", "roll_deg", "fov_deg"]  # as the files say
        np.testing.assert_array_equal(packed["depth"], np.load(out / f"{name}_depth.npy"))
        assert packed["depth"].shape == shape and packed["K"].shape == (3, 3) and packed["pose"].shape == (4,)
    sheet = cv2.imread(str(out / "contact_sheet.png"))
    assert sheet.shape[0] >= 3 * 160
    # a second run into the same folder adds its rows to poses.csv, replacing those of the same name
    other = tmp_path / "other"
    other.mkdir()
    cv2.imwrite(str(other / "new.png"), np.full((40, 60, 3), 90, np.uint8))
    cv2.imwrite(str(other / "grey.png"), np.full((30, 30), 10, np.uint8))
    main(["predict", str(other), "--ckpt", str(checkpoint), "--out", str(out), "--device", "cpu",
          "--outputs", "depth_npy", "--contact_sheet", "0", "--exist_ok"])
    rows = (out / "poses.csv").read_text().splitlines()
    assert [r.split(",")[0] for r in rows] == ["name", "colour", "grey", "rgba16", "new"]
    assert [p["name"] for p in json.loads((out / "poses.json").read_text())] == ["colour", "grey", "rgba16", "new"]


def test_one_line_predict_errors_and_help(checkpoint, image_folder, tmp_path, capsys):
    from dapm_lightning.cli import main

    with pytest.raises(SystemExit) as info:
        main(["predict", str(image_folder), "--ckpt_path", str(checkpoint), "--ot", str(tmp_path)])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "did you mean --out" in err and len(err.splitlines()) <= 3
    with pytest.raises(SystemExit) as info:
        main(["predict", str(image_folder), "--ckpt_path", str(checkpoint), "--outputs", "depth_np"])
    assert info.value.code == 2 and "did you mean depth_npy" in capsys.readouterr().err
    for option, value in (("--igd_bound", ["-1"]), ("--telemetry_sigma", ["-1", "0", "0", "0"]),
                          ("--sensor_width_mm", ["nan"])):  # refused with the usage error, before the model loads
        with pytest.raises(SystemExit) as info:
            main(["predict", str(image_folder), "--ckpt_path", str(tmp_path / "not read.ckpt"), option, *value])
        assert info.value.code == 2 and f"argument {option}: must be" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:  # SOURCE after --outputs KIND KIND: taken as a third kind
        main(["predict", "--outputs", "depth_npy", "camera", str(image_folder), "--ckpt_path", str(checkpoint)])
    assert info.value.code == 2 and f"required: SOURCE ('{image_folder}' was read as an --outputs kind: put SOURCE " \
        "before --outputs, or give the kinds with commas" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(["predict", str(tmp_path / "nothing"), "--ckpt_path", str(checkpoint)])
    assert info.value.code == 1 and "nothing: no such file or folder" in capsys.readouterr().err
    with pytest.raises(SystemExit) as info:
        main(["predict", "--help"])
    head = capsys.readouterr().out.splitlines()[:12]
    assert info.value.code == 0 and any("SOURCE" in line for line in head) and any("--out" in line for line in head)


def test_lightning_form_finds_the_packaged_config_and_short_class_names(tmp_path, monkeypatch, capsys):
    from dapm_lightning.cli import main

    monkeypatch.chdir(tmp_path)  # no configs/ folder here: the package's own predict.yaml is read
    with pytest.raises(SystemExit) as info:
        main(["predict", "--config", "configs/predict.yaml", "--print_config"])
    assert info.value.code == 0 and "PredictDataModule" in capsys.readouterr().out
    with pytest.raises(SystemExit) as info:
        main(["predict", "--data.help", "PredictDataModule"])
    help_text = capsys.readouterr().out
    assert info.value.code == 0 and "--data.source" in help_text and "a folder of images" in help_text


def test_horizon_segment_lies_on_horizontal_rays():
    from dapm_lightning.geometry.camera import camera_rays, horizon_segment

    for pitch, roll, fov in ((-10.0, 0.0, 60.0), (-25.0, 20.0, 90.0), (5.0, -35.0, 50.0), (-5.0, 80.0, 70.0)):
        (x0, y0), (x1, y1) = horizon_segment(pitch, roll, fov, (240, 320))
        for t in (0.0, 0.3, 1.0):
            x, y = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
            u, v = x - 160, y - 120
            f = 320 / (2 * math.tan(math.radians(fov) / 2))
            p, r = math.radians(pitch), math.radians(roll)
            d_z = -(u / f) * math.sin(r) * math.cos(p) - (v / f) * math.cos(r) * math.cos(p) + math.sin(p)
            assert abs(d_z) < 1e-9
    assert horizon_segment(-90.0, 0.0, 60.0, (240, 320)) is None
    # the pixel rows above the segment see the sky, those below the ground (pitch -10, no roll)
    rays = camera_rays(torch.tensor([-10.0]), torch.tensor([0.0]), torch.tensor([60.0]), (240, 320))
    row = int(horizon_segment(-10.0, 0.0, 60.0, (240, 320))[0][1])
    assert (rays[0, row - 2, :, 2] > 0).all() and (rays[0, row + 2, :, 2] < 0).all()
