import numpy as np
import pytest
import torch

from dapm_lightning.data.synthetic import render_scene, sample_pose, sample_scene
from dapm_lightning.geometry import MAX_DEPTH_M, POSE_RANGES, IGDSpec, normalize_pose
from dapm_lightning.models import DAPMConfig, DAPMNet, DAPMOutput, TeacherForcing
from dapm_lightning.training.loss import DAPMLoss, LossConfig

BACKBONE = "resnet18"


def make_net(**settings) -> DAPMNet:
    return DAPMNet(DAPMConfig(backbone=BACKBONE, **settings))


def forced(pose_norm, share):
    return TeacherForcing(pose_norm, share)
ABLATIONS = {
    "full": {},
    "no_pqb": dict(depth_bins=(), pose_bins=()),
    "no_d_pqb": dict(depth_bins=()),
    "no_p_pqb": dict(pose_bins=()),
    "no_igd_feature": dict(use_igd_feature=False),
    "bins_2_16_16": dict(depth_bins=(2, 16, 16), pose_bins=(16, 16)),
    "bins_2_64_64": dict(depth_bins=(2, 64, 64), pose_bins=(64, 64)),
    "bins_2": dict(depth_bins=(2,), pose_bins=(16,)),
    "paper_igd": dict(igd=IGDSpec(model="paper", depth_kind="planar")),
    "full_resolution_heads": dict(head_stride=1, head_channels=16),
    "decoder_pose_bins": dict(pose_bins_source="decoder", pose_stages=4, pose_projection=128,
                              pose_residual_init=False),
    "decoder_pose_bins_residual_init": dict(pose_bins_source="decoder"),
    "dapm_d": dict(use_pose=False, use_igd_feature=False),
    "dapm_p": dict(use_depth=False, use_igd_feature=False),
}


def targets_for(batch: int, size: tuple[int, int]) -> dict:
    depth = torch.rand(batch, 1, *size) * 300 + 2
    sky = torch.zeros(batch, 1, *size, dtype=torch.bool)
    sky[..., : size[0] // 4, :] = True
    depth[sky] = MAX_DEPTH_M
    return dict(depth=depth, sky=sky, valid=torch.ones_like(sky),
                pose=torch.tensor([[55.0, -45.0, 10.0, 75.0]] * batch), has_pose=torch.ones(batch, dtype=torch.bool))


@pytest.mark.parametrize("size", [(96, 128), (37, 53)])
def test_shapes_and_ranges_batch_one(size):
    out = make_net().eval()(torch.rand(1, 3, *size))
    assert isinstance(out, DAPMOutput)
    for name in ("depth_norm", "depth_init_norm", "sky_logits", "depth_m"):
        assert getattr(out.depth, name).shape == (1, 1, *size), name
    assert 0 <= out.depth.depth_norm.min() and out.depth.depth_norm.max() <= 1
    assert 0 < out.depth_m.min() and out.depth_m.max() <= MAX_DEPTH_M
    assert out.pose_physical.shape == (1, 4) and ((out.pose.pose_norm > 0) & (out.pose.pose_norm < 1)).all()
    assert [t.shape[1] for t in out.depth.bin_logits] == [16, 64]
    assert [t.shape[1:] for t in out.pose.bin_logits] == [(4, 16), (4, 64)]


@pytest.mark.parametrize("name", sorted(ABLATIONS))
def test_every_ablation_runs_forward_and_backward(name):
    net = make_net(**ABLATIONS[name])
    config = net.config
    loss = DAPMLoss(LossConfig(use_igd_loss=name != "no_igd_feature"), config.igd)
    out = net(torch.rand(2, 3, 48, 64))
    terms = loss(out, targets_for(2, (48, 64)))
    assert torch.isfinite(terms["total"])
    terms["total"].backward()
    unused = [n for n, p in net.named_parameters() if p.requires_grad and p.grad is None]
    assert not unused, f"built but not used (DDP refuses these): {unused[:5]}"
    assert ("depth" in terms) == (config.use_depth and (bool(config.depth_bins) or config.use_igd_feature))
    assert ("pq" in terms) == (config.use_pose and bool(config.pose_bins))
    assert (out.depth_m is None) == (not config.use_depth) and (out.pose is None) == (not config.use_pose)


def test_invalid_switches_are_refused():
    with pytest.raises(ValueError, match="use_igd_feature"):
        make_net(use_pose=False)
    with pytest.raises(ValueError, match="sky map"):
        make_net(depth_bins=(16, 2))
    with pytest.raises(ValueError, match="image must be"):
        make_net()(torch.rand(3, 32, 32))


def _grads(module, loss):
    module.zero_grad()
    loss.backward(retain_graph=True)
    return {n: p.grad is not None and p.grad.abs().sum().item() > 0 for n, p in module.named_parameters()}


@pytest.mark.parametrize("pose_bins_source", ["encoder", "decoder"])
def test_gradients_reach_only_where_they_should(pose_bins_source):
    torch.manual_seed(0)
    net = make_net(pose_bins_source=pose_bins_source)
    true = normalize_pose(torch.tensor([[50.0, -30, 5, 60]] * 2))
    terms = DAPMLoss()(net(torch.rand(2, 3, 48, 64), forced(true, 0.5)), targets_for(2, (48, 64)))
    for key in ("depth", "init_depth", "dq", "pose", "init_pose", "pq", "pd"):
        g = _grads(net, terms[key])
        assert any(v for n, v in g.items() if n.startswith("encoder.")), key
        reaches_pose = any(v for n, v in g.items() if n.startswith(("pose_decoder.", "pose_pqb.")))
        reaches_depth = any(v for n, v in g.items() if n.startswith(("depth_decoder.", "depth_pqb.")))
        assert reaches_pose == (key in ("pose", "init_pose", "pq", "pd")), key
        assert reaches_depth == (key in ("depth", "init_depth", "dq")), key
    # the initial pose's loss trains the pose decoder, not the refinement head
    g = _grads(net, terms["init_pose"])
    assert not any(v for n, v in g.items() if n.startswith("pose_pqb.head"))


def test_teacher_forcing_blends_the_igd_input():
    net = make_net().eval()
    image = torch.rand(1, 3, 48, 64)
    true = normalize_pose(torch.tensor([[30.0, -90.0, 0.0, 60.0]]))
    teacher = net(image, forced(true, 0.0)).depth
    own = net(image, forced(true, 1.0))
    igd = net.config.igd
    torch.testing.assert_close(teacher.igd_norm, igd.depth_norm(true, teacher.igd_norm.shape[-2:]))
    torch.testing.assert_close(own.depth.igd_norm, igd.depth_norm(own.pose.pose_norm, own.depth.igd_norm.shape[-2:]))
    assert not torch.allclose(teacher.depth_norm, own.depth.depth_norm)


def test_loss_is_finite_on_edge_batches():
    net = make_net()
    loss = DAPMLoss()
    size = (32, 48)
    all_sky = targets_for(2, size)
    all_sky["sky"][:] = True
    all_sky["depth"][:] = MAX_DEPTH_M
    invalid = targets_for(2, size)
    invalid["valid"][:] = False
    invalid["depth"][:] = 0.0
    no_pose = targets_for(2, size)
    no_pose["has_pose"][:] = False
    no_pose["pose"][:] = float("nan")
    for targets in (all_sky, invalid, no_pose, targets_for(1, size)):
        batch = targets["depth"].shape[0]
        terms = loss(net(torch.rand(batch, 3, *size)), targets)
        for key, value in terms.items():
            assert torch.isfinite(value), key
        net.zero_grad()
        terms["total"].backward()
        assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)


