"""DAPMNet: the joint depth / pose network of the paper as a plain ``nn.Module`` (no Lightning)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_RANGES
from dapm_lightning.geometry.depth_codec import decode_log_depth
from dapm_lightning.geometry.igd import DepthKind, IGDModel
from dapm_lightning.geometry.pose import denormalize_pose
from dapm_lightning.models.blocks import conv_bn_relu
from dapm_lightning.models.decoders import DepthDecoder, PoseDecoder
from dapm_lightning.models.encoder import Encoder
from dapm_lightning.models.igd_branch import IGDFeature, igd_norm_from_pose
from dapm_lightning.models.pqb import DepthPQB, PosePQB
from dapm_lightning.models.upsample import ConvexUpsample

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass
class DAPMOutput:
    """Everything one forward pass predicts; ``None`` where the branch is switched off.

    Full resolution ``[B, 1, H, W]``: ``depth_norm`` (refined normalised log depth), ``depth_init_norm``,
    ``sky_logits``, ``depth_m`` (metres, sky set to ``max_depth``). Head resolution: ``depth_bin_logits``
    (``[B, n, h, w]`` per stage), ``igd_norm`` (the IGD fed to the bins). Pose: ``pose_norm`` and
    ``pose_init_norm`` ``[B, 4]`` in [0, 1], ``pose`` ``[B, 4]`` physical (m, deg, deg, deg),
    ``pose_bin_logits`` (``[B, 4, n]`` per stage).
    """

    depth_norm: Tensor | None = None
    depth_init_norm: Tensor | None = None
    sky_logits: Tensor | None = None
    depth_bin_logits: list[Tensor] = field(default_factory=list)
    depth_m: Tensor | None = None
    igd_norm: Tensor | None = None
    pose_norm: Tensor | None = None
    pose_init_norm: Tensor | None = None
    pose_bin_logits: list[Tensor] = field(default_factory=list)
    pose: Tensor | None = None


class DAPMNet(nn.Module):
    """Depth estimation for Any Perspectives Model: encoder, depth and pose decoders, IGD, PQB.

    Every ablation of the paper is a switch: ``depth_bins=()`` (no D-PQB), ``pose_bins=()`` (no
    P-PQB), ``use_igd_feature`` (IGD into the depth bins; the IGD loss is a :class:`DAPMLoss` switch),
    ``use_pose=False`` (DAPM(D), depth only), ``use_depth=False`` (DAPM(P), pose only).

    Args:
        backbone, pretrained, weights_path: see :class:`Encoder`.
        use_depth, use_pose: build the depth / pose branches.
        depth_bins: per-pixel bins per stage; ``(2, 16, 64)``: sky map, 16 and 64 classes.
        pose_bins: per-component bins per stage; ``(16, 64)``.
        use_igd_feature: feed the IGD of the (blended) pose into every depth bins block.
        igd_model, depth_kind, max_depth: passed to ``ideal_ground_depth``; ``depth_kind`` must be the
            data set's.
        decoder_channels: FPN width. head_channels: width of the bins blocks and the depth head.
        igd_channels: IGD feature width.
        head_stride: resolution of the bins heads relative to the image: 4 (default, cheap, with a
            learned convex upsampling to full resolution) or 1 (paper-faithful, full resolution).
        igd_feature_grad: let the depth losses reach the pose branch through the IGD feature
            (default False: the IGD feature sees a detached pose).
        pose_ranges: normalisation ranges (UAPD's).

    Example:
        >>> net = DAPMNet("resnet18")
        >>> out = net(torch.rand(1, 3, 96, 128))
        >>> out.depth_m.shape, out.pose.shape
        (torch.Size([1, 1, 96, 128]), torch.Size([1, 4]))
    """

    def __init__(self, backbone: str = "resnet50", *, pretrained: bool = False, weights_path: str | None = None,
                 use_depth: bool = True, use_pose: bool = True, depth_bins: Sequence[int] = (2, 16, 64),
                 pose_bins: Sequence[int] = (16, 64), use_igd_feature: bool = True, igd_model: IGDModel = "pinhole",
                 depth_kind: DepthKind = "range", max_depth: float = MAX_DEPTH_M, decoder_channels: int = 96,
                 head_channels: int = 32, igd_channels: int = 16, head_stride: int = 4, dropout: float = 0.1,
                 pose_hidden: int = 256, igd_feature_grad: bool = False,
                 pose_ranges: Mapping[str, tuple[float, float]] = POSE_RANGES) -> None:
        super().__init__()
        if not (use_depth or use_pose):
            raise ValueError("DAPMNet needs use_depth or use_pose (or both)")
        if use_igd_feature and not (use_depth and use_pose):
            raise ValueError("use_igd_feature needs both branches: the IGD comes from the predicted pose and "
                             "feeds the depth bins (set use_igd_feature=False for DAPM(D) / DAPM(P))")
        if head_stride not in (1, 2, 4, 8):
            raise ValueError(f"head_stride must be 1, 2, 4 or 8, got {head_stride}")
        self.use_depth, self.use_pose, self.use_igd_feature = use_depth, use_pose, use_igd_feature
        self.depth_bins, self.pose_bins = tuple(depth_bins), tuple(pose_bins)
        self.igd_model, self.depth_kind, self.max_depth = igd_model, depth_kind, max_depth
        self.head_stride, self.igd_feature_grad = head_stride, igd_feature_grad
        self.pose_ranges = dict(pose_ranges)
        self.encoder = Encoder(backbone, pretrained=pretrained, weights_path=weights_path)
        channels = self.encoder.channels
        self.register_buffer("pixel_mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("pixel_std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)
        if use_depth:
            self.depth_decoder = DepthDecoder(channels[-3:], decoder_channels, dropout)
            self.to_head = conv_bn_relu(decoder_channels, head_channels, kernel_size=1)
            self.igd_feature = IGDFeature(igd_channels) if use_igd_feature else None
            self.depth_pqb = (DepthPQB(head_channels, igd_channels if use_igd_feature else 0, self.depth_bins,
                                       head_channels) if self.depth_bins else None)
            self.upsample = ConvexUpsample(head_channels, head_stride) if head_stride > 1 else None
        if use_pose:
            self.pose_decoder = PoseDecoder(channels, hidden=pose_hidden, depth_grid=8 if use_depth else 0)
            self.pose_pqb = PosePQB(pose_hidden, self.pose_bins, pose_hidden) if self.pose_bins else None

    def forward(self, image: Tensor, pose_norm_true: Tensor | None = None, predicted_share: float = 1.0) -> DAPMOutput:
        """Predict depth and pose.

        Args:
            image: ``[B, 3, H, W]`` RGB in [0, 1] (any H, W).
            pose_norm_true: ``[B, 4]`` normalised true pose, for the IGD teacher forcing in training
                (rows with NaN, images without a pose, use the prediction).
            predicted_share: weight of the predicted pose in the IGD input,
                ``w * predicted + (1 - w) * true``; 1 (predictions only) when no true pose is given.
        """
        if image.ndim != 4 or image.shape[1] != 3:
            raise ValueError(f"image must be [B, 3, H, W], got {tuple(image.shape)}")
        size = (image.shape[-2], image.shape[-1])
        features = self.encoder((image - self.pixel_mean) / self.pixel_std)
        out = DAPMOutput()
        depth_feature = depth_coarse = None
        if self.use_depth:
            depth_feature, depth_coarse = self.depth_decoder(features[-3:])
            out.depth_init_norm = F.interpolate(depth_coarse, size=size, mode="bilinear", align_corners=False)
        if self.use_pose:
            pose_feature, out.pose_init_norm = self.pose_decoder(
                features, None if depth_coarse is None else depth_coarse.detach())
            out.pose_norm = out.pose_init_norm
            if self.pose_pqb is not None:
                pose_logit, out.pose_bin_logits = self.pose_pqb(pose_feature, out.pose_init_norm)
                out.pose_norm = torch.sigmoid(pose_logit)
            out.pose = denormalize_pose(out.pose_norm, self.pose_ranges)
        if self.use_depth:
            assert depth_feature is not None and depth_coarse is not None and out.depth_init_norm is not None
            self._refine_depth(out, depth_feature, depth_coarse, size, pose_norm_true, predicted_share)
        return out

    def _refine_depth(self, out: DAPMOutput, depth_feature: Tensor, depth_coarse: Tensor, size: tuple[int, int],
                      pose_norm_true: Tensor | None, predicted_share: float) -> None:
        head_size = (max(1, -(-size[0] // self.head_stride)), max(1, -(-size[1] // self.head_stride)))
        feature = self.to_head(F.interpolate(depth_feature, size=head_size, mode="bilinear", align_corners=False))
        init_head = F.interpolate(depth_coarse, size=head_size, mode="bilinear", align_corners=False)
        igd_feature = None
        if self.igd_feature is not None:
            assert out.pose_norm is not None
            pose = out.pose_norm if self.igd_feature_grad else out.pose_norm.detach()
            if pose_norm_true is not None and predicted_share < 1.0:  # teacher forcing
                known = torch.isfinite(pose_norm_true).all(dim=1, keepdim=True)  # images without a pose keep theirs
                true = torch.where(known, pose_norm_true, pose)
                pose = predicted_share * pose + (1.0 - predicted_share) * true
            out.igd_norm = igd_norm_from_pose(pose, head_size, model=self.igd_model, depth_kind=self.depth_kind,
                                              max_depth=self.max_depth, pose_ranges=self.pose_ranges)
            igd_feature = self.igd_feature(out.igd_norm)
        if self.depth_pqb is None:
            out.depth_norm = out.depth_init_norm
        else:
            refined_logit, sky_logit, out.depth_bin_logits = self.depth_pqb(feature, init_head, igd_feature)
            refined = torch.sigmoid(refined_logit)
            if self.upsample is not None:
                refined = self.upsample(refined, feature, size)
            elif refined.shape[-2:] != size:
                refined = F.interpolate(refined, size=size, mode="bilinear", align_corners=False)
            out.depth_norm = refined
            if sky_logit is not None:
                out.sky_logits = F.interpolate(sky_logit, size=size, mode="bilinear", align_corners=False)
        depth_m = decode_log_depth(out.depth_norm, self.max_depth)
        if out.sky_logits is not None:
            depth_m = torch.where(out.sky_logits > 0, torch.full_like(depth_m, self.max_depth), depth_m)
        out.depth_m = depth_m
