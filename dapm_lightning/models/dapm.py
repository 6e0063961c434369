"""DAPMNet: the joint depth / pose network of the paper as a plain ``nn.Module`` (no Lightning)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from dapm_lightning.geometry.depth_codec import (
    IGD_RATIO_RANGE,
    decode_igd_ratio,
    decode_log_depth,
    encode_igd_ratio,
    encode_log_depth,
    flat_ground_logit,
)
from dapm_lightning.geometry.precision import held_in
from dapm_lightning.models.blocks import conv_bn_relu
from dapm_lightning.models.config import DAPMConfig
from dapm_lightning.models.decoders import DepthDecoder, PoseDecoder
from dapm_lightning.models.encoder import Encoder
from dapm_lightning.models.igd_branch import IGDFeature
from dapm_lightning.models.init import init_depth_decoder_like_authors, init_pose_like_authors
from dapm_lightning.models.pqb import DepthPQB, EncoderPosePQB, PosePQB, bins_mode
from dapm_lightning.models.prior import PRIOR_FEATURES, PosePrior, bins_spread, fuse_pose, prior_features
from dapm_lightning.models.teacher_forcing import TeacherForcing
from dapm_lightning.models.upsample import ConvexUpsample

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


class DepthPrediction(NamedTuple):
    """Depth branch output. Full resolution ``[B, 1, H, W]`` unless noted.

    ``depth_norm``: refined normalised log depth (the initial one when nothing refines it);
    ``depth_init_norm``: the decoder's; ``depth_m``: metres, sky set to ``max_depth``;
    ``sky_logits`` (None without a 2-bin stage); ``bin_logits``: ``[B, n, h, w]`` per bins stage;
    ``igd_norm``: the IGD fed to the refinement at head resolution (None without the IGD feature);
    ``refined``: whether a refinement head produced ``depth_norm``;
    ``igd_m``: with ``depth_parametrization: igd_ratio``, the IGD (metres, full resolution) of the pose the
    network used, which ``depth_norm`` is relative to (:func:`~dapm_lightning.geometry.depth_codec.encode_igd_ratio`);
    None: ``depth_norm`` is the absolute normalised log depth. ``ratio_max``: the upper end of that ratio's range
    (``model.net.igd_ratio_max``).
    ``readout_norm``: with ``depth_readout: bins_mode``, the depth read from the last bins stage, full resolution, in
    the space of ``depth_norm`` (``depth_m`` is its decoding); None: ``depth_m`` decodes ``depth_norm`` (the head's).
    ``depth_norm`` stays the head's either way: it is what Eq. 17 trains.
    """

    depth_norm: Tensor
    depth_init_norm: Tensor
    depth_m: Tensor
    sky_logits: Tensor | None
    bin_logits: tuple[Tensor, ...]
    igd_norm: Tensor | None
    refined: bool
    igd_m: Tensor | None = None
    readout_norm: Tensor | None = None
    ratio_max: float = IGD_RATIO_RANGE[1]

    def encode(self, depth_m: Tensor, max_depth: float) -> Tensor:
        """Metres ``[B, 1, H, W]`` in the space of ``depth_norm`` (targets of the loss and of the bins)."""
        if self.igd_m is None:
            return encode_log_depth(depth_m, max_depth)
        return encode_igd_ratio(depth_m, self.igd_m, max_depth, self.ratio_max)

    def decode(self, norm: Tensor, max_depth: float) -> Tensor:
        """Inverse of :meth:`encode`: metres."""
        if self.igd_m is None:
            return decode_log_depth(norm, max_depth)
        return decode_igd_ratio(norm, self.igd_m, max_depth, self.ratio_max)

    def log_depth_norm(self, max_depth: float) -> Tensor:
        """The output depth as absolute normalised log depth (the readout's; ``depth_norm`` in absolute space)."""
        norm = self.depth_norm if self.readout_norm is None else self.readout_norm
        return norm if self.igd_m is None else encode_log_depth(self.decode(norm, max_depth), max_depth)


class PosePrediction(NamedTuple):
    """Pose branch output.

    ``pose_norm``/``pose_init_norm`` ``[B, 4]`` in [0, 1], ``pose`` ``[B, 4]`` physical (m, deg, deg, deg): the
    network's own estimate (what the losses train); ``bin_logits`` ``[B, 4, n]`` per bins stage, ``refined`` as
    for depth. With a pose prior, ``used_norm``/``used``: the pose fused with it, which the IGD feature sees and
    inference reports (None without a prior: the network's own).
    """

    pose_norm: Tensor
    pose_init_norm: Tensor
    pose: Tensor
    bin_logits: tuple[Tensor, ...]
    refined: bool
    used_norm: Tensor | None = None
    used: Tensor | None = None


INFERENCE_OUTPUTS = ("depth_m", "sky_prob", "pose", "pose_network", "pose_spread")
"""What inference returns per image, by name: the predict step, the Python API and the ONNX model's outputs
(``pose_network`` only with a pose prior, ``pose_spread`` when asked for)."""


@dataclass(frozen=True)
class InferenceOutput:
    """What prediction takes from a forward pass, at the network size; what the model lacks is None.

    Every runtime (PyTorch, onnxruntime) returns this, so all go through the same post-processing.

    Attributes:
        depth_m: ``[B, 1, h, w]`` metres, sky at the depth limit.
        sky_prob: ``[B, 1, h, w]`` probability of "beyond max depth".
        pose: ``[B, 4]`` (height m, pitch, roll, fov deg): the pose used (fused with a prior where one was given).
        pose_network: ``[B, 4]`` the network's own estimate, when a prior was given to the network.
        pose_spread: ``[B, 4]`` normalised standard deviation of the last pose-bins distribution (to fuse a
            prior after the network).
    """

    depth_m: Tensor | None = None
    sky_prob: Tensor | None = None
    pose: Tensor | None = None
    pose_network: Tensor | None = None
    pose_spread: Tensor | None = None

    def named(self) -> dict[str, Tensor]:
        """The :data:`INFERENCE_OUTPUTS` present, by name, in that order (the ONNX model's outputs)."""
        return {name: value for name in INFERENCE_OUTPUTS if (value := getattr(self, name)) is not None}

    @property
    def batch_size(self) -> int:
        """Images in the batch."""
        return int(next(iter(self.named().values())).shape[0])

    @property
    def device(self) -> torch.device:
        """Where the outputs are."""
        return next(iter(self.named().values())).device

    def replace(self, **changes: Tensor | None) -> InferenceOutput:
        """A copy with ``changes``."""
        return dataclasses.replace(self, **changes)


class DAPMOutput(NamedTuple):
    """Everything one forward pass predicts; a branch switched off is ``None``."""

    depth: DepthPrediction | None
    pose: PosePrediction | None

    def inference_outputs(self, spread: bool = False) -> InferenceOutput:
        """The :class:`InferenceOutput` of this pass; ``spread``: with ``pose_spread`` (pose bins models)."""
        used = None if self.pose is None else self.pose.used
        pose_spread = None
        if spread and self.pose is not None and self.pose.bin_logits:
            pose_spread = bins_spread(self.pose.bin_logits[-1])
        return InferenceOutput(self.depth_m, self.sky_prob, self.pose_physical if used is None else used,
                               None if used is None else self.pose_physical, pose_spread)

    @property
    def depth_m(self) -> Tensor | None:
        """``[B, 1, H, W]`` metres, or None (DAPM(P))."""
        return None if self.depth is None else self.depth.depth_m

    @property
    def pose_physical(self) -> Tensor | None:
        """``[B, 4]`` (height m, pitch deg, roll deg, fov deg), or None (DAPM(D))."""
        return None if self.pose is None else self.pose.pose

    @property
    def sky_prob(self) -> Tensor | None:
        """``[B, 1, H, W]`` probability of "beyond max depth", or None without a sky stage."""
        if self.depth is None or self.depth.sky_logits is None:
            return None
        return torch.sigmoid(self.depth.sky_logits.float())  # float: half precision rounds near 0.5


class DAPMNet(nn.Module):
    """Depth estimation for Any Perspectives Model: encoder, depth and pose decoders, IGD, PQB.

    Only the modules a configuration uses are built (every parameter gets a gradient, as DDP
    requires). The depth is refined by a head at ``head_stride`` when there are depth bins stages or
    the IGD feature; with neither, the decoder's depth is the output.

    Example:
        >>> net = DAPMNet(DAPMConfig(backbone="resnet18"))
        >>> out = net(torch.rand(1, 3, 96, 128))
        >>> out.depth_m.shape, out.pose_physical.shape
        (torch.Size([1, 1, 96, 128]), torch.Size([1, 4]))
    """

    pixel_mean: Tensor
    pixel_std: Tensor

    def __init__(self, config: DAPMConfig | None = None) -> None:
        super().__init__()
        self.config = config = config or DAPMConfig()
        self.encoder = Encoder(config.backbone, pretrained=config.pretrained, weights_path=config.weights_path)
        channels = self.encoder.channels
        imagenet = config.input_normalization == "imagenet"  # "none": the [0, 1] image as is (the authors')
        mean, std = (IMAGENET_MEAN, IMAGENET_STD) if imagenet else ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
        self.register_buffer("pixel_mean", torch.tensor(mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("pixel_std", torch.tensor(std).view(1, 3, 1, 1), persistent=False)
        self.depth_decoder = self.to_head = self.igd_feature = self.depth_pqb = self.upsample = None
        self.pose_decoder = None
        self.pose_pqb: EncoderPosePQB | PosePQB | None = None
        if config.use_depth:
            self.depth_decoder = DepthDecoder(channels[-3:], config.decoder_channels, config.dropout,
                                              squeeze_excite=config.decoder_squeeze_excite,
                                              block_dropout=config.block_dropout)
            if self.refines_depth:
                igd_channels = config.igd_channels if config.use_igd_feature else 0
                self.to_head = conv_bn_relu(config.decoder_channels, config.head_channels, kernel_size=1)
                self.igd_feature = (IGDFeature(config.igd_channels,
                                               PRIOR_FEATURES if config.depth_prior_input else 0)
                                    if config.use_igd_feature else None)
                self.depth_pqb = DepthPQB(config.head_channels, igd_channels, config.depth_bins, config.head_channels)
                self.upsample = (ConvexUpsample(config.head_channels, config.head_stride)
                                 if config.head_stride > 1 else None)
        if config.use_pose:
            told = PRIOR_FEATURES if config.pose_prior_input else 0
            self.pose_decoder = PoseDecoder(channels[-config.pose_stages:], projection=config.pose_projection,
                                            hidden=config.pose_hidden, depth_grid=8 if config.use_depth else 0,
                                            projection_dropout=config.pose_dropout,
                                            mlp_dropout=config.linear_dropout, prior_features=told,
                                            pool_grid=config.pose_pool_grid)
            if config.pose_bins and config.pose_bins_source == "encoder":
                self.pose_pqb = EncoderPosePQB(channels[-1], config.pose_bins, config.pose_hidden,
                                               residual_init=config.pose_residual_init,
                                               block_dropout=config.block_dropout,
                                               linear_dropout=config.linear_dropout, prior_features=told,
                                               pool_grid=config.pose_pool_grid)
            elif config.pose_bins:
                self.pose_pqb = PosePQB(config.pose_hidden, config.pose_bins, config.pose_hidden)
        if config.weight_init == "authors":  # the bins heads and the IGD feature keep PyTorch's, as the authors'
            if self.depth_decoder is not None:
                init_depth_decoder_like_authors(self.depth_decoder)
            for part in (self.pose_decoder, self.pose_pqb):
                if part is not None:
                    init_pose_like_authors(part)

    @property
    def refines_depth(self) -> bool:
        """Whether a depth head refines the initial depth (depth bins stages or the IGD feature)."""
        return self.config.use_depth and (bool(self.config.depth_bins) or self.config.use_igd_feature)

    def forward(self, image: Tensor, teacher_forcing: TeacherForcing | None = None,
                prior: PosePrior | None = None) -> DAPMOutput:
        """Predict depth and pose.

        Args:
            image: ``[B, 3, H, W]`` RGB in [0, 1] (any H, W).
            teacher_forcing: in training, the true pose and the predicted share the IGD feature sees;
                None: the predicted pose alone.
            prior: known pose components (telemetry), fused with the network's pose (:func:`fuse_pose`) before
                the IGD feature and reported as ``pose.used``; ignored by a network without a pose branch.
        """
        if image.ndim != 4 or image.shape[1] != 3:
            raise ValueError(f"image must be [B, 3, H, W], got {tuple(image.shape)}")
        size = (image.shape[-2], image.shape[-1])
        features = self.encoder((image - self.pixel_mean) / self.pixel_std)
        depth_feature = depth_coarse = told = None
        if self.depth_decoder is not None:
            depth_feature, depth_coarse = self.depth_decoder(features[-3:])
        pose = None
        if self.pose_decoder is not None:
            told = (prior_features(prior, self.config.igd, image).to(image.dtype)
                    if self.config.pose_prior_input or self.config.depth_prior_input else None)
            pose = self._pose(features, None if depth_coarse is None else depth_coarse.detach(),
                              told if self.config.pose_prior_input else None)
            # exporting: always fused (a graph has no data-dependent branch; unknown components stay the network's)
            if prior is not None and (torch.compiler.is_exporting() or prior.known.any()):
                spread = bins_spread(pose.bin_logits[-1]).detach() if pose.bin_logits else None
                used_norm = fuse_pose(pose.pose_norm, prior.to(image.device), self.config.igd, spread)
                pose = pose._replace(used_norm=used_norm, used=self.config.igd.denormalize(used_norm))
        depth = None
        if depth_feature is not None and depth_coarse is not None:
            depth = self._depth(depth_feature, depth_coarse, size, pose, teacher_forcing,
                                told if self.config.depth_prior_input else None)
        return DAPMOutput(depth, pose)

    def _pose(self, features: list[Tensor], depth_coarse: Tensor | None,
              told: Tensor | None = None) -> PosePrediction:
        """``told``: the telemetry vector of a network with ``pose_prior_input`` (:func:`prior_features`)."""
        assert self.pose_decoder is not None
        pose_feature, pose_init, init_logit = self.pose_decoder(features[-self.config.pose_stages:], depth_coarse,
                                                                told)
        pose_norm, bin_logits = pose_init, ()
        if isinstance(self.pose_pqb, EncoderPosePQB):
            pose_logit, logits = self.pose_pqb(features[-1], init_logit, told)
            pose_norm, bin_logits = torch.sigmoid(pose_logit), tuple(logits)
        elif self.pose_pqb is not None:
            pose_logit, logits = self.pose_pqb(pose_feature, pose_init)
            if self.config.pose_residual_init:
                pose_logit = pose_logit + init_logit
            pose_norm, bin_logits = torch.sigmoid(pose_logit), tuple(logits)
        return PosePrediction(pose_norm, pose_init, self.config.igd.denormalize(pose_norm), bin_logits,
                              self.pose_pqb is not None)

    def _depth(self, depth_feature: Tensor, depth_coarse: Tensor, size: tuple[int, int],
               pose: PosePrediction | None, teacher_forcing: TeacherForcing | None,
               told: Tensor | None = None) -> DepthPrediction:
        igd = self.config.igd
        depth_init = F.interpolate(depth_coarse, size=size, mode="bilinear", align_corners=False)
        if self.depth_pqb is None or self.to_head is None:
            return DepthPrediction(depth_init, depth_init, decode_log_depth(depth_init, igd.max_depth), None, (),
                                   None, False)
        stride = self.config.head_stride
        # ceil division of positive sizes only: ONNX's integer Div truncates, so -(-H // s) exports as a floor
        head_size = (max(1, (size[0] + stride - 1) // stride), max(1, (size[1] + stride - 1) // stride))
        feature = self.to_head(F.interpolate(depth_feature, size=head_size, mode="bilinear", align_corners=False))
        init_head = F.interpolate(depth_coarse, size=head_size, mode="bilinear", align_corners=False)
        ratio = self.config.depth_parametrization == "igd_ratio"
        ratio_max = self.config.igd_ratio_max
        igd_norm = igd_feature = used_norm = None
        if pose is not None and (self.igd_feature is not None or ratio):
            own = pose.pose_norm if pose.used_norm is None else pose.used_norm
            used_norm = own if self.config.igd_feature_grad else own.detach()
            if teacher_forcing is not None:
                used_norm = teacher_forcing.blend(used_norm)
        if self.igd_feature is not None and used_norm is not None and pose is not None:
            igd_norm = held_in(igd.depth_norm(used_norm, head_size), pose.pose_norm)
            igd_feature = self.igd_feature(igd_norm, told)
        igd_m = igd_head = None
        if ratio and used_norm is not None:  # the depth is relative to the ground of the pose used
            used = igd.denormalize(used_norm.float())
            igd_m, igd_head = igd.depth(used, size), igd.depth(used, head_size)
        refined_logit, sky_logit, bin_logits = self.depth_pqb(feature, init_head, igd_feature)
        if self.config.depth_residual_priors and igd_head is not None:  # the initial depth as a ratio
            refined_logit = refined_logit + encode_igd_ratio(decode_log_depth(init_head, igd.max_depth), igd_head,
                                                             igd.max_depth, ratio_max).to(refined_logit.dtype)
        elif igd_head is not None:  # a correction to the flat ground (ratio 1)
            refined_logit = refined_logit + flat_ground_logit(ratio_max)
        elif self.config.depth_residual_priors:  # the authors' head: logit + initial depth + IGD (both in [0, 1])
            refined_logit = refined_logit + init_head + (0.0 if igd_norm is None else igd_norm)
        refined = self._to_size(torch.sigmoid(refined_logit), feature, size)
        readout = None
        if self.config.depth_readout == "bins_mode" and bin_logits:
            readout = self._to_size(bins_mode(bin_logits[-1]).to(refined.dtype), feature, size)
        sky_logits = (None if sky_logit is None
                      else F.interpolate(sky_logit, size=size, mode="bilinear", align_corners=False))
        output = refined if readout is None else readout
        depth_m = (decode_log_depth(output, igd.max_depth) if igd_m is None
                   else decode_igd_ratio(output, igd_m, igd.max_depth, ratio_max))
        if sky_logits is not None and self.config.sky_override:
            depth_m = torch.where(sky_logits > 0, torch.full_like(depth_m, igd.max_depth), depth_m)
        return DepthPrediction(refined, depth_init, depth_m, sky_logits, tuple(bin_logits), igd_norm, True, igd_m,
                               readout, ratio_max)

    def _to_size(self, norm: Tensor, feature: Tensor, size: tuple[int, int]) -> Tensor:
        """A ``[B, 1, h, w]`` map in [0, 1] at head resolution to the image size (the convex upsampling's)."""
        if self.upsample is not None:
            return self.upsample(norm, feature, size)
        if norm.shape[-2:] != size:
            return F.interpolate(norm, size=size, mode="bilinear", align_corners=False)
        return norm
