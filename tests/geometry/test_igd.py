import math

import pytest
import torch

from dapm_lightning.geometry import (
    MAX_DEPTH_M,
    POSE_RANGES,
    IGDSpec,
    camera_rays,
    decode_log_depth,
    encode_log_depth,
    ideal_ground_depth,
)


def pose(h, p, r, f, dtype=torch.float64):
    return torch.tensor([[h, p, r, f]], dtype=dtype)


@pytest.mark.parametrize("model", ["pinhole", "paper"])
def test_nadir_centre_pixel_is_height(model):
    depth = ideal_ground_depth(pose(50.0, -90.0, 0.0, 60.0), (5, 7), model=model)
    assert depth.shape == (1, 1, 5, 7)
    assert depth[0, 0, 2, 3].item() == pytest.approx(50.0, rel=1e-9)


def test_pitch_minus_45_centre_is_height_sqrt2():
    depth = ideal_ground_depth(pose(30.0, -45.0, 10.0, 90.0), (9, 9))
    assert depth[0, 0, 4, 4].item() == pytest.approx(30.0 * math.sqrt(2.0), rel=1e-9)


def test_planar_is_range_times_cos_angle_to_axis():
    size = (12, 16)
    p = pose(40.0, -60.0, 12.0, 75.0)
    rng = ideal_ground_depth(p, size, depth_kind="range")
    planar = ideal_ground_depth(p, size, depth_kind="planar")
    rays = camera_rays(p[:, 1], p[:, 2], p[:, 3], size)  # axis component 1
    cos_angle = 1.0 / rays.norm(dim=-1)
    ground = rng < MAX_DEPTH_M
    torch.testing.assert_close(planar[ground], (rng[0, 0] * cos_angle[0])[ground[0, 0]])


def test_independent_ray_plane_intersection():
    """Brute force: build the rotation from the convention text and intersect in a loop."""
    h, p_deg, r_deg, f_deg = 25.0, -35.0, 20.0, 80.0
    H, W = 6, 8
    depth = ideal_ground_depth(pose(h, p_deg, r_deg, f_deg), (H, W), max_depth=1e9)[0, 0]
    p, r = math.radians(p_deg), math.radians(r_deg)
    focal = W / (2 * math.tan(math.radians(f_deg) / 2))
    fwd = torch.tensor([math.cos(p), 0.0, math.sin(p)], dtype=torch.float64)
    right = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64)
    down = torch.linalg.cross(fwd, right)
    right_r = math.cos(r) * right + math.sin(r) * down
    down_r = -math.sin(r) * right + math.cos(r) * down
    for i in range(H):
        for j in range(W):
            u, v = j + 0.5 - W / 2, i + 0.5 - H / 2
            d = u / focal * right_r + v / focal * down_r + fwd
            if d[2] < 0:
                t = h / -d[2]
                assert depth[i, j].item() == pytest.approx((t * d).norm().item(), rel=1e-9)
            else:
                assert depth[i, j].item() == 1e9


def test_positive_roll_raises_right_end_of_horizon():
    depth = ideal_ground_depth(pose(50.0, 0.0, 15.0, 90.0), (64, 64))[0, 0]
    sky_rows = (depth >= MAX_DEPTH_M).sum(0)  # sky pixels per column
    assert sky_rows[-1] < sky_rows[0]  # fewer sky pixels at the right: horizon higher there


@pytest.mark.parametrize("model", ["pinhole", "paper"])
def test_mirror_equals_negated_roll(model):
    poses = torch.tensor([[40.0, -50.0, 17.0, 70.0], [80.0, 5.0, -25.0, 110.0]], dtype=torch.float64)
    flipped = poses * torch.tensor([1.0, 1.0, -1.0, 1.0], dtype=torch.float64)
    a = ideal_ground_depth(poses, (10, 15), model=model).flip(-1)
    b = ideal_ground_depth(flipped, (10, 15), model=model)
    torch.testing.assert_close(a, b)


def test_paper_equals_pinhole_on_central_column_at_roll_zero():
    poses = torch.tensor([[30.0, -70.0, 0.0, 60.0], [60.0, -20.0, 0.0, 100.0]], dtype=torch.float64)
    pin = ideal_ground_depth(poses, (21, 21), model="pinhole")
    paper = ideal_ground_depth(poses, (21, 21), model="paper")
    torch.testing.assert_close(paper[..., 10], pin[..., 10])
    assert not torch.allclose(paper, pin)  # it is an approximation elsewhere


def test_paper_centre_pixel_of_odd_size_is_finite():
    depth = ideal_ground_depth(pose(50.0, -90.0, 0.0, 60.0), (7, 7), model="paper")
    assert torch.isfinite(depth).all()


