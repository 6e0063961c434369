"""Each term of Eq. 16-19 against a value worked out by hand on a two-pixel example."""

import math

import pytest
import torch

from dapm_lightning.geometry import MAX_DEPTH_M, decode_log_depth, encode_log_depth, normalize_pose
from dapm_lightning.models import DAPMOutput, DepthPrediction, PosePrediction
from dapm_lightning.training.loss import DAPMLoss, LossConfig, laplacian_gradient_loss, silog_loss, silog_loss_per_image

LN2 = math.log(2.0)


def decode(x):
    return decode_log_depth(x, MAX_DEPTH_M)


def test_silog_by_hand():
    # g = (ln 2, 0): mean(g^2) = ln2^2 / 2, mean(g)^2 = ln2^2 / 4 -> 10 * sqrt(ln2^2 (1/2 - 0.85/4))
    value = silog_loss(torch.tensor([2.0, 4.0]), torch.tensor([1.0, 4.0]), torch.tensor([True, True]))
    assert value.item() == pytest.approx(10 * LN2 * math.sqrt(0.5 - 0.85 / 4), rel=1e-6)


def example():
    """Pixel 0: ground at 10 m, predicted 20 m; pixel 1: sky. Pose: nadir, height 46 m, predicted 55 m."""
    depth = torch.tensor([[[[10.0, MAX_DEPTH_M]]]])
    predicted = encode_log_depth(torch.tensor([[[[20.0, MAX_DEPTH_M]]]]))
    depth_prediction = DepthPrediction(
        depth_norm=predicted, depth_init_norm=predicted, depth_m=torch.tensor([[[[20.0, MAX_DEPTH_M]]]]),
        sky_logits=torch.zeros(1, 1, 1, 2), bin_logits=(torch.zeros(1, 16, 1, 2), torch.zeros(1, 64, 1, 2)),
        igd_norm=None, refined=True)
    true_pose = torch.tensor([[46.0, -90.0, 0.0, 60.0]])
    pose = torch.tensor([[55.0, -90.0, 0.0, 60.0]])
    pose_norm = normalize_pose(pose)
    pose_prediction = PosePrediction(pose_norm=pose_norm, pose_init_norm=normalize_pose(true_pose), pose=pose,
                                     bin_logits=(torch.zeros(1, 4, 16), torch.zeros(1, 4, 64)), refined=True)
    targets = dict(depth=depth, sky=depth >= MAX_DEPTH_M, valid=torch.ones_like(depth, dtype=torch.bool),
                   pose=true_pose, has_pose=torch.tensor([True]))
    return DAPMOutput(depth_prediction, pose_prediction), targets


def test_every_term_and_the_total_by_hand():
    out, targets = example()
    terms = DAPMLoss(LossConfig(igd_loss_stride=4))(out, targets)
    one_pixel_silog = 10 * LN2 * math.sqrt(1 - 0.85)  # Eq. 17 with g = ln 2 on the one ground pixel
    assert terms["depth"].item() == pytest.approx(one_pixel_silog, rel=1e-5)
    assert terms["init_depth"].item() == pytest.approx(one_pixel_silog, rel=1e-5)
    # Eq. 16: BCE of logit 0 on both valid pixels (ln 2) + CE of uniform 16 and 64 bins on the ground pixel
    assert terms["dq"].item() == pytest.approx(LN2 + math.log(16) + math.log(64), rel=1e-6)
    # Eq. 18: uniform bins, the mean over the 4 components of ln n
    assert terms["pq"].item() == pytest.approx(math.log(16) + math.log(64), rel=1e-6)
    # refined pose: height off by 9 m of a 90 m range, in 1 of 4 components
    assert terms["pose"].item() == pytest.approx((9 / 90) ** 2 / 4, rel=1e-5)
    assert terms["init_pose"].item() == pytest.approx(0.0, abs=1e-12)
    # L_pd: a 1x1 IGD of a nadir camera sees the ground at the camera height
    igd = (math.log2(56) - math.log2(47)) / math.log2(1001)
    assert terms["pd"].item() == pytest.approx(igd ** 2, rel=1e-4)
    expected = (terms["depth"] + 10 * terms["pose"] + terms["init_depth"] + terms["init_pose"] + terms["dq"]
                + terms["pq"] + 10 * terms["pd"])  # Eq. 19, rho = 10
    assert terms["total"].item() == pytest.approx(expected.item(), rel=1e-6)


