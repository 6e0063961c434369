"""``depth_parametrization: igd_ratio``: the refined depth as the log ratio to the IGD of the pose used."""

import math

import pytest
import torch

from dapm_lightning.geometry import MAX_DEPTH_M, IGDSpec
from dapm_lightning.geometry.depth_codec import IGD_RATIO_RANGE, decode_igd_ratio, encode_igd_ratio
from dapm_lightning.geometry.igd import ideal_ground_depth
from dapm_lightning.models import DAPMConfig, DAPMNet, PosePrior, TeacherForcing
from dapm_lightning.training.loss import DAPMLoss

TINY = {"backbone": "resnet18", "decoder_channels": 16, "head_channels": 8, "igd_channels": 4, "pose_hidden": 16,
        "depth_bins": (2, 4), "pose_bins": (4,), "depth_parametrization": "igd_ratio"}
POSES = torch.tensor([[40.0, -50.0, 5.0, 70.0], [120.0, -10.0, -8.0, 90.0]])
SIZE = (24, 40)


def tiny_net(**overrides) -> DAPMNet:
    torch.manual_seed(0)
    net = DAPMNet(DAPMConfig(**{**TINY, **overrides})).eval()
    net.depth_pqb.blocks[0].body[-1].bias.data.fill_(-4.0)  # mostly ground, not all sky
    return net


def test_round_trip_and_flat_ground_is_ratio_one():
    igd = ideal_ground_depth(POSES, SIZE)
    assert (igd < MAX_DEPTH_M).any() and (igd == MAX_DEPTH_M).any()  # ground and sky above the horizon
    one = (0 - math.log2(IGD_RATIO_RANGE[0])) / (math.log2(IGD_RATIO_RANGE[1]) - math.log2(IGD_RATIO_RANGE[0]))
    norm = encode_igd_ratio(igd, igd)  # a flat ground scene: depth = IGD everywhere
    torch.testing.assert_close(norm, torch.full_like(norm, one))
    torch.testing.assert_close(decode_igd_ratio(norm, igd), igd)
    ratio = torch.rand(2, 1, *SIZE) * (1.2 - 0.01) + 0.01  # within the range: exact round trip
    depth = (ratio * igd).clamp(max=MAX_DEPTH_M)
    torch.testing.assert_close(decode_igd_ratio(encode_igd_ratio(depth, igd), igd), depth, rtol=1e-4, atol=1e-3)
    above = igd == MAX_DEPTH_M  # above the horizon the ratio is of the depth limit: absolute depth
    torch.testing.assert_close(decode_igd_ratio(encode_igd_ratio(depth, igd), igd)[above], depth[above], rtol=1e-4,
                               atol=1e-3)
    far = decode_igd_ratio(torch.ones_like(igd), igd)  # the largest depth: 1.25 x the flat ground, the limit above
    torch.testing.assert_close(far, (IGD_RATIO_RANGE[1] * igd).clamp(max=MAX_DEPTH_M))


def test_depth_respects_the_ground_of_the_pose_used():
    net = tiny_net()
    prior = PosePrior(POSES, torch.zeros(4))  # exact: the pose used is the prior
    with torch.no_grad():
        out = net(torch.rand(2, 3, *SIZE), prior=prior)
    igd = ideal_ground_depth(POSES, SIZE)
    torch.testing.assert_close(out.depth.igd_m, igd)
    ground = out.depth.sky_logits <= 0
    assert (out.depth_m[ground] <= IGD_RATIO_RANGE[1] * igd[ground] * (1 + 1e-5) + 1e-3).all()
    torch.testing.assert_close(out.depth.decode(out.depth.depth_norm, MAX_DEPTH_M)[ground], out.depth_m[ground])
    assert 0 <= out.depth.log_depth_norm(MAX_DEPTH_M).min() and out.depth.log_depth_norm(MAX_DEPTH_M).max() <= 1


def test_teacher_forcing_moves_the_ratio_reference():
    net = tiny_net(use_igd_feature=False)  # the ratio alone: the IGD feature is not what changes the depth
    image = torch.rand(2, 3, *SIZE)
    with torch.no_grad():
        own = net(image)
        forced = net(image, TeacherForcing(IGDSpec().normalize(POSES), 0.0))
    torch.testing.assert_close(forced.depth.igd_m, ideal_ground_depth(POSES, SIZE))
    torch.testing.assert_close(forced.depth.depth_norm, own.depth.depth_norm)  # same ratio, another reference
    assert not torch.allclose(forced.depth_m, own.depth_m)