@pytest.mark.slow
def test_tiny_model_overfits_synthetic_images():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    size = (48, 64)
    images, depths, poses = [], [], []
    for _ in range(4):
        pose = sample_pose(rng)
        rgb, range_m, _ = render_scene(pose, size, sample_scene(rng))
        images.append(torch.from_numpy(rgb).permute(2, 0, 1).float() / 255)
        depths.append(torch.from_numpy(np.minimum(range_m, MAX_DEPTH_M)).float()[None])
        poses.append(torch.tensor(pose, dtype=torch.float32))
    image, depth, pose = torch.stack(images), torch.stack(depths), torch.stack(poses)
    targets = dict(depth=depth, sky=depth >= MAX_DEPTH_M, valid=torch.ones_like(depth, dtype=torch.bool), pose=pose)
    net = make_net(decoder_channels=32, head_channels=16, pose_hidden=64)
    loss = DAPMLoss()
    optimizer = torch.optim.AdamW(net.parameters(), lr=2e-3)
    history = []
    for _ in range(60):
        terms = loss(net(image, forced(normalize_pose(pose), 0.5)), targets)
        optimizer.zero_grad()
        terms["total"].backward()
        optimizer.step()
        history.append(terms["total"].item())
    assert history[-1] < history[0] / 4, history[::10]


def test_pose_ranges_are_configurable():
    image = torch.rand(1, 3, 32, 32)
    torch.manual_seed(0)
    default = make_net().eval()(image)
    torch.manual_seed(0)  # the same weights: the ranges only map the normalised pose to units
    wide = make_net(igd=IGDSpec(pose_ranges=dict(POSE_RANGES, height=(0.0, 500.0), fov=(20.0, 160.0)))).eval()(image)
    x = wide.pose.pose_norm[0]
    torch.testing.assert_close(x, default.pose.pose_norm[0])
    torch.testing.assert_close(wide.pose_physical[0], torch.stack([500 * x[0], -100 + 110 * x[1], -30 + 60 * x[2],
                                                                   20 + 140 * x[3]]))
    torch.testing.assert_close(default.pose_physical[0, 0], 10 + 90 * x[0])


@pytest.mark.parametrize("pose", [
    [10.0, -100.0, -30.0, 30.0], [100.0, 10.0, 30.0, 120.0],  # at the range limits
    [1e-4, -90.0, 0.0, 60.0], [250.0, 45.0, 120.0, 1e-3], [50.0, -40.0, 0.0, 179.999],  # beyond them
])
def test_loss_and_gradients_finite_for_extreme_true_poses(pose):
    net = make_net()
    targets = targets_for(2, (32, 48))
    targets["pose"] = torch.tensor([pose, pose])
    out = net(torch.rand(2, 3, 32, 48), forced(normalize_pose(targets["pose"]), 0.3))
    terms = DAPMLoss()(out, targets)
    assert all(torch.isfinite(v) for v in terms.values())
    terms["total"].backward()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