def test_pose_bins_targets_are_the_true_poses_classes():
    # true pose (46, -90, 0, 60) normalised: (0.4, 1/11, 0.5, 1/3) -> 16 bins: 6, 1, 8, 5; 64 bins: 25, 5, 32, 21
    out, targets = example()
    logits = []
    for n, classes in ((16, [6, 1, 8, 5]), (64, [25, 5, 32, 21])):
        confident = torch.zeros(1, 4, n)
        confident[0, torch.arange(4), classes] = 30.0
        logits.append(confident)
    out = out._replace(pose=out.pose._replace(bin_logits=tuple(logits)))
    assert DAPMLoss()(out, targets)["pq"].item() == pytest.approx(0.0, abs=1e-9)


def test_the_sky_stage_is_trained_on_valid_pixels_only():
    # pixel 0: ground at 10 m, sky logit 0 (BCE ln 2); pixel 1: no depth (invalid), confidently called sky
    depth = torch.tensor([[[[10.0, float("nan")]]]])
    norm = encode_log_depth(torch.tensor([[[[10.0, 10.0]]]]))
    prediction = DepthPrediction(depth_norm=norm, depth_init_norm=norm, depth_m=decode(norm),
                                 sky_logits=torch.tensor([[[[0.0, 30.0]]]]), bin_logits=(), igd_norm=None,
                                 refined=True)
    targets = dict(depth=depth, sky=torch.zeros_like(depth, dtype=torch.bool), valid=torch.isfinite(depth))
    assert DAPMLoss().depth_terms(prediction, targets)["dq"].item() == pytest.approx(LN2, rel=1e-6)


def test_pose_terms_count_only_images_with_a_pose():
    # image 0 is example()'s (refined pose off by 9 m of 90 in height); image 1 has no pose and a far-off prediction
    out, targets = example()
    pose = out.pose
    far = torch.full((1, 4), 0.9)
    two = pose._replace(pose_norm=torch.cat([pose.pose_norm, far]),
                        pose_init_norm=torch.cat([pose.pose_init_norm, far]), pose=torch.cat([pose.pose, pose.pose]),
                        bin_logits=tuple(torch.cat([b, b]) for b in pose.bin_logits))
    pose_targets = dict(pose=torch.cat([targets["pose"], torch.full((1, 4), float("nan"))]),
                        has_pose=torch.tensor([True, False]))
    terms = DAPMLoss(LossConfig(use_igd_loss=False)).pose_terms(two, pose_targets)
    assert terms["pose"].item() == pytest.approx((9 / 90) ** 2 / 4, rel=1e-5)
    assert terms["init_pose"].item() == pytest.approx(0.0, abs=1e-12)
    assert terms["pq"].item() == pytest.approx(math.log(16) + math.log(64), rel=1e-6)


def test_switched_off_terms_are_absent():
    out, targets = example()
    terms = DAPMLoss(LossConfig(use_igd_loss=False))(out, targets)
    assert "pd" not in terms
    unrefined = out._replace(depth=out.depth._replace(refined=False, sky_logits=None, bin_logits=()))
    assert set(DAPMLoss()(unrefined, targets)) == {"init_depth", "init_pose", "pose", "pq", "pd", "total"}


