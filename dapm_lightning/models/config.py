"""DAPMConfig: every setting of the network, written once; the architecture check derives from it."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any, Literal

from dapm_lightning.geometry.depth_codec import IGD_RATIO_RANGE
from dapm_lightning.geometry.igd import IGDSpec
from dapm_lightning.models.init import WeightInit

DepthReadout = Literal["head", "bins_mode"]
DEPTH_READOUTS: tuple[str, ...] = ("head", "bins_mode")
"""Where the output depth is read (:attr:`DAPMConfig.depth_readout`)."""


def _architecture(default: Any) -> Any:
    """A field that changes the weights' shapes: a checkpoint must agree on it to be loaded."""
    return field(default=default, metadata={"architecture": True})


@dataclass(frozen=True)
class DAPMConfig:
    """Settings of :class:`~dapm_lightning.models.dapm.DAPMNet`; in configs under ``model.net``.

    Every ablation of the paper is a switch: ``depth_bins=()`` (no D-PQB), ``pose_bins=()`` (no P-PQB),
    ``use_igd_feature`` (the IGD of the predicted pose as a depth feature; the IGD *loss* is a loss
    setting), ``use_pose=False`` (DAPM(D)), ``use_depth=False`` (DAPM(P)).

    Args:
        backbone: timm model name (``resnet50`` in the paper, ``resnet18`` for CPU runs); an unknown name is
            refused when the config is built, with the closest names.
        pretrained: load ImageNet weights for the backbone (from the hub, or ``weights_path``).
        weights_path: local backbone weights file (``.safetensors``/``.pth``) for machines without internet.
        use_depth: build the depth branch.
        use_pose: build the pose branch.
        depth_bins: per-pixel bins per D-PQB stage; ``(2, 16, 64)``: sky map, 16 and 64 classes.
        pose_bins: per-component bins per P-PQB stage; ``(16, 64)``.
        use_igd_feature: feed the IGD of the (teacher-forced) predicted pose to the depth refinement.
        igd: the IGD specification (model, depth kind, max depth, pose ranges), shared with the loss.
        decoder_channels: FPN width.
        head_channels: width of the depth bins blocks and the depth head.
        igd_channels: width of the IGD feature.
        head_stride: resolution of the depth refinement relative to the image: 4 (cheap, learned convex
            upsampling to full resolution) or 1 (full resolution, as the paper); 2 and 8 also work.
        dropout: spatial dropout on the FPN laterals.
        pose_hidden: width of the pose decoder's MLP and of the pose bins stages.
        igd_feature_grad: let the depth losses reach the pose branch through the IGD feature
            (default False: the IGD feature sees a detached pose).
        pose_stages: how many of the deepest encoder stages the pose decoder pools (3: the 2nd-4th, as
            the paper's text and the authors' code, the default; 4: all).
        pose_projection: width of each pooled projection in the pose decoder (authors and default: 256).
        pose_bins_source: where the pose bins stages read from: ``"encoder"`` (a residual conv block on
            the deepest encoder stage per bins stage, the authors' released code: 11.8 M of their
            42.82 M; the default) or ``"decoder"`` (MLP stages on the pose decoder's feature: 12 M fewer
            parameters at ResNet-50, but worse roll and height at equal steps, docs/model.md).
        pose_residual_init: the refined pose logit is the head's output plus the initial pose logit
            (authors' code, the default); False: the head's output alone.
        depth_residual_priors: the refined depth logit is the head's output plus the initial depth and
            the IGD (both normalised; authors' code); False: the head's output alone.
        decoder_squeeze_excite: squeeze-excitation on the FPN laterals (authors' code only, not in the
            paper's text).
        sky_override: pixels the binary (sky) stage calls sky are set to ``max_depth`` in ``depth_m``
            (this project's default, needed when the depth loss leaves sky out, ``depth_space: metric``);
            False: ``depth_m`` is the refined depth alone, as the authors' code outputs it (their binary
            stage is supervised and feeds the later stages only; with ``depth_space: log_norm`` the
            regression itself learns sky as 1.0).
        input_normalization: ``"imagenet"`` (default): the [0, 1] image is normalised with ImageNet's mean and
            std inside the network; ``"none"``: the [0, 1] image goes to the encoder as is, as the authors feed
            it (``ToTensor()`` only; paper configs).
        block_dropout: ``Dropout2d`` at the end of every residual conv block (FPN, its head, the conv pose
            bins); the authors' 0.1 in the paper configs, 0 by default.
        pose_dropout: ``Dropout`` on each pooled vector before the pose decoder's projections (authors: 0.2).
        linear_dropout: ``Dropout`` after the inner ReLU of the pose branch's residual linear / MLP blocks
            (authors: 0.3).
        depth_parametrization: what the refined depth (the bins and the head) predicts: ``"absolute"`` (default,
            the paper's: the normalised log depth) or ``"igd_ratio"``: the normalised log of depth / IGD of the pose
            the network uses (its own, teacher-forced in training, or fused with a prior) over
            1/1024 to ``igd_ratio_max``, so nothing below the horizon is predicted farther than that many times the
            flat ground of that pose. Needs both branches and a refinement head; the decoder's initial depth stays
            absolute (the pose branch reads it). docs/model.md.
        igd_ratio_max: the upper end of the ``igd_ratio`` range, in (1, 4]: 1.25 by default (the default of
            :data:`~dapm_lightning.geometry.depth_codec.IGD_RATIO_RANGE`, what checkpoints saved without the setting
            were trained with); :data:`~dapm_lightning.geometry.depth_codec.GROUND_CENTRED_RATIO_MAX` (1.181)
            puts the flat ground at the centre of a bin of a 64-bin stage instead of on the edge between
            two, where the bins' mode reads it 6 % short. Saved with the weights: it is what their depth means.
        depth_readout: where the output depth (``depth_m``) is read: ``"head"`` (default, the paper's: the
            refinement head's regression over every bins stage) or ``"bins_mode"``: the mode of the last depth-bins
            stage: the soft-argmax over the heaviest window of three bins, chosen smoothly (continuous in the
            logits). The head, trained by Eq. 17, gives the mean of the depths it finds likely; where a pixel may be
            ground or an object (scenes unlike the training's) that mean lies between the two and is neither; the
            mode is one of them. Changes no weight: a checkpoint reads out either way
            (:func:`~dapm_lightning.training.checkpointing.load_dapm_module` ``net_overrides``). Needs depth bins
            stages. docs/model.md.
        pose_prior_input: the pose branch is told the telemetry (a pose prior: which components are known, their
            normalised values and σ; zeros when nothing is) in its decoder's pooled inputs and its refinement head,
            so that a known component informs the others (the height the FoV, the FoV the height, ...). Off by
            default and in the paper configs (the paper has no telemetry); trained by ``model.prior_training``.
            The depth branch is told the telemetry through the IGD of the fused pose either way. docs/model.md.
        pose_pool_grid: the pose branch pools each encoder feature map to a ``g x g`` grid instead of its mean (1, the
            default and the paper's global average pooling): where in the picture a feature lies (the texture
            coarsening toward the bottom of an oblique view, a horizon's tilt) then reaches the pose. Applies to the
            pose decoder's pooled stages and to the encoder pose bins stages. docs/model.md.
        depth_prior_input: the IGD feature is told the same telemetry vector beside the IGD map, so that the depth
            refinement knows how far the pose behind the IGD is to be trusted (all of it given, the height alone,
            nothing: the network's own). Needs ``use_igd_feature``; off by default and in the paper configs.
        weight_init: ``"pytorch"`` (default: PyTorch's) or ``"authors"``: the depth decoder's convs
            Kaiming-normal (fan_out) with bias 0, the pose branch's linears Xavier-normal with bias 0.01 and
            its convs Kaiming-normal (fan_out); the depth bins heads and the IGD feature keep PyTorch's, as the
            authors' code does. The encoder keeps its (ImageNet or random) weights.

    The paper's network (Table 7's 42.82 M at ResNet-50) is ``configs/paper/*.yaml``; the efficient
    variant (bins heads at 1/4 resolution) is ``configs/variants/efficient.yaml``. docs/model.md has the
    table of every difference between the paper's text, the authors' code and this project.
    """

    backbone: str = _architecture("resnet50")
    pretrained: bool = False
    weights_path: str | None = None
    use_depth: bool = _architecture(True)
    use_pose: bool = _architecture(True)
    depth_bins: tuple[int, ...] = _architecture((2, 16, 64))
    pose_bins: tuple[int, ...] = _architecture((16, 64))
    use_igd_feature: bool = _architecture(True)
    igd: IGDSpec = field(default_factory=IGDSpec)
    decoder_channels: int = _architecture(96)
    head_channels: int = _architecture(32)
    igd_channels: int = _architecture(16)
    head_stride: int = _architecture(4)
    dropout: float = 0.1
    pose_hidden: int = _architecture(256)
    igd_feature_grad: bool = False
    pose_stages: int = _architecture(3)
    pose_projection: int = _architecture(256)
    pose_bins_source: Literal["decoder", "encoder"] = _architecture("encoder")
    pose_residual_init: bool = _architecture(True)
    depth_residual_priors: bool = _architecture(False)
    decoder_squeeze_excite: bool = _architecture(False)
    sky_override: bool = True
    input_normalization: Literal["imagenet", "none"] = "imagenet"
    block_dropout: float = 0.0
    pose_dropout: float = 0.0
    linear_dropout: float = 0.0
    weight_init: WeightInit = "pytorch"
    depth_parametrization: Literal["absolute", "igd_ratio"] = _architecture("absolute")
    igd_ratio_max: float = _architecture(IGD_RATIO_RANGE[1])
    depth_readout: DepthReadout = "head"
    pose_prior_input: bool = _architecture(False)
    depth_prior_input: bool = _architecture(False)
    pose_pool_grid: int = _architecture(1)

    def __post_init__(self) -> None:
        object.__setattr__(self, "depth_bins", tuple(int(n) for n in self.depth_bins))
        object.__setattr__(self, "pose_bins", tuple(int(n) for n in self.pose_bins))
        if isinstance(self.igd, Mapping):
            object.__setattr__(self, "igd", IGDSpec(**self.igd))
        from dapm_lightning.models.encoder import check_backbone  # timm, imported when a config is built

        check_backbone(self.backbone)
        if not (self.use_depth or self.use_pose):
            raise ValueError("model.net: needs use_depth or use_pose (or both)")
        if self.use_igd_feature and not (self.use_depth and self.use_pose):
            raise ValueError("model.net.use_igd_feature needs both branches: the IGD comes from the predicted pose and "
                             "feeds the depth refinement (set use_igd_feature: false for DAPM(D) / DAPM(P))")
        if self.pose_bins_source not in ("decoder", "encoder"):
            raise ValueError("model.net.pose_bins_source must be 'decoder' or 'encoder', "
                             f"got {self.pose_bins_source!r}")
        if not 1 <= self.pose_stages <= 4:
            raise ValueError("model.net.pose_stages must be 1 to 4 (deepest encoder stages pooled), "
                             f"got {self.pose_stages}")
        if self.input_normalization not in ("imagenet", "none"):
            raise ValueError("model.net.input_normalization must be 'imagenet' or 'none', "
                             f"got {self.input_normalization!r}")
        if self.weight_init not in ("pytorch", "authors"):
            raise ValueError(f"model.net.weight_init must be 'pytorch' or 'authors', got {self.weight_init!r}")
        for name in ("dropout", "block_dropout", "pose_dropout", "linear_dropout"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"model.net.{name} must be in [0, 1), got {getattr(self, name)}")
        if self.depth_parametrization not in ("absolute", "igd_ratio"):
            raise ValueError("model.net.depth_parametrization must be 'absolute' or 'igd_ratio', "
                             f"got {self.depth_parametrization!r}")
        if self.depth_parametrization == "igd_ratio" and not (
                self.use_depth and self.use_pose and (self.depth_bins or self.use_igd_feature)):
            raise ValueError("model.net.depth_parametrization 'igd_ratio' needs both branches and a depth refinement "
                             "(depth_bins or use_igd_feature): the ratio is to the IGD of the predicted pose")
        if isinstance(self.igd_ratio_max, bool) or not 1.0 < float(self.igd_ratio_max) <= 4.0:
            raise ValueError("model.net.igd_ratio_max must be a number above 1 and at most 4, "
                             f"got {self.igd_ratio_max!r}")
        object.__setattr__(self, "igd_ratio_max", float(self.igd_ratio_max))
        if self.depth_readout not in DEPTH_READOUTS:
            raise ValueError(f"model.net.depth_readout must be one of {', '.join(DEPTH_READOUTS)}, "
                             f"got {self.depth_readout!r}")
        if self.depth_readout == "bins_mode" and not (self.use_depth and any(n > 2 for n in self.depth_bins)):
            raise ValueError("model.net.depth_readout 'bins_mode' needs a depth-bins stage of more than 2 bins "
                             f"(model.net.depth_bins, got {list(self.depth_bins)})")
        if self.pose_prior_input and not self.use_pose:
            raise ValueError("model.net.pose_prior_input needs the pose branch (use_pose): it tells the telemetry to "
                             "the pose decoder")
        if self.depth_prior_input and not self.use_igd_feature:
            raise ValueError("model.net.depth_prior_input needs the IGD feature (use_igd_feature): the telemetry is "
                             "told beside the IGD map")
        grid = self.pose_pool_grid
        if isinstance(grid, bool) or not (isinstance(grid, int) and 1 <= grid <= 8):
            raise ValueError(f"model.net.pose_pool_grid must be an integer from 1 to 8, got {grid!r}")
        if self.head_stride not in (1, 2, 4, 8):
            raise ValueError(f"model.net.head_stride must be 1, 2, 4 or 8, got {self.head_stride}")

    @classmethod
    def architecture_fields(cls) -> tuple[str, ...]:
        """Names of the settings that change the weights' shapes or what their outputs mean."""
        return tuple(f.name for f in fields(cls) if f.metadata.get("architecture"))

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> DAPMConfig:
        """Build from a plain mapping (a checkpoint's hyper-parameters); unknown keys are an error."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown model.net setting(s) {unknown}; known: {sorted(known)}")
        return cls(**dict(values))

    def to_dict(self) -> dict[str, Any]:
        """Plain values only (lists, dicts, numbers), safe in a ``weights_only`` checkpoint."""
        values = asdict(self)
        values["depth_bins"], values["pose_bins"] = list(self.depth_bins), list(self.pose_bins)
        values["igd"]["pose_ranges"] = {k: list(v) for k, v in self.igd.pose_ranges.items()}
        return values

    def check_loads(self, saved: Mapping[str, Any] | DAPMConfig, source: str) -> None:
        """Raise a ValueError listing every architecture setting where ``saved`` differs from this config.

        Args:
            saved: the network settings a checkpoint was trained with (``hyper_parameters["net"]``).
            source: what ``saved`` came from, for the message (a checkpoint path).
        """
        saved_config = saved if isinstance(saved, DAPMConfig) else DAPMConfig.from_dict(saved)
        differences = [f"model.net.{name}: checkpoint {getattr(saved_config, name)!r}, this run "
                       f"{getattr(self, name)!r}"
                       for name in self.architecture_fields() if getattr(saved_config, name) != getattr(self, name)]
        if differences:
            raise ValueError(f"{source} was trained with another network; it cannot be loaded into this one:\n  "
                             + "\n  ".join(differences)
                             + "\nFix: pass the config it was trained with (the config.yaml next to its log), or "
                               "set the settings above to the checkpoint's values.")


PAPER_NETWORK: Mapping[str, Any] = {
    "decoder_channels": 256, "head_channels": 128, "igd_channels": 32, "head_stride": 1, "pose_stages": 3,
    "pose_projection": 256, "pose_bins_source": "encoder", "pose_residual_init": True,
    "depth_residual_priors": True, "decoder_squeeze_excite": True, "sky_override": False}
"""The paper's network (configs/paper/*.yaml): 42.60 M parameters at ResNet-50 (the authors' 42.82 M, -0.5 %)."""

EFFICIENT_NETWORK: Mapping[str, Any] = {name: getattr(DAPMConfig, name) for name in PAPER_NETWORK}
"""The efficient variant: the :class:`DAPMConfig` defaults of the settings the paper's network changes (their
only home; configs/variants/efficient.yaml repeats them as an overlay, checked by a test). The paper's pose
branch with light depth heads: 38.00 M parameters and 26.9 GMAC at ResNet-50, 512² (paper: 226.3)."""

AUTHORS_TRAINING: Mapping[str, Any] = {
    "input_normalization": "none", "block_dropout": 0.1, "pose_dropout": 0.2, "linear_dropout": 0.3,
    "weight_init": "authors"}
"""What the authors' code adds to the network for training (configs/paper/*.yaml): no ImageNet normalisation of
the input, their dropouts and their initialisation. No parameter count changes."""
