"""A model against the baselines on a UAPD-format split, with and without telemetry.

Used by the quickstart (``with_telemetry``) and the leave-one-family-out benchmark (``benchmarks/bench_synth.py
transfer``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from dapm_lightning.data.uapd import UAPDDataset
from dapm_lightning.geometry.constants import MAX_DEPTH_M, MIN_DEPTH_M
from dapm_lightning.geometry.igd import ideal_ground_depth
from dapm_lightning.inference.prior import apply_pose_prior, bound_by_ground
from dapm_lightning.metrics import DepthMetrics, PoseMetrics
from dapm_lightning.models.prior import IGD_BOUND_MARGIN, PosePrior, PriorMode

TELEMETRY_SUBSETS = {"full": (True, True, True, True), "height": (True, False, False, False),
                     "gravity": (False, True, True, False), "fov": (False, False, False, True)}
"""Which pose components the telemetry rows know: all, the height, pitch and roll, the FoV."""
TELEMETRY_NOISE = (3.0, 1.0, 1.0, 2.0)
"""Telemetry noise of the evaluation, also the σ the model is told: height 3 m, angles 1°, FoV 2°."""
TELEMETRY_ROWS = tuple(f"{subset}/{mode}" for subset in TELEMETRY_SUBSETS for mode in ("cond", "scale"))
BOUNDED_SUBSETS = ("full", "height")
"""The subsets that give the height, where the IGD bound applies (rows ``SUBSET/cond+bound``)."""
TELEMETRY_IGD_ROW = "full/igd"
"""The IGD of the noisy full telemetry alone (no network): what a model given that telemetry must beat."""
GROUND_TOLERANCE = 0.03
"""A pixel is flat ground when its true depth is within 3 % (about one 8-bit grey level) of the true pose's IGD."""


def bound_row(subset: str, margin: float) -> str:
    """A bounded row's name: ``SUBSET/cond+bound`` at the default margin, ``SUBSET/cond+bound@MARGIN`` else."""
    return f"{subset}/cond+bound" + ("" if margin == IGD_BOUND_MARGIN else f"@{margin:g}")


def bound_rows(margins: tuple[float, ...]) -> list[str]:
    """Names of the bounded rows of every subset that gives the height, at each margin."""
    return [bound_row(subset, m) for subset in BOUNDED_SUBSETS for m in margins]