def test_silog_in_the_authors_space_by_hand():
    # Eq. 17 as the authors compute it: on normalised log depth, per image, sky included, + 1e-3 under the root
    out, targets = example()
    terms = DAPMLoss(LossConfig(depth_space="log_norm"))(out, targets)
    g = math.log(math.log2(21) / math.log2(11))  # ground pixel: ln(encode(20 m) / encode(10 m)); sky: g = 0
    by_hand = 10 * math.sqrt(g ** 2 / 2 - 0.85 * (g / 2) ** 2 + 1e-3)
    assert terms["depth"].item() == pytest.approx(by_hand, rel=1e-5)
    assert terms["init_depth"].item() == pytest.approx(by_hand, rel=1e-5)
    metric = DAPMLoss(LossConfig(depth_space="metric"))(out, targets)["depth"].item()
    assert metric / by_hand > 1.4  # the same error weighs more in metres (the imbalance the switch undoes)
    # the other terms do not depend on the space
    assert terms["dq"].item() == pytest.approx(LN2 + math.log(16) + math.log(64), rel=1e-6)
    assert terms["pose"].item() == pytest.approx((9 / 90) ** 2 / 4, rel=1e-5)


def test_authors_space_averages_images_and_counts_zero_metres():
    # image 0: g = (ln 2, 0) on two ground pixels; image 1: a 0 m target (grey 0, clamped at 1e-3) predicted at 1e-3
    pred = torch.tensor([[[[0.2, 0.3]]], [[[1e-3, 0.5]]]])
    target_norm = torch.tensor([[[[0.1, 0.3]]], [[[0.0, 0.5]]]])
    depth = decode(target_norm)
    value = silog_loss_per_image(pred, target_norm, torch.ones_like(pred, dtype=torch.bool))
    image0 = 10 * math.sqrt(LN2 ** 2 / 2 - 0.85 * LN2 ** 2 / 4 + 1e-3)
    image1 = 10 * math.sqrt(1e-3)
    assert value.item() == pytest.approx((image0 + image1) / 2, rel=1e-5)
    prediction = DepthPrediction(depth_norm=pred, depth_init_norm=pred, depth_m=decode(pred), sky_logits=None,
                                 bin_logits=(), igd_norm=None, refined=False)
    targets = dict(depth=depth, sky=depth >= MAX_DEPTH_M, valid=depth > 0)
    term = DAPMLoss(LossConfig(depth_space="log_norm")).depth_terms(prediction, targets)["init_depth"]
    assert term.item() == pytest.approx((image0 + image1) / 2, rel=1e-4)  # the 0 m pixel counts


def test_gradient_loss_by_hand_and_opt_in():
    # 1x1 maps, zero padding: L(x) = 1 - 4x; t = 0.5, p = 0.25 -> (4 (p - t))^2 + (t - p)^2 (1 - 4 t) = 1 - 0.0625
    value = laplacian_gradient_loss(torch.tensor([[[[0.25]]]]), torch.tensor([[[[0.5]]]]),
                                    torch.tensor([[[[True]]]]))
    assert value.item() == pytest.approx(0.9375, rel=1e-6)
    out, targets = example()
    assert "grad" not in DAPMLoss()(out, targets)
    terms = DAPMLoss(LossConfig(use_gradient_loss=True))(out, targets)
    assert terms["total"].item() == pytest.approx(
        sum(LossConfig().weights[k] * v.item() for k, v in terms.items() if k != "total"), rel=1e-6)
    assert LossConfig().weights["grad"] == 10.0
    with pytest.raises(ValueError, match="depth_space"):
        LossConfig(depth_space="metres")


