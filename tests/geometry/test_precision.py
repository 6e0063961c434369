"""Geometry under mixed precision: bf16 inputs and autocast regions compute in float32 (geometry/precision.py)."""

from collections import namedtuple

import pytest
import torch

from dapm_lightning.geometry import (
    IGDSpec,
    decode_log_depth,
    denormalize_pose,
    encode_log_depth,
    ideal_ground_depth,
    normalize_pose,
    quantize,
)
from dapm_lightning.geometry.precision import float32, to_float32

Pair = namedtuple("Pair", "low, high, logits, refined")

POSES = torch.tensor([[57.3, -63.4, 12.75, 88.1], [12.0, -90.0, 0.0, 60.0], [95.0, -5.0, -25.0, 115.0]])


def bf16_autocast():
    return torch.autocast("cpu", dtype=torch.bfloat16)


@pytest.mark.parametrize("model", ["pinhole", "paper"])
def test_igd_under_autocast_matches_float32(model):
    pose = POSES.bfloat16()  # what a bf16 pose head hands over
    expected = ideal_ground_depth(pose.float(), (24, 40), model=model)
    with bf16_autocast():
        got = ideal_ground_depth(pose, (24, 40), model=model)
        spec = IGDSpec(model=model)
        norm = spec.depth_norm(spec.normalize(pose.float()).bfloat16(), (24, 40))
    assert got.dtype == torch.float32 and norm.dtype == torch.float32
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=0)
    torch.testing.assert_close(norm, IGDSpec(model=model).depth_norm(spec.normalize(pose.float()).bfloat16().float(),
                                                                       (24, 40)), rtol=1e-5, atol=0)


def test_codec_pose_ranges_and_bin_targets_under_autocast_match_float32():
    depth = torch.tensor([0.0, 0.7, 12.5, 333.0, 999.0, 1000.0]).bfloat16()
    with bf16_autocast():
        encoded, decoded = encode_log_depth(depth), decode_log_depth(encode_log_depth(depth).bfloat16())
        pose_norm, pose = normalize_pose(POSES.bfloat16()), denormalize_pose(normalize_pose(POSES).bfloat16())
        levels = torch.linspace(0, 1, 1001).bfloat16()
        classes = quantize(levels, 100)
    torch.testing.assert_close(encoded, encode_log_depth(depth.float()), rtol=1e-5, atol=0)
    torch.testing.assert_close(decoded, decode_log_depth(encode_log_depth(depth.float()).bfloat16().float()),
                               rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(pose_norm, normalize_pose(POSES.bfloat16().float()), rtol=1e-5, atol=0)
    torch.testing.assert_close(pose, denormalize_pose(normalize_pose(POSES).bfloat16().float()), rtol=1e-5, atol=0)
    assert torch.equal(classes, quantize(levels.float(), 100))


def test_float32_switches_autocast_off_and_keeps_gradients():
    @float32
    def matmul(a, b):
        return a @ b

    a = torch.randn(3, 3, dtype=torch.bfloat16, requires_grad=True)
    with bf16_autocast():
        out = matmul(a, torch.randn(3, 3))  # autocast would run this matmul in bf16
    assert out.dtype == torch.float32
    out.sum().backward()
    assert a.grad is not None and a.grad.dtype == torch.bfloat16


def test_to_float32_keeps_structure_and_float64():
    pair = Pair(torch.ones(1).bfloat16(), torch.ones(1).double(), (torch.ones(1).half(),), True)
    cast = to_float32({"out": [pair], "n": 3})
    inner = cast["out"][0]
    assert isinstance(inner, Pair) and cast["n"] == 3 and inner.refined is True
    assert (inner.low.dtype, inner.high.dtype, inner.logits[0].dtype) == (torch.float32, torch.float64, torch.float32)


def test_outside_autocast_a_half_network_gets_half_back_computed_in_float32():
    """``export --fp16`` holds the whole network in float16: the IGD it feeds on must come back in float16."""
    pose = POSES.half()
    got = ideal_ground_depth(pose, (24, 40))
    assert got.dtype == torch.float16
    assert torch.equal(got, ideal_ground_depth(pose.float(), (24, 40)).half())
    assert quantize(torch.rand(5).half(), 4).dtype == torch.long


def test_torch_compile_traces_the_float32_islands_without_a_graph_break():
    import torch._dynamo

    def igd_of_a_bf16_pose(pose):
        return ideal_ground_depth(pose.bfloat16(), (8, 12)) * 2

    with bf16_autocast():
        explained = torch._dynamo.explain(igd_of_a_bf16_pose)(POSES)
    assert explained.graph_break_count == 0, [b.reason for b in explained.break_reasons]