def median_scaled(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``pred`` times ``median(target) / median(pred)`` per image over the valid pixels (scale-free depth)."""
    scaled = pred.clone()
    for i in range(pred.shape[0]):
        valid = (target[i] > MIN_DEPTH_M) & (target[i] < MAX_DEPTH_M)
        if valid.any():
            scaled[i] = pred[i] * target[i][valid].median() / pred[i][valid].clamp(min=MIN_DEPTH_M).median()
    return scaled


def telemetry_prior(pose: torch.Tensor, subset: str, generator: torch.Generator) -> PosePrior:
    """Noisy telemetry of the true poses ``[B, 4]``: the subset's components known, the rest NaN."""
    sigma = torch.tensor(TELEMETRY_NOISE, dtype=torch.float64)
    noisy = pose + torch.randn(pose.shape, generator=generator, dtype=torch.float64) * sigma
    known = torch.tensor(TELEMETRY_SUBSETS[subset]).expand_as(pose)
    return PosePrior(torch.where(known, noisy, torch.full_like(noisy, float("nan"))).float(), sigma.float())


def scale_errors(pred: torch.Tensor, true: torch.Tensor) -> dict[str, float]:
    """Median relative errors of the height and of the ground footprint ``height * tan(fov / 2)``.

    The footprint is what the image shows directly (at nadir, how many metres the picture spans); the
    height follows from it only with the FoV. ``exp(median |log(pred / true)|) - 1``: 0.25 = off by 25 %.
    """
    def relative(a: torch.Tensor, b: torch.Tensor) -> float:
        return float((a / b).log().abs().median().exp() - 1)

    def footprint(pose: torch.Tensor) -> torch.Tensor:
        return pose[:, 0] * torch.tan(torch.deg2rad(pose[:, 3]) / 2)

    return {"height_rel": relative(pred[:, 0], true[:, 0]), "footprint_rel": relative(footprint(pred), footprint(true))}


class GroundSplit:
    """d1 of one row on the flat-ground pixels and on the others (objects), each per image then averaged.

    Ground: the true depth within :data:`GROUND_TOLERANCE` of the true pose's IGD. Shows whether a row loses on the
    ground it was told about or on what stands on it; keys ``d1_ground``, ``d1_objects``, ``ground_share``.
    """

    def __init__(self) -> None:
        self.ground, self.objects = DepthMetrics(), DepthMetrics()
        self.pixels = [0.0, 0.0]

    def update(self, pred: torch.Tensor, depth: torch.Tensor, ground: torch.Tensor) -> None:
        valid = (depth > MIN_DEPTH_M) & (depth < MAX_DEPTH_M)
        zero = torch.zeros_like(depth)
        self.ground.update(pred, torch.where(ground, depth, zero))
        self.objects.update(pred, torch.where(ground, zero, depth))
        self.pixels[0] += float((valid & ground).sum())
        self.pixels[1] += float(valid.sum())

    def compute(self) -> dict[str, float]:
        return {"d1_ground": float(self.ground.compute()["d1"]), "d1_objects": float(self.objects.compute()["d1"]),
                "ground_share": self.pixels[0] / max(self.pixels[1], 1.0)}


@torch.no_grad()
def evaluate(module: Any, root: Path, mean_pose: torch.Tensor, batch: int = 32,
             telemetry: bool = True, bound_margins: tuple[float, ...] = (IGD_BOUND_MARGIN,)
             ) -> dict[str, dict[str, float]]:
    """Metrics on ``root/val`` per row (depth and pose keys).

    ``module``: a :class:`~dapm_lightning.training.module.DAPMModule` in eval mode, or None (baselines only).
    Rows: ``model``; ``scale_fixed``: the model's depth rescaled per image to the true median (how much
    of the depth error is metric scale); ``mean_pose``: the mean training pose and its IGD (no
    learning); ``true_pose``: the IGD of each image's true pose (what a perfect pose alone gives);
    with ``telemetry``, ``SUBSET/cond`` and ``SUBSET/scale``: the model given noisy telemetry of the
    subset (:data:`TELEMETRY_SUBSETS`, :data:`TELEMETRY_NOISE`) into its IGD feature (conditioning), or
    after it (the depth fitted to the ground of the known pose), see :mod:`dapm_lightning.inference.prior`;
    ``SUBSET/cond+bound``: the conditioned depth capped by the IGD bound (:func:`bound_by_ground`) at each of
    ``bound_margins`` (:func:`bound_rows`).
    """
    data = UAPDDataset(root, "val")
    names = ["model", "scale_fixed", "mean_pose", "true_pose"]
    names += [TELEMETRY_IGD_ROW] if telemetry else []
    names += [*TELEMETRY_ROWS, *bound_rows(bound_margins)] if module is not None and telemetry else []
    metrics = {name: (DepthMetrics(), PoseMetrics()) for name in names}
    splits = {name: GroundSplit() for name in names if name not in ("scale_fixed", "mean_pose")}
    poses: dict[str, list[torch.Tensor]] = {"true": [], "model": [], "mean_pose": []}
    generator = torch.Generator().manual_seed(0)
    for start in range(0, len(data), batch):
        samples = [data[i] for i in range(start, min(start + batch, len(data)))]
        image = torch.stack([s["image"] for s in samples])
        depth = torch.stack([s["depth"] for s in samples])
        pose = torch.stack([s["pose"] for s in samples]).double()
        base = mean_pose[None].expand(len(samples), 4)
        igd = ideal_ground_depth(base, tuple(depth.shape[-2:]), depth_kind="range")
        metrics["mean_pose"][0].update(igd.float(), depth)
        metrics["mean_pose"][1].update(base, pose)
        poses["true"].append(pose)
        poses["mean_pose"].append(base)
        true_igd = ideal_ground_depth(pose, tuple(depth.shape[-2:]), depth_kind="range")
        metrics["true_pose"][0].update(true_igd.float(), depth)
        metrics["true_pose"][1].update(pose, pose)
        ground = ((depth / true_igd.float()) - 1).abs() < GROUND_TOLERANCE
        splits["true_pose"].update(true_igd.float(), depth, ground)
        if telemetry:  # its own draw, so that the rows with a model keep the telemetry they always had
            noisy = telemetry_prior(pose, "full", torch.Generator().manual_seed(start + 1)).value.double()
            noisy_igd = ideal_ground_depth(noisy, tuple(depth.shape[-2:]), depth_kind="range").float()
            metrics[TELEMETRY_IGD_ROW][0].update(noisy_igd, depth)
            metrics[TELEMETRY_IGD_ROW][1].update(noisy, pose)
            splits[TELEMETRY_IGD_ROW].update(noisy_igd, depth, ground)
        if module is not None:
            out = module(image)
            metrics["model"][0].update(out.depth_m.float(), depth)
            splits["model"].update(out.depth_m.float(), depth, ground)
            metrics["model"][1].update(out.pose_physical.double(), pose)
            metrics["scale_fixed"][0].update(median_scaled(out.depth_m.float(), depth), depth)
            metrics["scale_fixed"][1].update(out.pose_physical.double(), pose)
            poses["model"].append(out.pose_physical.double())
            spec = module.net_config.igd
            for subset in TELEMETRY_SUBSETS if telemetry else ():
                prior = telemetry_prior(pose, subset, generator)  # the same telemetry for both ways of using it
                ways: tuple[tuple[str, PriorMode], ...] = (("cond", "condition"), ("scale", "scale"))
                for mode, way in ways:
                    given = (module(image, prior) if mode == "cond" else out).inference_outputs(spread=True)
                    used = apply_pose_prior(given, prior, way, spec).output
                    row = f"{subset}/{mode}"
                    metrics[row][0].update(used.depth_m.float(), depth)
                    splits[row].update(used.depth_m.float(), depth, ground)
                    metrics[row][1].update(used.pose.double(), pose)
                    poses.setdefault(row, []).append(used.pose.double())
                    for margin in bound_margins if mode == "cond" and subset in BOUNDED_SUBSETS else ():
                        capped = bound_by_ground(used, prior, spec, margin)
                        metrics[bound_row(subset, margin)][0].update(capped.depth_m.float(), depth)
                        splits[bound_row(subset, margin)].update(capped.depth_m.float(), depth, ground)
                        metrics[bound_row(subset, margin)][1].update(capped.pose.double(), pose)
    result = {}
    for name, (depth_m, pose_m) in metrics.items():
        if name in ("model", "scale_fixed") and module is None:
            continue
        result[name] = {**{k: float(v) for k, v in depth_m.compute().items()},
                        **{k: float(v) for k, v in pose_m.compute().items()}}
        if poses.get(name):
            result[name].update(scale_errors(torch.cat(poses[name]), torch.cat(poses["true"])))
        if name in splits:
            result[name].update(splits[name].compute())
    return result


__all__ = ["BOUNDED_SUBSETS", "GROUND_TOLERANCE", "TELEMETRY_IGD_ROW", "TELEMETRY_NOISE", "TELEMETRY_ROWS",
           "TELEMETRY_SUBSETS", "GroundSplit", "bound_row", "bound_rows", "evaluate", "median_scaled", "scale_errors",
           "telemetry_prior"]
