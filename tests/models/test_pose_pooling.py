"""``model.net.pose_pool_grid``: the pose branch pools its feature maps to a grid of cells, not their mean."""
import pytest
import torch
import torch.nn.functional as F

from dapm_lightning.models import DAPMConfig, DAPMNet
from dapm_lightning.models.blocks import pool_cells
from dapm_lightning.models.decoders import PoseDecoder
from dapm_lightning.models.pqb import EncoderPosePQB


def test_pool_cells_is_the_mean_at_one_and_the_cells_means_beyond():
    x = torch.randn(2, 3, 4, 6)
    assert torch.equal(pool_cells(x, 1), x.mean(dim=(2, 3)))
    cells = pool_cells(x, 2).view(2, 3, 2, 2)  # channel-major: [B, C, rows, columns]
    assert torch.allclose(cells[:, :, 0, 1], x[:, :, :2, 3:].mean(dim=(2, 3)))
    assert torch.allclose(cells[:, :, 1, 0], x[:, :, 2:, :3].mean(dim=(2, 3)))
    odd = torch.randn(1, 2, 5, 7)  # uneven windows and a map smaller than the grid: PyTorch's adaptive windows
    assert torch.allclose(pool_cells(odd, 3), F.adaptive_avg_pool2d(odd, 3).flatten(1))
    assert pool_cells(torch.randn(1, 2, 1, 1), 2).shape == (1, 8)


def _top_and_bottom(channels: int, size: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    """The same feature in the top half of a map and in its bottom half: equal means, different layouts."""
    top = torch.zeros(1, channels, size, size)
    top[:, :, : size // 2] = torch.randn(1, channels, size // 2, size)
    return top, top.flip(2)


@pytest.mark.parametrize("grid", [1, 2])
def test_the_pose_decoder_sees_where_a_feature_lies_only_with_a_grid(grid):
    torch.manual_seed(0)
    decoder = PoseDecoder([8, 16], projection=16, hidden=32, depth_grid=0, pool_grid=grid).eval()
    (top8, bottom8), (top16, bottom16) = _top_and_bottom(8), _top_and_bottom(16)
    upper = decoder([top8, top16], None)[1]
    lower = decoder([bottom8, bottom16], None)[1]
    assert torch.allclose(upper, lower) == (grid == 1)


@pytest.mark.parametrize("grid", [1, 2])
def test_the_encoder_pose_bins_see_where_a_feature_lies_only_with_a_grid(grid):
    torch.manual_seed(0)
    head = EncoderPosePQB(8, (4, 8), channels=16, pool_grid=grid).eval()
    top, bottom = _top_and_bottom(8)
    # the conv block's zero padding alone tells top from bottom: compare the pooled cells, not the output
    stage = head.stages[0]
    upper, lower = stage[:3](top), stage[:3](bottom)
    assert upper.shape == (1, 16 * grid * grid)
    if grid == 1:
        assert torch.allclose(stage[0](top).mean(dim=(2, 3)), upper)
    else:
        assert not torch.allclose(upper, lower)
        assert torch.allclose(upper, pool_cells(stage[0](top), grid))
    logits, bins = head(top, torch.zeros(1, 4))
    assert logits.shape == (1, 4) and [b.shape for b in bins] == [(1, 4, 4), (1, 4, 8)]


def test_a_pooled_network_runs_at_any_size_and_every_weight_learns():
    torch.manual_seed(0)
    net = DAPMNet(DAPMConfig(backbone="resnet18", decoder_channels=32, head_channels=16, pose_pool_grid=3))
    for size in ((37, 53), (64, 96)):  # deepest stage 2x2 (smaller than the grid) and 2x3
        out = net(torch.rand(2, 3, *size))
        assert out.depth_m.shape == (2, 1, *size) and out.pose_physical.shape == (2, 4)
        out.pose_physical.sum().backward()
    pooled = [p for n, p in net.named_parameters() if n.startswith(("pose_decoder.projections", "pose_pqb.stages"))]
    assert pooled and all(p.grad is not None and p.grad.abs().sum() > 0 for p in pooled)


@pytest.mark.parametrize("grid", [0, 9, 1.5, "2", True])
def test_a_pool_grid_outside_one_to_eight_is_refused(grid):
    with pytest.raises(ValueError, match="pose_pool_grid"):
        DAPMConfig(pose_pool_grid=grid)