def test_authors_space_counts_zero_metre_pixels_in_the_bins():
    # one image, pixel 0 at 0 m (Potsdam ground) confidently in its class 0 (CE ~ 0), pixel 1 at 10 m uniform (ln 16)
    depth = torch.tensor([[[[0.0, 10.0]]]])
    norm = encode_log_depth(depth)
    logits = torch.zeros(1, 16, 1, 2)
    logits[0, 0, 0, 0] = 30.0
    prediction = DepthPrediction(depth_norm=norm, depth_init_norm=norm, depth_m=depth,
                                 sky_logits=torch.zeros(1, 1, 1, 2), bin_logits=(logits,), igd_norm=None, refined=True)
    targets = dict(depth=depth, sky=depth >= MAX_DEPTH_M, valid=depth > 0)
    authors = DAPMLoss(LossConfig(depth_space="log_norm")).depth_terms(prediction, targets)
    metric = DAPMLoss(LossConfig(depth_space="metric")).depth_terms(prediction, targets)
    assert authors["dq"].item() == pytest.approx(LN2 + math.log(16) / 2, rel=1e-6)  # CE: mean over both pixels
    assert metric["dq"].item() == pytest.approx(LN2 + math.log(16), rel=1e-6)  # CE: the 10 m pixel alone
    assert torch.isfinite(authors["depth"]) and authors["depth"].item() == pytest.approx(10 * math.sqrt(1e-3))


def test_sky_object_weight_weighs_what_stands_against_the_sky():
    """Row 0 of a level camera's picture lies above the horizon; a mast there (not sky) is weighted, the rest is not."""
    height, width = 8, 4
    pose = torch.tensor([[50.0, 0.0, 0.0, 60.0]])  # level: the top half above the horizon
    depth = torch.full((1, 1, height, width), MAX_DEPTH_M)
    depth[..., height // 2:, :] = 100.0  # ground below the horizon
    depth[..., 0, 0] = 80.0  # a mast above it
    logits = torch.full((1, 1, height, width), 3.0)  # everything called sky

    def dq(weight, has_pose=True):
        norm = encode_log_depth(depth.clamp(max=MAX_DEPTH_M))
        prediction = DepthPrediction(depth_norm=norm, depth_init_norm=norm, depth_m=depth, sky_logits=logits,
                                     bin_logits=(), igd_norm=None, refined=True)
        targets = dict(depth=depth, sky=depth >= MAX_DEPTH_M, valid=torch.ones_like(depth, dtype=torch.bool),
                       pose=pose if has_pose else torch.full_like(pose, float("nan")))
        return DAPMLoss(LossConfig(sky_object_weight=weight)).depth_terms(prediction, targets)["dq"].item()

    wrong = torch.nn.functional.softplus(torch.tensor(3.0)).item()  # BCE of a non-sky pixel called sky at logit 3
    assert dq(5.0) - dq(1.0) == pytest.approx(4 * wrong / (height * width), rel=1e-5)  # the mast alone, x5
    assert dq(5.0, has_pose=False) == pytest.approx(dq(1.0, has_pose=False))  # no pose: no horizon, no weight
    with pytest.raises(ValueError, match="sky_object_weight"):
        LossConfig(sky_object_weight=0.0)


@pytest.mark.parametrize(("setting", "value"), [("igd_loss_stride", 0), ("igd_loss_stride", -4),
                                                ("igd_loss_stride", 2.5), ("variance_focus", 1.5),
                                                ("variance_focus", -0.1), ("silog_scale", -10.0), ("silog_scale", 0.0)])
def test_loss_numbers_that_break_a_term_are_refused_naming_the_setting(setting, value):
    """Before: igd_loss_stride 0 died in the first step ('ZeroDivisionError: integer division or modulo by zero'), -4
    silently computed L_pd on a 1 x 1 IGD, variance_focus 1.5 left Eq. 17 clamped at 0 (no gradient) and a negative
    silog_scale made the depth terms rewards."""
    with pytest.raises(ValueError, match=rf"model.loss.{setting} .*must be .*got {value!r}"):
        LossConfig(**{setting: value})
    assert LossConfig(igd_loss_stride=1, variance_focus=1.0, silog_scale=1.0).variance_focus == 1.0