@pytest.mark.parametrize("model", ["pinhole", "paper"])
@pytest.mark.parametrize("kind", ["range", "planar"])
def test_gradcheck_float64(model, kind):
    p = torch.tensor([[35.0, -55.0, 8.0, 65.0], [70.0, -80.0, -12.0, 40.0]], dtype=torch.float64,
                     requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda x: ideal_ground_depth(x, (5, 6), model=model, depth_kind=kind), (p,), eps=1e-6, atol=1e-5)


EXTREME = [
    [50.0, 80.0, 0.0, 60.0],  # looking up: all sky
    [50.0, -90.0, 180.0, 60.0],
    [50.0, -90.0, -180.0, 179.9999],
    [1e-9, -45.0, 0.0, 1e-9],
    [0.0, -90.0, 0.0, 0.0],
    [-5.0, -30.0, 10.0, 90.0],
    [1e6, -1.0, 30.0, 180.0],
    [50.0, 0.0, 0.0, 90.0],  # horizon through the centre
    [50.0, -200.0, 400.0, 500.0],
]


@pytest.mark.parametrize("model", ["pinhole", "paper"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_no_nan_or_inf_for_any_pose(model, dtype):
    p = torch.tensor(EXTREME, dtype=dtype, requires_grad=True)
    for kind in ("range", "planar"):
        depth = ideal_ground_depth(p, (9, 11), model=model, depth_kind=kind)
        assert torch.isfinite(depth).all()
        assert (depth >= 0).all() and (depth <= MAX_DEPTH_M).all()
        (grad,) = torch.autograd.grad(encode_log_depth(depth).sum(), p)
        assert torch.isfinite(grad).all()


def test_each_kind_clamped_on_its_own():
    size = (32, 32)
    p = pose(90.0, -5.0, 0.0, 100.0)
    rng = ideal_ground_depth(p, size, depth_kind="range", max_depth=1000.0)
    planar = ideal_ground_depth(p, size, depth_kind="planar", max_depth=1000.0)
    both = (rng >= 1000.0) & (planar < 1000.0)
    assert both.any()  # planar is not forced to max_depth where the range exceeds it


def test_batched_matches_single_and_cuda_if_present():
    poses = torch.tensor([[30.0, -40.0, 5.0, 70.0], [60.0, -80.0, -20.0, 100.0]])
    batched = ideal_ground_depth(poses, (8, 12))
    for k in range(2):
        torch.testing.assert_close(batched[k:k + 1], ideal_ground_depth(poses[k], (8, 12)))
    if torch.cuda.is_available():
        torch.testing.assert_close(ideal_ground_depth(poses.cuda(), (8, 12)).cpu(), batched)


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match=r"\[B, 4\]"):
        ideal_ground_depth(torch.zeros(2, 3), (4, 4))
    with pytest.raises(ValueError, match="model"):
        ideal_ground_depth(torch.zeros(1, 4), (4, 4), model="fisheye")  # type: ignore[arg-type]


def test_codec_roundtrip_and_limits():
    d = torch.tensor([0.0, 0.5, 1.0, 10.0, 123.4, 999.0, 1000.0], dtype=torch.float64)
    torch.testing.assert_close(decode_log_depth(encode_log_depth(d)), d)
    assert encode_log_depth(torch.tensor(5000.0)).item() == pytest.approx(1.0)
    x = torch.linspace(0, 1, 11, dtype=torch.float64)
    torch.testing.assert_close(encode_log_depth(decode_log_depth(x)), x)


@pytest.mark.parametrize("bad", [(90.0, 90.0), (120.0, 30.0), (30.0, math.inf), (30.0,), "30"])
def test_a_pose_range_that_normalises_nothing_is_refused_naming_the_setting(bad):
    """fov: [90, 90] (one lens) used to be accepted: every pose target became NaN, and the first training step failed
    in the pose bins' cross-entropy with 'IndexError: Target -9223372036854775808 is out of bounds'."""
    ranges = {**POSE_RANGES, "fov": bad}
    with pytest.raises(ValueError, match=r"model.net.igd.pose_ranges.fov: .*lo < hi.*\nFix: model.net.igd.pose_ranges"
                                         r".fov: \[30, 120\] \(UAPD's\)"):
        IGDSpec(pose_ranges=ranges)
    assert IGDSpec(pose_ranges={**POSE_RANGES, "fov": [89, 91]}).pose_ranges["fov"] == (89.0, 91.0)


def test_pose_ranges_given_in_part_keep_uapd_s_for_the_rest_and_an_unknown_component_is_refused():
    """conventions.md's one-lens example, `pose_ranges: {fov: [85, 95]}`, used to be refused for the three missing."""
    spec = IGDSpec(pose_ranges={"fov": [85, 95]})
    assert spec.pose_ranges == {**POSE_RANGES, "fov": (85.0, 95.0)}
    assert list(spec.pose_ranges) == list(POSE_RANGES)
    with pytest.raises(ValueError, match=r"pose_ranges: unknown component\(s\) \['fv'\]; the pose's are \['height'"):
        IGDSpec(pose_ranges={"fv": [85, 95]})
