import json
import math

import cv2
import numpy as np
import pytest
import torch
from PIL import Image

from dapm_lightning.geometry import depth_to_points, ideal_ground_depth, intrinsics_matrix
from dapm_lightning.models import DAPMConfig
from dapm_lightning.tools.predict import (
    DEPTH16_SCALE,
    DAPMPredictor,
    ImageFolderDataset,
    PredictionWriter,
    VideoFramesDataset,
    make_prediction,
    network_size,
    resolve_source,
    to_rgb8,
    write_prediction,
)
from dapm_lightning.training.lightning_cli import run_lightning_cli
from dapm_lightning.training.module import DAPMModule
from tests.conftest import CONFIGS

TINY = {"backbone": "resnet18", "decoder_channels": 16, "head_channels": 8, "igd_channels": 4, "pose_hidden": 16,
        "depth_bins": (2, 4), "pose_bins": (4,)}


def read_ply_independently(path):
    """A PLY reader written from the format's specification, independent of dapm_lightning.tools.ply."""
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
    ds = ImageFolderDataset(image_folder, image_width=64)
    for i in range(len(ds)):
        item = ds[i]
        assert item["image"].dtype == torch.uint8 and item["image"].shape[0] == 3
        assert item["image"].shape[2] == 64 and item["image"].shape[1] % 32 == 0
    with pytest.raises(ValueError, match="float32"):
        to_rgb8(np.zeros((4, 4), np.float32), "x.tif")
    with pytest.raises(ValueError, match="channels"):
        to_rgb8(np.zeros((4, 4, 5), np.uint8), "x.tif")
    assert network_size(480, 640, 512) == (384, 512)


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
    with pytest.raises(FileNotFoundError, match="matches no image.*quote"):
        resolve_source(f"{tmp_path}/*.jpg")
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(ValueError, match="neither an image"):
        resolve_source(tmp_path / "notes.txt")
    (tmp_path / "damaged.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="damaged.png: cannot be decoded"):
        ImageFolderDataset(tmp_path / "damaged.png")[0]
    (tmp_path / "broken.mp4").write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match="broken.mp4: OpenCV cannot open it"):
        VideoFramesDataset(tmp_path / "broken.mp4")


def test_video_frames_in_order_with_step_limit_and_workers(tmp_path):
    video = write_video(tmp_path / "flight.avi", frames=9)
    frames = list(VideoFramesDataset(video, image_width=32, frame_step=2, max_frames=4))
    assert [f["name"] for f in frames] == ["flight_f000000", "flight_f000002", "flight_f000004", "flight_f000006"]
    assert frames[0]["orig_size"].tolist() == [36, 48]
    # 2 workers, chunks of the batch size: the loader gives the frames back in video order
    loader = torch.utils.data.DataLoader(VideoFramesDataset(video, 32, chunk=2), batch_size=2, num_workers=2,
                                         collate_fn=lambda items: [i["name"] for i in items])
    assert [n for batch in loader for n in batch] == [f"flight_f{k:06d}" for k in range(9)]


