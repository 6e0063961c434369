"""DAPMModule: the LightningModule around :class:`DAPMNet` and :class:`DAPMLoss`."""

from __future__ import annotations

import math
import time
import warnings
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from typing import Any, Literal, cast

import lightning as L
import numpy as np
import torch
import torch.distributed as dist
from lightning.pytorch.trainer.states import TrainerFn
from lightning.pytorch.utilities import rank_zero_info
from lightning.pytorch.utilities.types import LRSchedulerTypeUnion, OptimizerLRSchedulerConfig
from torch import Tensor
from torch.nn.parallel import DistributedDataParallel
from torchmetrics import Metric

from dapm_lightning.data.sample import depth_masks
from dapm_lightning.data.unlabelled import PredictBatch
from dapm_lightning.geometry.image import unit_image
from dapm_lightning.metrics import AuthorsDepthMetrics, AuthorsPoseMetrics, DepthMetrics, PoseMetrics
from dapm_lightning.models.config import DAPMConfig
from dapm_lightning.models.dapm import DAPMNet, DAPMOutput
from dapm_lightning.models.prior import PosePrior
from dapm_lightning.models.teacher_forcing import TeacherForcing
from dapm_lightning.training.checkpoint_files import check_dapm_checkpoint, read_checkpoint
from dapm_lightning.training.loss import DAPMLoss, LossConfig
from dapm_lightning.training.resume import (
    count_batches_as_resumed,
    keep_checkpoint_rankings,
    resume_after_last_batch,
    start_next_epoch_as_any_other,
)
from dapm_lightning.training.rng import pack_rng_states, rng_states, set_rng_states, unpack_rng_states
from dapm_lightning.training.signals import SigtermAgreement, is_distributed

Stage = Literal["train", "val", "test"]


def warmup_cosine(step: int, total_steps: int, warmup_fraction: float, min_lr_ratio: float) -> float:
    """LR factor: linear warm-up over ``warmup_fraction`` of the steps, then cosine annealing to ``min_lr_ratio``."""
    warmup = max(1, int(round(total_steps * warmup_fraction)))
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total_steps - warmup))
    return min_lr_ratio + (1.0 - min_lr_ratio) * 0.5 * (1.0 + math.cos(math.pi * progress))


class TimeBudgetLR(torch.optim.lr_scheduler.LambdaLR):
    """Warm-up then cosine (:func:`warmup_cosine`) over ``budget`` seconds of training instead of steps.

    The factor follows :attr:`seconds`, the training time spent, in thousandths of the budget (:attr:`ticks`; the
    final rate once it is spent), which :meth:`read_clock` sets before each step. :attr:`seconds` is part of the
    state dict, so a resumed run goes on from it; the budget and the shape are the current settings'.
    """

    TICKS = 1000
    _NOT_SAVED = ("budget", "_started")

    def __init__(self, optimizer: torch.optim.Optimizer, budget: float, warmup_fraction: float,
                 min_lr_ratio: float) -> None:
        self.budget = budget
        self.seconds = 0.0
        """Training time spent, counted from the end of the first optimiser step."""
        self._started: tuple[float, float] | None = None
        """``(this process's clock, seconds)`` at this run's first :meth:`read_clock`."""
        super().__init__(optimizer, lambda _: warmup_cosine(self.ticks, self.TICKS, warmup_fraction, min_lr_ratio))

    @property
    def ticks(self) -> int:
        """Thousandths of the budget spent, 0 to 1000 (rounded down)."""
        return min(self.TICKS, int(self.TICKS * self.seconds / self.budget))

    def read_clock(self, agree: Callable[[float], float] = float) -> None:
        """Set :attr:`seconds` to the time since this run's first call plus the time spent before it.

        ``agree`` turns this process's figure into the one used (under DDP: the same on every process).
        """
        now = time.perf_counter()
        if self._started is None:
            self._started = (now, self.seconds)
        started, spent_before = self._started
        self.seconds = agree(spent_before + now - started)

    def state_dict(self) -> dict[str, Any]:
        return {k: v for k, v in super().state_dict().items() if k not in self._NOT_SAVED}