def test_loss_is_in_the_ratio_space():
    net = tiny_net()
    net.train()
    depth = ideal_ground_depth(POSES, SIZE)  # a flat ground scene, sky above the horizon
    sky = depth >= MAX_DEPTH_M
    targets = {"depth": depth, "sky": sky, "valid": torch.ones_like(sky), "pose": POSES,
               "has_pose": torch.ones(2, dtype=torch.bool)}
    out = net(torch.rand(2, 3, *SIZE), TeacherForcing(IGDSpec().normalize(POSES), 0.0))
    terms = DAPMLoss(igd=net.config.igd)(out, targets)
    terms["total"].backward()
    assert all(torch.isfinite(v) for v in terms.values())
    used = {n for n, p in net.named_parameters() if p.grad is not None}
    assert used == {n for n, _ in net.named_parameters()}  # every parameter trained (DDP)
    # every ground pixel is one class: the ratio 1 (bins over the ratio range, not the absolute log depth)
    classes = out.depth.encode(depth, MAX_DEPTH_M)[~sky]
    assert torch.allclose(classes, classes[0])


@pytest.mark.parametrize("settings", [{"use_pose": False, "use_igd_feature": False},
                                      {"depth_bins": (), "use_igd_feature": False}])
def test_ratio_needs_a_pose_and_a_refinement(settings):
    with pytest.raises(ValueError, match="igd_ratio"):
        DAPMConfig(**{**TINY, **settings})


def test_a_checkpoint_of_the_other_parametrisation_is_refused():
    with pytest.raises(ValueError, match="depth_parametrization"):
        DAPMConfig(**TINY).check_loads(DAPMConfig(**{**TINY, "depth_parametrization": "absolute"}), "x.ckpt")


def test_paper_residual_priors_start_from_the_initial_depth():
    net = tiny_net(depth_residual_priors=True, head_stride=1)
    with torch.no_grad():
        for p in net.depth_pqb.head[-1].parameters():
            p.zero_()  # the head adds nothing: the refined ratio is sigmoid(initial depth as a ratio)
        out = net(torch.rand(1, 3, *SIZE), prior=PosePrior(POSES[:1], torch.zeros(4)))
    initial = encode_igd_ratio(torch.exp2(out.depth.depth_init_norm * math.log2(MAX_DEPTH_M + 1)) - 1,
                               out.depth.igd_m)
    torch.testing.assert_close(out.depth.depth_norm, torch.sigmoid(initial), rtol=1e-4, atol=1e-5)


FORCING = '[{"class_path": "dapm_lightning.training.callbacks.IGDTeacherForcing"}]'


def test_a_two_step_fit_with_priors_and_teacher_forcing(tiny_uapd, tmp_path):
    from dapm_lightning.training.checkpointing import load_dapm_module
    from dapm_lightning.training.lightning_cli import run_lightning_cli
    from tests.conftest import QUICKSTART

    cli = run_lightning_cli(["fit", "--config", str(QUICKSTART), "--data.class_path",
                             "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(tiny_uapd),
                             "--data.init_args.batch_size", "2", "--data.init_args.num_workers", "0",
                             "--model.net.depth_parametrization", "igd_ratio", "--model.prior_training.enabled", "true",
                             "--model.prior_training.image_fraction", "1.0",
                             "--trainer.max_steps", "2", "--trainer.limit_val_batches", "1",
                             "--trainer.logger", "false", "--trainer.callbacks", FORCING,
                             "--trainer.enable_checkpointing", "false", "--trainer.default_root_dir", str(tmp_path)])
    assert torch.isfinite(cli.trainer.callback_metrics["train_loss_step"])
    cli.trainer.save_checkpoint(tmp_path / "m.ckpt")
    module = load_dapm_module(tmp_path / "m.ckpt").eval()
    assert module.net_config.depth_parametrization == "igd_ratio"
    with torch.no_grad():
        out = module(torch.rand(1, 3, *SIZE))
    assert out.depth.igd_m is not None and torch.isfinite(out.depth_m).all()


