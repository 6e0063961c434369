import math

import pytest
import torch

from dapm_lightning.geometry import (
    MAX_DEPTH_M,
    camera_to_world,
    depth_to_points,
    ideal_ground_depth,
    intrinsics_matrix,
    valid_points,
)

POSES = [[50.0, -90.0, 0.0, 60.0], [30.0, -45.0, 12.0, 90.0], [80.0, -20.0, -25.0, 110.0],
         [15.0, -70.0, 30.0, 35.0], [40.0, 5.0, -10.0, 75.0]]


@pytest.mark.parametrize("depth_kind", ["range", "planar"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_flat_ground_lies_at_z_zero(depth_kind, dtype):
    pose = torch.tensor(POSES, dtype=dtype)
    depth = ideal_ground_depth(pose, (37, 52), depth_kind=depth_kind)
    points = depth_to_points(depth, pose, depth_kind=depth_kind)
    ground = valid_points(depth)
    assert ground.sum() > 0.3 * ground.numel() and not ground.all()  # the last pose sees sky
    distance = torch.linalg.vector_norm(points - torch.cat([torch.zeros_like(pose[:, :2]), pose[:, :1]], 1)
                                        [:, None, None], dim=-1)
    assert (points[..., 2][ground].abs() <= 1e-3 * distance[ground]).all()
    if depth_kind == "range":  # the point lies at the given range from the lens
        torch.testing.assert_close(distance[ground], depth[:, 0][ground], rtol=1e-5, atol=1e-4)


def test_worked_numbers():
    # odd size: the centre pixel looks along the optical axis
    nadir = depth_to_points(torch.full((1, 1, 5, 7), 50.0), torch.tensor([[50.0, -90.0, 0.0, 60.0]]))
    torch.testing.assert_close(nadir[0, 2, 3], torch.zeros(3), atol=1e-5, rtol=0)
    oblique = depth_to_points(torch.full((1, 5, 7), 50 * math.sqrt(2)), torch.tensor([[50.0, -45.0, 0.0, 60.0]]))
    torch.testing.assert_close(oblique[0, 2, 3], torch.tensor([50.0, 0.0, 0.0]), atol=1e-4, rtol=0)
    # positive roll turns the camera clockwise: its right side looks down, so the horizon's right end goes up
    rolled = depth_to_points(torch.full((1, 5, 7), 10.0), torch.tensor([[50.0, 0.0, 20.0, 60.0]]))
    assert rolled[0, 2, 6, 1] < 0 and rolled[0, 2, 6, 2] < 50.0 < rolled[0, 2, 0, 2]  # right: -Y and below the lens


def test_points_project_back_through_k():
    pose = torch.tensor([[35.0, -50.0, 17.0, 80.0]], dtype=torch.float64)
    h, w = 9, 14
    depth = torch.rand(1, 1, h, w, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 90 + 5
    planar = depth_to_points(depth, pose, depth_kind="planar")[0] - torch.tensor([0.0, 0.0, 35.0], dtype=torch.float64)
    p, r = (math.radians(x) for x in (-50.0, 17.0))
    forward = torch.tensor([math.cos(p), 0.0, math.sin(p)], dtype=torch.float64)
    right0, down0 = torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64), torch.tensor([math.sin(p), 0, -math.cos(p)],
                                                                                       dtype=torch.float64)
    right, down = math.cos(r) * right0 + math.sin(r) * down0, -math.sin(r) * right0 + math.cos(r) * down0
    camera = torch.stack([planar @ right, planar @ down, planar @ forward], -1)  # camera frame: x right, y down, z fwd
    torch.testing.assert_close(camera[..., 2], depth[0, 0])  # planar depth is the z of the camera frame
    transform = camera_to_world(pose)[0]  # the same camera frame as a 4x4 rigid transform
    torch.testing.assert_close(transform[:3, :3], torch.stack([right, down, forward], 1))
    torch.testing.assert_close(transform[:3, :3].T @ transform[:3, :3], torch.eye(3, dtype=torch.float64))
    world = camera @ transform[:3, :3].T + transform[:3, 3]
    torch.testing.assert_close(world, planar + torch.tensor([0.0, 0.0, 35.0], dtype=torch.float64))
    pixels = camera @ intrinsics_matrix(pose[:, 3], (h, w))[0].T
    jj, ii = torch.meshgrid(torch.arange(w, dtype=torch.float64), torch.arange(h, dtype=torch.float64), indexing="xy")
    torch.testing.assert_close(pixels[..., 0] / pixels[..., 2], jj + 0.5)
    torch.testing.assert_close(pixels[..., 1] / pixels[..., 2], ii + 0.5)


def test_mirror_is_negated_roll_and_y():
    pose = torch.tensor([[40.0, -35.0, 14.0, 70.0]])
    depth = torch.rand(1, 1, 6, 10, generator=torch.Generator().manual_seed(1)) * 100 + 1
    a = depth_to_points(depth, pose)
    b = depth_to_points(depth.flip(-1), pose * torch.tensor([1.0, 1.0, -1.0, 1.0]))
    torch.testing.assert_close(b.flip(2), a * torch.tensor([1.0, -1.0, 1.0]), atol=1e-4, rtol=1e-5)


def test_validity_and_bad_shapes():
    depth = torch.tensor([[[[1.0, MAX_DEPTH_M, float("nan"), 0.0]]]])
    assert valid_points(depth).tolist() == [[[True, False, False, False]]]
    with pytest.raises(ValueError, match=r"\[B, 4\]"):
        depth_to_points(torch.ones(2, 1, 3, 3), torch.ones(1, 4))
    with pytest.raises(ValueError, match="depth_m"):
        depth_to_points(torch.ones(1, 2, 3, 3), torch.ones(1, 4))
    with pytest.raises(ValueError, match="depth_kind"):
        depth_to_points(torch.ones(1, 1, 3, 3), torch.ones(1, 4), depth_kind="disparity")
