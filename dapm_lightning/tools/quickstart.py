"""The README's main job: synthetic data -> train a small DAPM on the CPU -> test -> metrics vs baselines -> pictures.

``python -m dapm_lightning.tools.quickstart --out outputs/quickstart`` (what ``make demo`` runs).
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from pathlib import Path

import torch

from dapm_lightning.data.uapd import UAPDDataset
from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.geometry.igd import ideal_ground_depth
from dapm_lightning.metrics import DepthMetrics, PoseMetrics
from dapm_lightning.tools.evaluate import evaluate
from dapm_lightning.training.checkpointing import best_or_last_checkpoint, load_dapm_module
from dapm_lightning.training.lightning_cli import run_lightning_cli

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "quickstart.yaml"
ROWS = [("depth", "d1", "higher"), ("depth", "abs_rel", "lower"), ("depth", "rmse", "lower"),
        *[("pose", f"{c}_median", "lower") for c in POSE_KEYS],
        *[("pose", f"{c}_auc5", "higher") for c in POSE_KEYS]]
"""(group, metric, better) rows of the report; the model must beat both baselines on d1, abs_rel and every median."""


def baselines(root: Path, depth_kind: str = "range") -> dict[str, dict[str, float]]:
    """Mean training pose (pose baseline) and the IGD of that pose (depth baseline) on the val split."""
    train, val = UAPDDataset(root, "train"), UAPDDataset(root, "val")
    mean_pose = torch.from_numpy(train.poses.mean(axis=0))
    depth_metrics, pose_metrics = DepthMetrics(), PoseMetrics()
    for i in range(len(val)):
        sample = val[i]
        size = (sample["depth"].shape[-2], sample["depth"].shape[-1])
        igd = ideal_ground_depth(mean_pose[None], size, depth_kind=depth_kind)  # type: ignore[arg-type]
        depth_metrics.update(igd, sample["depth"][None])
        pose_metrics.update(mean_pose[None], sample["pose"][None])
    return {"depth": {k: float(v) for k, v in depth_metrics.compute().items()},
            "pose": {k: float(v) for k, v in pose_metrics.compute().items()},
            "mean_pose": {"pose": mean_pose.tolist()}}


def with_telemetry(checkpoint: str, root: Path) -> dict[str, dict[str, float]]:
    """The model on the validation images given their full telemetry, as ``predict --telemetry`` uses it.

    Telemetry with noise (height 3 m, angles 1°, FoV 2°) through the network's IGD, and the IGD bound at its
    default margin; returns the depth metrics and those of the pose used.
    """
    module = load_dapm_module(checkpoint).eval()
    rows = evaluate(module, root, torch.zeros(4, dtype=torch.float64), telemetry=True)["full/cond+bound"]
    return {"depth": {k: v for k, v in rows.items() if k in ("d1", "d2", "d3", "abs_rel", "rmse", "sq_rel")},
            "pose": {k: v for k, v in rows.items() if k.startswith(("height_", "pitch_", "roll_", "fov_"))}}


def report(model: dict[str, dict[str, float]], base: dict[str, dict[str, float]],
           telemetry: dict[str, dict[str, float]] | None = None) -> tuple[str, list[str]]:
    """A table of the model against the baselines, and the rows where it does not beat them.

    ``telemetry``: a last column, the model given telemetry (:func:`with_telemetry`).
    """
    extra = f"{'+telem.':>9}" if telemetry else ""
    lines = [f"{'metric':<26}{'DAPM':>9}{'baseline':>10}{'ratio':>8}{extra}", "-" * (53 + len(extra))]
    failures = []
    for group, name, better in ROWS:
        ours, theirs = model[group].get(name, math.nan), base[group].get(name, math.nan)
        unit = {"height_median": " [m]", "rmse": " [m]"}.get(name, " [deg]" if "median" in name else "")
        arrow = " ↑" if better == "higher" else " ↓"
        beaten = ours > theirs if better == "higher" else ours < theirs
        gain = (ours / theirs if better == "higher" else theirs / ours) if ours and theirs else math.nan
        given = f"{telemetry[group].get(name, math.nan):>9.3f}" if telemetry else ""
        lines.append(f"{group + ' ' + name + unit + arrow:<26}{ours:>9.3f}{theirs:>10.3f}{gain:>7.1f}x{given}")
        if not beaten and (name in ("d1", "abs_rel") or name.endswith("_median")):
            failures.append(f"{group} {name}")
    return "\n".join(lines), failures


def main(argv: list[str] | None = None) -> int:
    """Run the quickstart; returns 0 when the model beats both baselines where it must."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("outputs/quickstart"), help="output folder")
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    parser.add_argument("--data-root", type=Path, default=None, help="synthetic data cache (default OUT/data)")
    parser.add_argument("--max-epochs", type=int, default=None, help="override the config's trainer.max_epochs")
    parser.add_argument("--train-size", type=int, default=None, help="override the synthetic training set size")
    args = parser.parse_args(argv)
    warnings.filterwarnings("ignore", message="LightningCLI's args parameter")  # we call the CLI from Python
    warnings.filterwarnings("ignore", message=".*treespec, LeafSpec.*")
    start = time.time()
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    data_root = (args.data_root or out / "data").resolve()
    overrides = out / "quickstart_overrides.yaml"
    overrides.write_text(json.dumps({  # the config's loggers have no save_dir: they follow default_root_dir
        "trainer": {"default_root_dir": str(out)}, "data": {"init_args": {"root": str(data_root)}}}, indent=2))
    common = ["--config", str(args.config), "--config", str(overrides)]
    if args.train_size:
        common += ["--data.init_args.train_size", str(args.train_size)]
    fit_args = ["fit", *common] + (["--trainer.max_epochs", str(args.max_epochs)] if args.max_epochs else [])
    print(f"[1/3] synthetic UAPD-format data in {data_root} (rendered on first use), then training on the CPU")
    fit = run_lightning_cli(fit_args)
    best = best_or_last_checkpoint(fit.trainer)
    print(f"[2/3] testing {best}")
    test = run_lightning_cli(["test", *common, "--ckpt_path", best])
    metrics = {k: float(v) for k, v in test.trainer.callback_metrics.items()}
    model = {"depth": {k[len("test_depth_"):]: v for k, v in metrics.items() if k.startswith("test_depth_")},
             "pose": {k[len("test_pose_"):]: v for k, v in metrics.items() if k.startswith("test_pose_")}}
    print("[3/3] baselines on the same validation images")
    base = baselines(data_root)
    telemetry = with_telemetry(best, data_root)
    table, failures = report(model, base, telemetry)
    panels = sorted(out.rglob("panels/*.png"))
    figures = sorted(out.rglob("viewpoints.png"))
    summary = {"model": model, "baselines": base, "with_telemetry": telemetry, "checkpoint": best,
               "minutes": (time.time() - start) / 60,
               "beats_baselines": not failures, "not_beaten": failures,
               "depth_log_space": {k[len("test_depthlog_"):]: v for k, v in metrics.items()
                                   if k.startswith("test_depthlog_")}}
    (out / "metrics.json").write_text(json.dumps(summary, indent=2) + "\n")
    print("\nDAPM vs baselines on the validation images (depth in metres; one 8-bit grey level of the")
    print("ground truth is a factor of ~1.027 in depth). Baselines: depth = IGD of the mean training pose,")
    print("pose = the mean training pose. ratio > 1: the model is better by that factor. +telem.: the model")
    print("given each image's telemetry (height, pitch, roll, FoV with noise of 3 m, 1 deg, 1 deg, 2 deg) through")
    print("its IGD: the pose used and the depth it gives (docs/predict.md, Telemetry).\n")
    print(table)
    print("\n" + ("The trained model beats both baselines on depth d1, AbsRel and every pose median."
                  if not failures else f"NOT beaten: {', '.join(failures)}"))
    print(f"\nOutputs in {out}:")
    print("  metrics.json       all figures above (and the paper's 8-bit log-space depth metrics)")
    for figure in figures[-1:]:
        print(f"  {figure.relative_to(out)}  d1 and pose error per bin of pitch, height, roll, FoV")
    folders = sorted({str(p.parent.relative_to(out)) for p in panels})
    print(f"  {', '.join(folders) or 'panels'}: {len(panels)} picture(s): "
          "RGB | true depth | predicted | IGD of predicted pose | error")
    print("  tensorboard/, csv/ logs of the fit (version_0) and test (version_1) runs; checkpoints in "
          "tensorboard/version_0/checkpoints")
    print(f"Took {(time.time() - start) / 60:.1f} min.")
    return 0 if not failures else 1


if __name__ == "__main__":
    raise SystemExit(main())


__all__ = ["baselines", "main", "report", "with_telemetry"]