def test_cli_predict_writes_every_output(checkpoint, image_folder, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # LightningCLI saves its config.yaml into the working directory when logger: false
    out = tmp_path / "pred"
    cli = run_lightning_cli(["predict", "--config", str(CONFIGS / "predict.yaml"), "--ckpt_path", str(checkpoint),
                             "--data.init_args.source", str(image_folder), "--data.init_args.image_width", "64",
                             "--data.init_args.batch_size", "1", "--data.init_args.num_workers", "0",
                             "--trainer.callbacks.output_dir", str(out), "--trainer.callbacks.points_stride", "3"])
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
        fov = camera["pose"]["fov_deg"]
        assert camera["pose"]["fov_deg"] == pytest.approx(row["fov_deg"], abs=1e-3)
        k = np.array(camera["K"])
        assert k[0, 0] == pytest.approx(shape[1] / (2 * math.tan(math.radians(fov) / 2)))
        assert (k[0, 2], k[1, 2]) == (shape[1] / 2, shape[0] / 2)
        # the point cloud is the written depth lifted with the written pose, every 3rd pixel, coloured
        ply = read_ply_independently(out / f"{name}_points.ply")
        pose = torch.tensor([[camera["pose"][k] for k in ("height_m", "pitch_deg", "roll_deg", "fov_deg")]],
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
            prediction = make_prediction("flat", (30, 44), depth, None, pose_t, depth_kind=depth_kind)
            write_prediction(tmp_path, "flat", prediction, outputs=["points", "camera"], points_stride=1)
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
    bf16 = DAPMPredictor(predictor.module, image_width=64, precision="bf16")(rgb)
    assert bf16.depth_m.dtype == np.float32 and np.isfinite(bf16.depth_m).all()
    points = a.points(stride=2, rgb=rgb)
    assert points.xyz.shape[1] == 3 and points.rgb.shape == points.xyz.shape
    with pytest.raises(ValueError, match="precision"):
        DAPMPredictor(predictor.module, precision="8")
    with pytest.raises(FileNotFoundError, match="no such checkpoint"):
        DAPMPredictor.from_checkpoint("missing.ckpt")


def test_python_api_video_and_single_branch_models(tmp_path):
    video = write_video(tmp_path / "v.avi", frames=5)
    torch.manual_seed(0)
    depth_only = DAPMPredictor(DAPMModule(net=DAPMConfig(**TINY, use_pose=False, use_igd_feature=False)),
                               image_width=32, batch_size=2)
    results = list(depth_only.predict_source(video, keep_rgb=True))
    assert [r.name for r in results] == [f"v_f{k:06d}" for k in range(5)]
    r = results[0]
    assert r.depth_m.shape == (36, 48) and r.pose is None and r.K is None and r.extras["rgb"].shape == (36, 48, 3)
    with pytest.raises(ValueError, match="needs depth and pose"):
        r.points()
    written = write_prediction(tmp_path, r.name, r)
    assert {p.name for p in written} == {f"{r.name}_{s}" for s in ("depth.npy", "depth.tif", "depth16.png",
                                                                    "depth_color.png", "sky.png")}
    pose_only = DAPMPredictor(DAPMModule(net=DAPMConfig(**TINY, use_depth=False, use_igd_feature=False)),
                              image_width=32)
    p = pose_only(np.zeros((36, 48, 3), np.uint8))
    assert p.depth_m is None and p.K.shape == (3, 3)
    assert {q.name for q in write_prediction(tmp_path, "pose_only", p)} == {"pose_only_camera.json"}
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
        [f"{n}_{s}" for n in names for s in ("depth.npy", "camera.json")] + ["poses.csv", "poses.json"])
    fp32 = DAPMPredictor.from_checkpoint(checkpoint, image_width=64)(next(iter(
        VideoFramesDataset(video, image_width=None, keep_rgb=True)))["rgb"].numpy())
    bf16 = np.load(out / "clip_f000000_depth.npy")
    assert bf16.dtype == np.float32 and not np.array_equal(bf16, fp32.depth_m)  # bf16 ran, not float32
    np.testing.assert_allclose(bf16, fp32.depth_m, rtol=0.1)


@pytest.mark.slow
def test_python_api_onnxruntime_backend_matches_pytorch(tmp_path):
    torch.manual_seed(0)
    module = DAPMModule(net=DAPMConfig(**TINY))
    module.net.depth_pqb.blocks[0].body[-1].bias.data.fill_(-4.0)
    rgb = np.random.default_rng(3).integers(0, 255, (50, 80, 3), np.uint8)
    eager = DAPMPredictor(module, image_width=64)(rgb)
    fast = DAPMPredictor(module, image_width=64, onnx_path=tmp_path / "m.onnx")
    assert (tmp_path / "m.onnx").is_file()
    for got in (fast(rgb), fast([rgb, rgb])[1]):
        np.testing.assert_allclose(got.depth_m, eager.depth_m, rtol=1e-4, atol=1e-3)
        assert max(abs(got.pose[k] - eager.pose[k]) for k in got.pose) < 1e-3