@pytest.mark.slow
def test_onnx_export_equals_pytorch(tmp_path):
    from dapm_lightning.inference.onnx import export_onnx

    rows = export_onnx(tiny_net(), tmp_path / "m.onnx", (64, 64), checks=1, dynamic=False)
    assert rows[0]["depth_m"] < 1e-2 and rows[0]["pose"] < 1e-3  # metres, degrees: max differences


def test_a_head_that_adds_nothing_predicts_the_flat_ground():
    net = tiny_net(head_stride=1)
    with torch.no_grad():
        for p in net.depth_pqb.head[-1].parameters():
            p.zero_()
        out = net(torch.rand(2, 3, *SIZE), prior=PosePrior(POSES, torch.zeros(4)))
    ground = out.depth.sky_logits <= 0
    torch.testing.assert_close(out.depth_m[ground], ideal_ground_depth(POSES, SIZE)[ground], rtol=1e-4, atol=1e-3)


def test_the_centred_range_puts_the_flat_ground_at_a_bin_centre():
    from dapm_lightning.geometry.bins import bin_centers, quantize
    from dapm_lightning.geometry.depth_codec import GROUND_CENTRED_RATIO_MAX, flat_ground_norm

    igd = ideal_ground_depth(POSES, SIZE)
    below = igd < MAX_DEPTH_M
    for ratio_max, offset in ((IGD_RATIO_RANGE[1], 0.0), (GROUND_CENTRED_RATIO_MAX, 0.5)):
        norm = encode_igd_ratio(igd, igd, ratio_max=ratio_max)  # a flat ground scene
        assert ((norm[below] * 64) - (62.0 + offset)).abs().max() < 0.01  # 1.25: on the edge; centred: mid-bin
        assert flat_ground_norm(ratio_max) * 64 == pytest.approx(62.0 + offset, abs=0.01)
    # centred: the class the flat ground (and the 8-bit floor just under it, 0.986) falls in decodes to the ground
    for ratio in (1.0, 0.986):
        norm = encode_igd_ratio(ratio * igd, igd, ratio_max=GROUND_CENTRED_RATIO_MAX)
        centre = bin_centers(64, norm)[quantize(norm, 64)]
        decoded = decode_igd_ratio(centre, igd, ratio_max=GROUND_CENTRED_RATIO_MAX)
        torch.testing.assert_close(decoded[below], igd[below], rtol=1e-4, atol=1e-3)
    # 1.25: that class's centre is 5.5 % short of the ground
    norm = encode_igd_ratio(0.986 * igd, igd)
    short = decode_igd_ratio(bin_centers(64, norm)[quantize(norm, 64)], igd)[below] / igd[below]
    assert short.max() < 0.95


def test_igd_ratio_max_bounds_the_depth_is_checked_and_saved_with_the_weights():
    from dapm_lightning.geometry.depth_codec import GROUND_CENTRED_RATIO_MAX

    net = tiny_net(igd_ratio_max=GROUND_CENTRED_RATIO_MAX, depth_readout="bins_mode")
    prior = PosePrior(POSES, torch.zeros(4))
    with torch.no_grad():
        out = net(torch.rand(2, 3, *SIZE), prior=prior)
    igd = ideal_ground_depth(POSES, SIZE)
    ground = out.depth.sky_logits <= 0
    assert out.depth.ratio_max == GROUND_CENTRED_RATIO_MAX
    assert (out.depth_m[ground] <= GROUND_CENTRED_RATIO_MAX * igd[ground] * (1 + 1e-5) + 1e-3).all()
    readout = out.depth.decode(out.depth.readout_norm, MAX_DEPTH_M)
    torch.testing.assert_close(readout[ground], out.depth_m[ground])
    assert "igd_ratio_max" in DAPMConfig.architecture_fields()  # a checkpoint's depth means what it was trained as
    saved = {k: v for k, v in DAPMConfig(**TINY).to_dict().items() if k != "igd_ratio_max"}
    assert DAPMConfig.from_dict(saved).igd_ratio_max == IGD_RATIO_RANGE[1]  # saved before the setting: 1.25
    for bad in (1.0, 0.5, 5.0, True):
        with pytest.raises(ValueError, match="igd_ratio_max"):
            DAPMConfig(**{**TINY, "igd_ratio_max": bad})