@dataclass(frozen=True)
class OptimizerConfig:
    """AdamW with linear warm-up then cosine annealing; in configs under ``model.optimizer``.

    Args:
        lr: peak learning rate (paper: 1e-4).
        weight_decay: AdamW weight decay (paper: 0.01).
        betas: AdamW betas (paper: 0.9, 0.999).
        warmup_fraction: share of the steps with a linear warm-up (paper: 0.3).
        min_lr_ratio: final learning rate as a share of ``lr``.
        schedule_steps: planned training length in optimiser steps, for the warm-up/cosine schedule and
            the IGD teacher forcing; None: the trainer's (``max_steps``, or epochs x batches). Fix it when a
            job may be stopped by ``max_steps`` and continued, so no step depends on where the job stopped.
        schedule_seconds: planned training length in seconds of wall time, for a run bounded by
            ``trainer.max_time`` (also with ``max_epochs: -1`` and no ``max_steps``): the
            warm-up/cosine schedule and the IGD teacher forcing follow the training time spent
            (:class:`TimeBudgetLR`: in thousandths of the budget, the final rate once it is spent) instead of
            the steps. Under DDP every process takes the same time; a resumed run goes on from the time
            spent when its checkpoint was saved. None: the schedules follow steps.
    """

    lr: float = 1e-4
    weight_decay: float = 0.01
    betas: tuple[float, float] = (0.9, 0.999)
    warmup_fraction: float = 0.3
    min_lr_ratio: float = 0.0
    schedule_steps: int | None = None
    schedule_seconds: float | None = None

    def __post_init__(self) -> None:
        """Refuse settings that cannot train (a negative ``min_lr_ratio`` ascended the gradient), naming them."""
        checks = {"lr": (self.lr, 0 <= self.lr < math.inf, ">= 0"),  # 0: the weights kept (tests, a warm-up probe)
                  "weight_decay": (self.weight_decay, 0 <= self.weight_decay < math.inf, ">= 0"),
                  "betas": (list(self.betas), len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas),
                            "two numbers in [0, 1)"),
                  "warmup_fraction": (self.warmup_fraction, 0 <= self.warmup_fraction <= 1, "in [0, 1]"),
                  "min_lr_ratio": (self.min_lr_ratio, 0 <= self.min_lr_ratio <= 1, "in [0, 1]"),
                  "schedule_steps": (self.schedule_steps, self.schedule_steps is None or self.schedule_steps >= 1,
                                     ">= 1 (or null)"),
                  "schedule_seconds": (self.schedule_seconds,
                                       self.schedule_seconds is None or 0 < self.schedule_seconds < math.inf,
                                       "> 0 (or null)")}
        for name, (value, ok, wanted) in checks.items():
            if not ok:
                raise ValueError(f"model.optimizer.{name} must be {wanted}, got {value}")


@dataclass(frozen=True)
class PriorTraining:
    """Pose priors during training, so that one checkpoint serves flights with full, partial or no telemetry.

    Each training image gets a prior with probability ``image_fraction``; each of its four components is then
    known with probability ``component_probability``: the true value plus Gaussian noise of ``noise`` (height m,
    pitch, roll, fov deg), given to the network with that σ. The network fuses it with its own pose
    (:func:`~dapm_lightning.models.prior.fuse_pose`) before the IGD feature; the pose losses keep training its
    own estimate. An image's draws depend only on (``seed``, epoch, its name), so runs repeat exactly under any
    number of processes and across a resume. Off in the paper configs; ``model.prior_training`` in configs.

    Args:
        enabled: give priors at all.
        image_fraction: share of training images with a prior.
        component_probability: chance that each component of such an image is known.
        noise: σ of the noise on (height m, pitch deg, roll deg, fov deg), the σ the network is told.
        seed: the draws of each image are seeded by (seed, epoch, image name).
    """

    enabled: bool = False
    image_fraction: float = 0.5
    component_probability: float = 0.5
    noise: tuple[float, float, float, float] = (3.0, 1.0, 1.0, 2.0)
    seed: int = 0

    def __post_init__(self) -> None:
        if not (0.0 <= self.image_fraction <= 1.0 and 0.0 <= self.component_probability <= 1.0):
            raise ValueError("model.prior_training: image_fraction and component_probability must be in [0, 1]")
        if len(self.noise) != 4 or min(self.noise) < 0:
            raise ValueError("model.prior_training.noise: four standard deviations >= 0 (height m, pitch, roll, "
                             "fov deg)")

    def sample(self, pose: Tensor, has_pose: Tensor, names: Sequence[str], epoch: int) -> PosePrior | None:
        """A training prior from the true poses ``[B, 4]`` (only images with a pose get one), or None when off.

        Each image's draws come from (``seed``, ``epoch``, its name): the same whatever the batch, the process
        count or a resume, and apart from the random state dropout uses.
        """
        if not self.enabled:
            return None
        uniform, normal = [], []
        for name in names:
            generator = torch.Generator().manual_seed(_draw_seed(self.seed, epoch, name))
            uniform.append(torch.rand(5, generator=generator))
            normal.append(torch.randn(4, generator=generator))
        u, z = torch.stack(uniform).to(pose.device), torch.stack(normal).to(pose.device)
        with_prior = (u[:, :1] < self.image_fraction) & has_pose.view(-1, 1)
        known = with_prior & (u[:, 1:] < self.component_probability)
        sigma = torch.tensor(self.noise, device=pose.device, dtype=torch.float32)
        noisy = pose.float() + z * sigma
        return PosePrior(torch.where(known, noisy, torch.full_like(noisy, float("nan"))), sigma)


def _draw_seed(seed: int, epoch: int, name: str) -> int:
    """A 63-bit seed from (seed, epoch, a sample's name)."""
    state = np.random.SeedSequence([seed, epoch, zlib.crc32(name.encode("utf-8"))]).generate_state(2)
    return int(state[0]) << 31 ^ int(state[1])


