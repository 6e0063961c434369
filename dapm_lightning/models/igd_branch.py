"""IGD module, feature side: a pose becomes an ideal ground depth map, then convolutional features."""

from __future__ import annotations

from torch import Tensor, nn

from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_RANGES
from dapm_lightning.geometry.depth_codec import encode_log_depth
from dapm_lightning.geometry.igd import DepthKind, IGDModel, ideal_ground_depth
from dapm_lightning.geometry.pose import PoseRanges, denormalize_pose
from dapm_lightning.models.blocks import conv_bn_relu


def igd_norm_from_pose(pose_norm: Tensor, size: tuple[int, int], *, model: IGDModel = "pinhole",
                       depth_kind: DepthKind = "range", max_depth: float = MAX_DEPTH_M,
                       pose_ranges: PoseRanges = POSE_RANGES) -> Tensor:
    """IGD of a normalised pose ``[B, 4]`` in the normalised log space, ``[B, 1, H, W]`` in [0, 1]."""
    depth = ideal_ground_depth(denormalize_pose(pose_norm, pose_ranges), size, model=model,
                               depth_kind=depth_kind, max_depth=max_depth)
    return encode_log_depth(depth, max_depth)


class IGDFeature(nn.Module):
    """``IGD map [B, 1, h, w] -> [B, channels, h, w]`` through two 3x3 conv-BN-ReLU layers."""

    def __init__(self, channels: int = 16) -> None:
        super().__init__()
        self.body = nn.Sequential(conv_bn_relu(1, channels), conv_bn_relu(channels, channels))

    def forward(self, igd_norm: Tensor) -> Tensor:
        return self.body(igd_norm)