def _as_config(value: Any, kind: type[Any]) -> Any:
    """A settings dataclass from itself, a mapping (checkpoint hyper-parameters) or None (defaults)."""
    if value is None:
        return kind()
    if isinstance(value, kind):
        return value
    if isinstance(value, Mapping):
        return kind.from_dict(value) if hasattr(kind, "from_dict") else kind(**value)
    raise TypeError(f"expected {kind.__name__} or a mapping, got {type(value).__name__}")


def training_image_size(checkpoint: dict[str, Any]) -> tuple[int, int] | None:
    """``(H, W)`` a checkpoint was trained at; None when it does not say.

    Recorded by :class:`DAPMModule`; older checkpoints: the saved data module's ``image_size`` or ``crop_size``.
    """
    recorded = checkpoint.get("dapm_train_image_size")
    if recorded is not None:
        return int(recorded[0]), int(recorded[1])
    data = checkpoint.get("datamodule_hyper_parameters") or {}
    data = data.get("init_args", data) if isinstance(data, dict) else {}
    for key in ("image_size", "crop_size"):
        if isinstance(data.get(key), int):
            return int(data[key]), int(data[key])
    return None


class DAPMModule(L.LightningModule):
    """Train, validate, test and predict DAPM and its ablations; every loss term and metric logged by name.

    Args:
        net: the network's settings (:class:`~dapm_lightning.models.config.DAPMConfig`), ``model.net`` in configs.
        loss: the loss' weights and switches (:class:`~dapm_lightning.training.loss.LossConfig`), ``model.loss``.
        optimizer: AdamW and its schedule (:class:`OptimizerConfig`), ``model.optimizer``.
        log_space_metrics: also log the toolbox depth metrics on grey levels of the 8-bit log encoding
            (``<stage>_depthlog_*``: per image, sky excluded; not the authors' protocol).
        authors_depth_metrics: also log the authors' released evaluation (``<stage>_depthauthors_*``:
            grey levels, sky included, pixels pooled; RMS as ``rmse_grey`` and ``rmse_unit``), the only
            depth figures comparable with the paper's Table 4.
        pose_auc_min_error: pose errors at or below it count as perfect in the AUC, as GeoCalib's ``min_error``
            (its evaluation passes 1; :func:`~dapm_lightning.metrics.auc_of_recall`); the medians are unchanged.
        authors_pose_metrics: also log the authors' pose protocol (``<stage>_poseauthors_*``: the 3-point AUC
            through (0, 0), (1, r1), (5, r5), (10, r10) and the MAE per component), the protocol of the
            paper's Table 8 AUC figures.
        skip_nonfinite_loss: skip a training step whose loss is NaN or Inf (with a warning and
            ``train_nonfinite_steps``) instead of corrupting the weights.
        prior_training: pose priors drawn from the true pose during training (:class:`PriorTraining`), so
            that the model learns to use telemetry; off by default.
        init_weights: start ``fit`` from the weights of this checkpoint (a ``.ckpt``, a split checkpoint folder
            such as ``models/dapm-synthetic-r18-256``, or a remote file) instead of random or ImageNet ones:
            fine-tuning (the backbone is then built without ImageNet weights: nothing is downloaded). Its network
            must have this run's architecture (the differences are listed otherwise); the optimizer, the step
            count and the schedule start afresh. ``dapm-lightning fit`` reads it before the fit starts, in every
            process, unless ``--ckpt_path`` resumes a run (the resumed weights win; the file may be gone). In
            Python, call :meth:`load_initial_weights` before ``trainer.fit`` (or the module does it as the fit
            starts). Read once: weights from a checkpoint (a resume, ``load_from_checkpoint``) or a later fit
            of the same module are never replaced by it.

    :attr:`igd_predicted_share` (the IGD teacher-forcing weight) is set by
    :class:`~dapm_lightning.training.callbacks.IGDTeacherForcing` during training; validation, test and
    predict always use the predicted pose alone. Checkpoints carry the RNG states, and loading one trained
    with another architecture fails with a message listing what differs.

    Logged keys: ``<stage>_loss_<term>``, ``<stage>_depth_<metric>`` (metres),
    ``<stage>_depthlog_<metric>`` (toolbox protocol on grey levels), ``<stage>_depthauthors_<metric>`` (the
    authors' protocol), ``<stage>_pose_<component>_<stat>`` (GeoCalib's AUC),
    ``<stage>_poseauthors_<component>_<stat>`` (the authors' AUC and MAE).
    """

    igd_predicted_share: float
    """Weight of the predicted pose in the IGD input during training (1: predictions only)."""

    def __init__(self, net: DAPMConfig = DAPMConfig(), loss: LossConfig = LossConfig(),  # noqa: B008 (frozen)
                 optimizer: OptimizerConfig = OptimizerConfig(), log_space_metrics: bool = True,  # noqa: B008
                 pose_auc_min_error: float | None = None, skip_nonfinite_loss: bool = True,
                 authors_depth_metrics: bool = True,
                 prior_training: PriorTraining = PriorTraining(),  # noqa: B008
                 authors_pose_metrics: bool = True, init_weights: str | None = None) -> None:
        super().__init__()
        # settings arrive as dataclasses (CLI, Python) or as plain mappings (a checkpoint's hyper-parameters)
        self.net_config: DAPMConfig = _as_config(net, DAPMConfig)
        self.loss_config: LossConfig = _as_config(loss, LossConfig)
        self.optimizer_config: OptimizerConfig = _as_config(optimizer, OptimizerConfig)
        self.prior_training: PriorTraining = _as_config(prior_training, PriorTraining)
        if init_weights is not None:  # every weight comes from that file: no ImageNet download first
            self.net_config = replace(self.net_config, pretrained=False, weights_path=None)
        self.save_hyperparameters({  # plain values: checkpoints load with weights_only=True
            "net": self.net_config.to_dict(), "loss": {**asdict(self.loss_config),
                                                        "weights": dict(self.loss_config.weights)},
            "optimizer": {**asdict(self.optimizer_config), "betas": list(self.optimizer_config.betas)},
            "log_space_metrics": log_space_metrics, "pose_auc_min_error": pose_auc_min_error,
            "skip_nonfinite_loss": skip_nonfinite_loss, "authors_depth_metrics": authors_depth_metrics,
            "prior_training": {**asdict(self.prior_training), "noise": list(self.prior_training.noise)},
            "authors_pose_metrics": authors_pose_metrics, "init_weights": init_weights})
        self.init_weights = init_weights
        self.weights_are_final = False
        """True once the weights came from ``init_weights`` or a checkpoint: ``init_weights`` is not read (again)."""
        self.igd_predicted_share = 1.0
        self.skip_nonfinite_loss = skip_nonfinite_loss
        self.configure_models()
        self.configure_losses()
        self.configure_metrics(log_space_metrics, authors_depth_metrics, pose_auc_min_error, authors_pose_metrics)
        self.nonfinite_steps = 0
        self._training_rng_states: dict[str, Any] | None = None
        """RNG states of the training stream while a validation inside a fit runs (:meth:`on_validation_start`)."""
        self.sigterm = SigtermAgreement()
        """SIGTERM and Ctrl-C acted on by every process after the same optimizer step (:mod:`.signals`)."""
        self.train_image_size: tuple[int, int] | None = None
        """``(H, W)`` of the training images (saved in checkpoints; inference runs at the same pixel count)."""
        self.eval_losses: dict[str, tuple[dict[str, Tensor], int]] = {}
        """Per evaluation stage: ``({key: sum of loss x batch size}, images)`` of this process, logged at the
        epoch's end (:meth:`_log_metrics`)."""

    def configure_models(self) -> None:
        """The network, :attr:`net`, from ``net``."""
        self.net = DAPMNet(self.net_config)

    def configure_losses(self) -> None:
        """The training objective (Eq. 16-19), :attr:`criterion`, from ``loss`` and the network's IGD settings."""
        self.criterion = DAPMLoss(self.loss_config, self.net_config.igd)

    def configure_metrics(self, log_space_metrics: bool, authors_depth_metrics: bool,
                          pose_auc_min_error: float | None, authors_pose_metrics: bool) -> None:
        """Validation and test metrics, :attr:`metrics`, named ``<stage>_<kind>``, for the branches the network has."""
        max_depth = self.net_config.igd.max_depth
        self.metrics = torch.nn.ModuleDict()
        for stage in ("val", "test"):
            if self.net_config.use_depth:
                self.metrics[f"{stage}_depth"] = DepthMetrics(max_depth=max_depth)
                if log_space_metrics:
                    self.metrics[f"{stage}_depthlog"] = DepthMetrics(max_depth=max_depth, space="uapd_log")
                if authors_depth_metrics:
                    self.metrics[f"{stage}_depthauthors"] = AuthorsDepthMetrics(max_depth=max_depth)
            if self.net_config.use_pose:
                self.metrics[f"{stage}_pose"] = PoseMetrics(min_error=pose_auc_min_error)
                if authors_pose_metrics:
                    self.metrics[f"{stage}_poseauthors"] = AuthorsPoseMetrics()

    def on_fit_start(self) -> None:
        if self.init_weights is not None and not self.weights_are_final:  # Python use without load_initial_weights
            if self.trainer.strategy.restore_checkpoint_after_setup:
                raise ValueError(f"model.init_weights: the {type(self.trainer.strategy).__name__} strategy shards the "
                                 "weights before this point. Fix: call load_initial_weights() before trainer.fit "
                                 "(dapm-lightning fit does)")
            self.load_initial_weights()

    def load_initial_weights(self) -> None:
        """Copy the network weights of the checkpoint ``init_weights`` into this module.

        Raises:
            ValueError: the checkpoint's network has another architecture (every difference listed), or it is
                not a dapm-lightning checkpoint.
            FileNotFoundError, CheckpointReadError: as :func:`~.checkpoint_files.read_checkpoint`.
        """
        path = self.init_weights
        if path is None:
            raise ValueError("load_initial_weights: model.init_weights is not set")
        checkpoint = read_checkpoint(path)
        check_dapm_checkpoint(checkpoint, path)
        self.net_config.check_loads(checkpoint["hyper_parameters"]["net"], f"{path} (model.init_weights)")
        weights = {k.removeprefix("net."): v for k, v in checkpoint["state_dict"].items() if k.startswith("net.")}
        self.net.load_state_dict(weights, strict=True)  # copied into this module's tensors, in their dtype
        if self.train_image_size is None:  # predict's network size until a fit sets its own
            self.train_image_size = training_image_size(checkpoint)
        self.weights_are_final = True
        rank_zero_info(f"model.init_weights: the network starts from {path} ({len(weights)} tensors)")

    def setup(self, stage: str) -> None:
        self.check_data_agrees(getattr(self._trainer, "datamodule", None) if self._trainer is not None else None)

    def check_data_agrees(self, datamodule: Any, checkpoint: str | None = None) -> None:
        """Raise a ValueError with the fix when ``datamodule``'s depth kind or depth limit is not the network's.

        ``checkpoint``: where the network's settings came from (``--ckpt_path``); its settings cannot be changed,
        so the fix is then the data's, or another checkpoint.
        """
        data_kind = getattr(datamodule, "depth_kind", None)
        model_kind = self.net_config.igd.depth_kind
        if data_kind is not None and data_kind != model_kind and self.net_config.use_pose:
            fix = (f"the network of {checkpoint} was trained for {model_kind} depth and keeps it: give it data of "
                   f"{model_kind} depth (data.init_args.depth_kind: {model_kind}, if the files hold it), or train "
                   f"one with model.net.igd.depth_kind: {data_kind}" if checkpoint else
                   f"set model.net.igd.depth_kind: {data_kind} (or fix data.init_args.depth_kind)")
            raise ValueError(f"the data holds {data_kind} depth but the model's IGD computes {model_kind} depth: {fix}")
        data_limit, model_limit = getattr(datamodule, "max_depth", None), self.net_config.igd.max_depth
        if data_limit is not None and data_limit != model_limit:
            fix = (f"the network of {checkpoint} keeps its {model_limit:g} m: give the data its files' own limit "
                   f"(data.init_args.max_depth: {model_limit:g}, if they encode that), or train one with "
                   f"model.net.igd.max_depth: {data_limit:g}" if checkpoint else
                   f"set model.net.igd.max_depth: {data_limit:g} (or fix data.init_args.max_depth)")
            raise ValueError(f"the data's depth PNGs encode depth up to {data_limit:g} m (grey 255) but the model's "
                             f"limit is {model_limit:g} m: {fix}")

    def forward(self, image: Tensor, prior: PosePrior | None = None) -> DAPMOutput:
        """``image [B, 3, H, W]`` (uint8 or float in [0, 1]) -> :class:`DAPMOutput` (predictions only).

        ``prior``: known pose components (telemetry), see :class:`~dapm_lightning.models.prior.PosePrior`.
        """
        return self.net(unit_image(image), prior=prior)

    def _shared_step(self, batch: dict[str, Any], stage: Stage) -> tuple[Tensor, DAPMOutput]:
        image = unit_image(batch["image"])
        teacher_forcing = None
        if stage == "train" and self.igd_predicted_share < 1.0:
            teacher_forcing = TeacherForcing(self.net_config.igd.normalize(batch["pose"]), self.igd_predicted_share)
        prior = None
        if stage == "train":
            names = batch.get("name") or [str(k) for k in range(image.shape[0])]
            prior = self.prior_training.sample(batch["pose"], batch["has_pose"], names, self.current_epoch)
        out = self.net(image, teacher_forcing, prior)
        sky, valid = depth_masks(batch["depth"], self.net_config.igd.max_depth)
        terms = self.criterion(out, {**batch, "sky": sky, "valid": valid})
        batch_size = image.shape[0]
        named = {f"{stage}_loss_{k}": v.detach() for k, v in terms.items() if k != "total"}
        if stage != "train":  # the mean over the epoch's images, logged at its end (_log_metrics)
            sums, images = self.eval_losses.get(stage, ({}, 0))
            for key, value in {**named, f"{stage}_loss": terms["total"].detach()}.items():
                sums[key] = sums.get(key, 0.0) + value * batch_size
            self.eval_losses[stage] = (sums, images + batch_size)
        else:  # each step's values as they are (NaN included); the epoch's mean over the steps whose loss is finite
            # (a non-finite step, skipped by default, weighs 0): <key>_step and <key>_epoch, as Lightning names a value
            # logged on both; sync_dist: epoch-level values are the mean over all processes
            finite = bool(torch.isfinite(terms["total"]))
            for key, value in {**named, "train_loss": terms["total"].detach()}.items():
                self.log(f"{key}_step", value, batch_size=batch_size, prog_bar=key == "train_loss", on_step=True,
                         on_epoch=False, sync_dist=True)
                self.log(f"{key}_epoch", value if finite else torch.zeros_like(value), prog_bar=key == "train_loss",
                         batch_size=batch_size if finite else 0, on_step=False, on_epoch=True, sync_dist=True)
        if stage != "train":
            self._update_metrics(out, batch, stage)
        return terms["total"], out

    def _stage_metrics(self, stage: str, kinds: tuple[str, ...]) -> list[Metric]:
        """The metrics of ``stage`` among ``kinds`` that this module has."""
        return [cast(Metric, self.metrics[f"{stage}_{kind}"]) for kind in kinds if f"{stage}_{kind}" in self.metrics]

    def _update_metrics(self, out: DAPMOutput, batch: dict[str, Any], stage: str) -> None:
        if out.depth_m is not None:
            for metric in self._stage_metrics(stage, ("depth", "depthlog", "depthauthors")):
                metric.update(out.depth_m, batch["depth"])
        has_pose = batch["has_pose"]
        if out.pose_physical is not None and has_pose.any():
            for metric in self._stage_metrics(stage, ("pose", "poseauthors")):
                metric.update(out.pose_physical[has_pose], batch["pose"][has_pose])

    def _log_metrics(self, stage: str) -> None:
        """Log the epoch's losses (means over its images) and metrics, figures of all processes' images.

        Under DDP a process may have fewer images than another, or none (fewer images than processes): every
        process logs the same keys in the same order (their collectives pair up), and one without images adds
        nothing. A metric that no process updated (no image with a pose) is left out, as with one process.
        Every value is then the same on every rank, so the mean that ``sync_dist`` takes is that value (and
        Lightning does not warn about unsynced epoch-level logs).
        """
        sums, images = self.eval_losses.pop(stage, ({}, 0))
        metrics = {name: cast(Metric, m) for name, m in self.metrics.items() if name.startswith(stage + "_")}
        names, updated = list(sums), {name for name, metric in metrics.items() if metric.update_called}
        distributed = self._trainer is not None and is_distributed(self.trainer)
        if distributed:
            parts: list[Any] = [None] * self.trainer.world_size
            dist.all_gather_object(parts, (names, updated))
            names = max((part[0] for part in parts), key=len)  # [] from a process without images
            updated = set().union(*(part[1] for part in parts))
        if names:
            zero = torch.zeros((), device=self.device)
            totals = torch.stack([*(sums.get(key, zero) for key in names), zero + images])
            if distributed:
                dist.all_reduce(totals)
            means = dict(zip(names, totals[:-1] / totals[-1]))
            total = means.pop(f"{stage}_loss")
            self.log_dict(means, sync_dist=True)
            self.log(f"{stage}_loss", total, prog_bar=True, sync_dist=True)
        for name, metric in metrics.items():
            if name in updated:
                with warnings.catch_warnings():  # compute() on a process without images: its sync is still due
                    warnings.filterwarnings("ignore", "The ``compute`` method of metric", UserWarning)
                    values = metric.compute()  # reduced over processes
                # on the module's device: NCCL, the backend of multi-GPU runs, reduces no CPU tensor
                self.log_dict({f"{name}_{k}": v.to(self.device) for k, v in values.items()}, sync_dist=True)
                metric.reset()

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> Tensor | None:
        self.train_image_size = (int(batch["image"].shape[-2]), int(batch["image"].shape[-1]))
        loss, _ = self._shared_step(batch, "train")
        if not self.skip_nonfinite_loss:
            return loss
        finite = bool(torch.isfinite(loss))
        distributed = is_distributed(self.trainer)
        everywhere = finite
        if distributed:  # every process decides alike: the step, the count and its log are the whole job's
            flag = torch.tensor([int(finite)], device=loss.device)
            dist.all_reduce(flag, op=dist.ReduceOp.MIN)
            everywhere = bool(flag.item())
        if everywhere:
            return loss
        self.nonfinite_steps += 1
        if not finite:  # the process whose batch it was names its files (under DDP, maybe not rank 0)
            names = ", ".join(batch.get("name", [])[:8])
            where = f"process {self.trainer.global_rank}, " if distributed else ""
            done = ("a zero-gradient step on every process (AdamW's momentum and weight decay still apply)"
                    if distributed else "step skipped, weights unchanged")
            warnings.warn(f"non-finite training loss at step {self.global_step} ({where}batch {batch_idx}: {names}); "
                          f"{done} ({self.nonfinite_steps} so far)", UserWarning, stacklevel=2)
        self.log("train_nonfinite_steps", float(self.nonfinite_steps), on_step=True, on_epoch=False, batch_size=1)
        if distributed:  # every process must run backward under DDP: a zero-gradient step, on every process
            return sum((p.sum() * 0.0 for p in self.parameters() if p.requires_grad), torch.zeros(()))
        return None  # Lightning skips backward and the optimiser step

    def on_sanity_check_start(self) -> None:
        """SIGTERM and Ctrl-C acted on between optimizer steps from here on (:class:`~.signals.SigtermAgreement`)."""
        self.sigterm.install(self.trainer)

    def on_train_start(self) -> None:
        """As :meth:`on_sanity_check_start`, for runs without a sanity check.

        A resumed run's next epoch then starts as any other
        (:func:`~dapm_lightning.training.resume.start_next_epoch_as_any_other`), and the restored epoch counts the
        batches the data module's loader resumes after, also on another number of processes
        (:func:`~dapm_lightning.training.resume.count_batches_as_resumed`).
        """
        self.sigterm.install(self.trainer)
        fit_loop = self.trainer.fit_loop
        start_next_epoch_as_any_other(fit_loop)
        resumed_at = getattr(getattr(self.trainer, "datamodule", None), "resumed_at", None)  # a DAPMDataModule's
        if resumed_at is not None:
            count_batches_as_resumed(fit_loop, *resumed_at)

    def on_train_batch_end(self, outputs: Any, batch: Any, batch_idx: int) -> None:
        """On SIGTERM or Ctrl-C to any process, all stop after this batch's optimizer step (or its validation)."""
        self.sigterm.agree(self.trainer)

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Add the training image size, the skipped steps' count, the training RNG states and exact loop counters.

        The RNG states are those of the training stream: during a validation inside a fit, those saved when
        it started (:meth:`on_validation_start`). Loop counters that Lightning would resume in the wrong epoch
        (a save after the epoch loop stopped: ``on_train_end`` after ``max_steps``, ``on_train_epoch_end``, a
        SIGTERM at the end of an epoch) become those of a save right after the last training batch
        (:func:`~dapm_lightning.training.resume.resume_after_last_batch`).
        """
        if self.train_image_size is not None:
            checkpoint["dapm_train_image_size"] = list(self.train_image_size)
        checkpoint["dapm_nonfinite_steps"] = self.nonfinite_steps  # rank 0's count, as its warning says
        fit_loop = checkpoint.get("loops", {}).get("fit_loop")
        if fit_loop is not None and self._trainer is not None and self.trainer.state.fn == TrainerFn.FITTING:
            resume_after_last_batch(fit_loop)
        states = self._training_rng_states if self._training_rng_states is not None else rng_states()
        # every process saves (Lightning calls this hook on all ranks, rank 0 writes): under DDP the RNG
        # states of all ranks are gathered, so that each resumes its own dropout and augmentation draws
        if self._trainer is not None and self.trainer.world_size > 1:
            packed = pack_rng_states(states)
            checkpoint["dapm_rng_states_per_rank"] = {k: cast(Tensor, self.all_gather(v)).cpu()
                                                      for k, v in packed.items()}
        else:
            checkpoint["dapm_rng_states"] = states

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        self.weights_are_final = True  # a resume, load_from_checkpoint: init_weights is not read over them
        saved = checkpoint.get("hyper_parameters", {}).get("net")
        if saved is not None:
            self.net_config.check_loads(saved, "the checkpoint")
        self.train_image_size = training_image_size(checkpoint)
        if self._trainer is None:
            return
        if self.trainer.state.fn == TrainerFn.FITTING:  # the best model stays the best across a resume
            self.nonfinite_steps = int(checkpoint.get("dapm_nonfinite_steps", 0))  # "N so far" counts the whole run
            roots = [self.trainer.default_root_dir, *(getattr(log, "save_dir", None) for log in self.trainer.loggers)]
            keep_checkpoint_rankings(checkpoint, self.trainer.checkpoint_callbacks, roots)
        else:  # validate, test, predict save no checkpoint: the fit's rankings are not restored (nor warned about)
            states = checkpoint.get("callbacks") or {}
            for callback in self.trainer.checkpoint_callbacks:
                for key in (getattr(callback, "state_key", None), getattr(callback, "_legacy_state_key", None)):
                    states.pop(key, None)
        per_rank = checkpoint.get("dapm_rng_states_per_rank")
        if per_rank is not None:  # saved under DDP: [world size, ...] per state
            saved_ranks = per_rank["torch"].shape[0]
            rank = self.trainer.global_rank % saved_ranks  # same process count: each rank its own states
            # clone: a row of the gathered tensor is a view with a storage offset, which set_rng_state misreads
            set_rng_states(unpack_rng_states({k: v[rank].clone() for k, v in per_rank.items()}))
        elif "dapm_rng_states" in checkpoint:
            set_rng_states(checkpoint["dapm_rng_states"])  # a resumed run draws what the uninterrupted one would

    def on_validation_start(self) -> None:
        """During a fit, keep the RNG states of the training stream (see :meth:`on_validation_end`).

        Under DDP, also sync the buffers (rank 0's batch-norm statistics) here, on every process, where DDP would
        have the first validation forward sync them: a process without a validation batch (fewer images than
        processes) would never join that collective, and the others would wait for it.
        """
        if self._trainer is not None and self.trainer.state.fn == TrainerFn.FITTING:
            self._training_rng_states = rng_states()
            wrapper = self.trainer.strategy.model
            if isinstance(wrapper, DistributedDataParallel):
                if wrapper.will_sync_module_buffers():  # type: ignore[no-untyped-call]
                    wrapper._sync_buffers()  # type: ignore[no-untyped-call]
                wrapper.require_forward_param_sync = False  # no validation forward syncs them again

    def on_validation_end(self) -> None:
        """Give training back the RNG states it had when the validation started; then stop on SIGTERM or Ctrl-C.

        Whatever a validation draws (a callback, a metric, a data set), training then draws what it would
        have drawn without it: a run resumed from a checkpoint taken before, during or after a validation
        (which the resumed run does not repeat) trains exactly as the uninterrupted one. A stop agreed before the
        validation, or a signal received during it, is handed to Lightning here on every process, once the callbacks
        (the best-model and ``last.ckpt`` saves) have seen the validation
        (:meth:`.signals.SigtermAgreement.after_validation`).
        """
        if self._training_rng_states is not None:
            set_rng_states(self._training_rng_states)
            self._training_rng_states = None
        if self._trainer is not None:
            self.sigterm.after_validation(self.trainer)

    def validation_step(self, batch: dict[str, Any], batch_idx: int) -> DAPMOutput:  # type: ignore[override]
        return self._shared_step(batch, "val")[1]

    def test_step(self, batch: dict[str, Any], batch_idx: int) -> DAPMOutput:  # type: ignore[override]
        return self._shared_step(batch, "test")[1]

    def _start_evaluation(self, stage: str) -> None:
        """Forget what an evaluation of ``stage`` cut short by an error left (its loss sums, its metrics' states)."""
        self.eval_losses.pop(stage, None)
        for name, metric in self.metrics.items():
            if name.startswith(stage + "_"):
                cast(Metric, metric).reset()

    def on_validation_epoch_start(self) -> None:
        self._start_evaluation("val")

    def on_test_epoch_start(self) -> None:
        self._start_evaluation("test")

    def on_validation_epoch_end(self) -> None:
        self._log_metrics("val")

    def on_test_epoch_end(self) -> None:
        self._log_metrics("test")

    def predict_step(self, batch: PredictBatch, batch_idx: int, dataloader_idx: int = 0) -> DAPMOutput:
        """The network's output for a :class:`~dapm_lightning.data.unlabelled.PredictBatch`, given its prior.

        :class:`~dapm_lightning.inference.writers.PredictionWriter` turns it into files.
        """
        return self(batch.images, batch.network_prior)

    @property
    def planned_steps(self) -> int:
        """Training length the step schedules follow: ``optimizer.schedule_steps``, else the trainer's estimate.

        Raises:
            ValueError: neither gives a finite number of steps (``max_epochs: -1`` and no ``max_steps``).
        """
        planned = self.optimizer_config.schedule_steps or self.trainer.estimated_stepping_batches
        if not (math.isfinite(planned) and planned > 0):
            raise ValueError(
                "the learning-rate schedule and the IGD teacher forcing follow the planned training length, but "
                f"this run has no number of steps (trainer.max_epochs: {self.trainer.max_epochs}, trainer.max_steps: "
                f"{self.trainer.max_steps}, or a data set without a length).\nFix: set "
                "model.optimizer.schedule_seconds for a run bounded by trainer.max_time (the schedules then follow "
                "the time), or trainer.max_steps, model.optimizer.schedule_steps or a finite trainer.max_epochs.")
        return int(planned)

    def schedule_progress(self, step: int) -> float:
        """Share of the planned training done at optimiser step ``step``, which the IGD teacher forcing follows.

        With ``optimizer.schedule_seconds``: the share of that time spent, as the learning rate counts it; else
        ``step`` of :attr:`planned_steps`.
        """
        if self.optimizer_config.schedule_seconds is not None:
            scheduler = self.lr_schedulers()
            if isinstance(scheduler, TimeBudgetLR):
                return scheduler.ticks / scheduler.TICKS
        return step / self.planned_steps

    def configure_optimizers(self) -> OptimizerLRSchedulerConfig:
        config = self.optimizer_config
        optimizer = torch.optim.AdamW(self.parameters(), lr=config.lr, betas=config.betas,
                                      weight_decay=config.weight_decay)
        scheduler: torch.optim.lr_scheduler.LambdaLR
        if config.schedule_seconds is not None:
            scheduler = TimeBudgetLR(optimizer, config.schedule_seconds, config.warmup_fraction, config.min_lr_ratio)
        else:
            total = self.planned_steps
            scheduler = torch.optim.lr_scheduler.LambdaLR(
                optimizer, lambda step: warmup_cosine(step, total, config.warmup_fraction, config.min_lr_ratio))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    def lr_scheduler_step(self, scheduler: LRSchedulerTypeUnion, metric: Any | None) -> None:
        """Step ``scheduler``; a :class:`TimeBudgetLR` first reads the time, the latest among the processes."""
        if isinstance(scheduler, TimeBudgetLR):
            scheduler.read_clock(self._latest_among_processes)
        super().lr_scheduler_step(scheduler, metric)

    def _latest_among_processes(self, seconds: float) -> float:
        """The largest of the processes' ``seconds`` (under DDP one all-reduce of a scalar), the same on each."""
        if not (dist.is_available() and dist.is_initialized()) or self.trainer.world_size == 1:
            return seconds
        latest = torch.tensor(seconds, dtype=torch.float64, device=self.trainer.strategy.root_device)
        dist.all_reduce(latest, op=dist.ReduceOp.MAX)
        return float(latest.item())


__all__ = ["DAPMModule", "OptimizerConfig", "TimeBudgetLR", "warmup_cosine"]
