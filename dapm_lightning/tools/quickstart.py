"""The README's main job: synthetic data -> train a small DAPM on the CPU -> test -> metrics vs baselines -> pictures.

``python -m dapm_lightning.tools.quickstart --out outputs/quickstart`` (what ``make demo`` runs). With
``--checkpoint PATH`` (``make demo CKPT=PATH``) nothing is trained: the checkpoint (a file or a split checkpoint folder
such as ``models/dapm-synthetic-r18-256``) is tested on freshly rendered images at its training size instead.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path

import cv2
import torch

from dapm_lightning.data.synthetic.generate import generate_uapd, is_current
from dapm_lightning.data.uapd import UAPDDataset
from dapm_lightning.geometry.constants import POSE_KEYS
from dapm_lightning.geometry.igd import ideal_ground_depth
from dapm_lightning.metrics import DepthMetrics, PoseMetrics
from dapm_lightning.tools.argv import whole_number
from dapm_lightning.tools.errors import debug_requested, run_reporting_errors
from dapm_lightning.tools.evaluate import evaluate
from dapm_lightning.training.checkpoint_files import is_remote, local_path, read_checkpoint, split_checkpoint_card
from dapm_lightning.training.checkpointing import best_or_last_checkpoint, load_dapm_module
from dapm_lightning.training.lightning_cli import run_lightning_cli
from dapm_lightning.training.module import training_image_size
from dapm_lightning.training.visualize import depth_panel

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
    return _grouped(evaluate(module, root, torch.zeros(4, dtype=torch.float64), telemetry=True)["full/cond+bound"])


def _grouped(row: dict[str, float]) -> dict[str, dict[str, float]]:
    """One row of :func:`~dapm_lightning.tools.evaluate.evaluate` as ``{"depth": ..., "pose": ...}``."""
    return {"depth": {k: v for k, v in row.items() if k in ("d1", "d2", "d3", "abs_rel", "rmse", "sq_rel")},
            "pose": {k: v for k, v in row.items() if k.startswith(("height_", "pitch_", "roll_", "fov_"))}}


def evaluate_checkpoint(checkpoint: str, root: Path, out: Path, mean_pose: torch.Tensor, panel_images: int = 4
                        ) -> tuple[dict[str, dict[str, float]], dict[str, dict[str, float]], Path]:
    """A trained checkpoint on ``root/val`` without training: its own figures, those given telemetry, a panel.

    The figures are the test's (:func:`~dapm_lightning.tools.evaluate.evaluate`'s ``model`` row: the same depth and
    pose metrics on the same images) and :func:`with_telemetry`'s; the panel of the first ``panel_images`` images
    (RGB | true depth | predicted | IGD of the predicted pose | error) is written to ``out/panels/test_val.png``.
    """
    module = load_dapm_module(checkpoint).eval()
    with torch.no_grad():
        rows = evaluate(module, root, mean_pose, telemetry=True)
        samples = [UAPDDataset(root, "val")[i] for i in range(panel_images)]
        image = torch.stack([s["image"] for s in samples])
        panel = depth_panel(image, torch.stack([s["depth"] for s in samples]), module(image), panel_images,
                            module.net_config.igd)
    path = out / "panels" / "test_val.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(panel, cv2.COLOR_RGB2BGR)):
        raise OSError(f"{path}: could not write the panel")
    return _grouped(rows["model"]), _grouped(rows["full/cond+bound"]), path


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
        ratio = f"{gain:>7.1f}x" if math.isfinite(gain) else f"{'-':>8}"  # a zero (or missing) figure: no ratio
        lines.append(f"{group + ' ' + name + unit + arrow:<26}{ours:>9.3f}{theirs:>10.3f}{ratio}{given}")
        if not beaten and (name in ("d1", "abs_rel") or name.endswith("_median")):
            failures.append(f"{group} {name}")
    return "\n".join(lines), failures


def outputs_listing(out: Path, fit_dir: Path, test_dir: Path, checkpoint: Path) -> list[str]:
    """The lines naming this run's outputs under ``out``: its log folders, panels, viewpoint figure and checkpoint.

    A second run in the same ``out`` logs to new ``version_N`` folders beside the first's; only its own are named.
    """
    def shown(path: Path) -> str:
        return str(path.relative_to(out)) if path.is_relative_to(out) else str(path)

    lines = ["  metrics.json       all figures above (and depth metrics on the 8-bit log encoding's grey levels)"]
    if (test_dir / "viewpoints.png").is_file():
        lines.append(f"  {shown(test_dir / 'viewpoints.png')}  d1 and pose error per bin of pitch, height, roll, FoV")
    panels = [p for run in (fit_dir, test_dir) for p in sorted(run.glob("panels/*.png"))]
    if panels:
        folders = list(dict.fromkeys(shown(p.parent) for p in panels))
        lines.append(f"  {', '.join(folders)}: {len(panels)} picture(s): "
                     "RGB | true depth | predicted | IGD of predicted pose | error")
    lines.append(f"  {shown(fit_dir)}, {shown(test_dir)}: logs of the fit and the test (TensorBoard; the same "
                 "figures as CSV under csv/)")
    lines.append(f"  {shown(checkpoint)}: the checkpoint tested")
    return lines


def main(argv: list[str] | None = None) -> int:
    """Run the quickstart; returns 0 when the model beats both baselines where it must."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("outputs/quickstart"), help="output folder")
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG)
    parser.add_argument("--data-root", type=Path, default=None, help="synthetic data cache (default OUT/data)")
    parser.add_argument("--max-epochs", type=at_least_one, default=None,
                        help="override the config's trainer.max_epochs")
    parser.add_argument("--train-size", type=at_least_one, default=None,
                        help="override the synthetic training set size")
    parser.add_argument("--checkpoint", default=None,
                        help="test this trained checkpoint (a file or a split checkpoint folder) instead of training")
    parser.add_argument("--image-size", type=at_least_one, default=None,
                        help="with --checkpoint: the images' size (default: the size the checkpoint was trained at, "
                             "else 64)")
    parser.add_argument("--render-seed", type=int, default=1,
                        help="with --checkpoint: the seed of the images rendered (default 1; the quickstart and the "
                             "shipped model train on seed 0)")
    parser.add_argument("--val-size", type=at_least_one, default=200, help="with --checkpoint: the test images")
    args = parser.parse_args(argv)
    if args.checkpoint:
        return main_checkpoint(args)
    if args.image_size is not None:
        parser.error("--image-size is for --checkpoint: the quickstart trains and tests at its config's "
                     "data.init_args.image_size (--config FILE to change it)")
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
    print("\n".join(outputs_listing(out, Path(fit.trainer.log_dir or out), Path(test.trainer.log_dir or out),
                                     Path(best))))
    print(f"Took {(time.time() - start) / 60:.1f} min.")
    return 0 if not failures else 1


at_least_one = whole_number(1)
"""An argparse type for the counts and sizes: 0 would silently mean the config's."""


def checkpoint_image_size(checkpoint: str, default: int = 64) -> int:
    """The square side a checkpoint was trained at: a split folder's card, a local file's record, else ``default``."""
    card = split_checkpoint_card(checkpoint)
    if "image_size" in card:
        return int(card["image_size"])
    if not is_remote(checkpoint) and local_path(checkpoint).is_file():
        size = training_image_size(read_checkpoint(local_path(checkpoint)))
        if size is not None:
            return max(size)
    return default


def main_checkpoint(args: argparse.Namespace) -> int:
    """The quickstart without training: ``args.checkpoint`` tested on rendered images beside the baselines."""
    start = time.time()
    if not is_remote(args.checkpoint) and not local_path(args.checkpoint).exists():
        raise FileNotFoundError(f"{args.checkpoint}: no such checkpoint file or folder")  # before any rendering
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    size = args.image_size or checkpoint_image_size(args.checkpoint)
    data_root = (args.data_root or out / f"data_{size}_seed{args.render_seed}").resolve()
    chosen = {"train": args.train_size or 500, "val": args.val_size, "size": size, "seed": args.render_seed}
    print(f"[1/3] synthetic UAPD-format data in {data_root}: {chosen['val']} test images at {size}x{size}, "
          f"render seed {args.render_seed} ({chosen['train']} training images for the mean-pose baseline)")
    if not is_current(data_root, **chosen):
        generate_uapd(data_root, **chosen)
    print("[2/3] baselines on the test images")
    base = baselines(data_root)
    print(f"[3/3] testing {args.checkpoint} (no training)")
    model, telemetry, panel = evaluate_checkpoint(args.checkpoint, data_root, out,
                                                  torch.tensor(base["mean_pose"]["pose"], dtype=torch.float64))
    table, failures = report(model, base, telemetry)
    summary = {"model": model, "baselines": base, "with_telemetry": telemetry, "checkpoint": str(args.checkpoint),
               "data": {**chosen, "root": str(data_root)}, "minutes": (time.time() - start) / 60,
               "beats_baselines": not failures, "not_beaten": failures}
    (out / "metrics.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"\n{args.checkpoint} vs baselines on {chosen['val']} rendered images (depth in metres). Baselines: depth "
          "= IGD of the mean training pose, pose = the mean training pose. +telem.: the model given each image's "
          "telemetry (noise of 3 m, 1 deg, 1 deg, 2 deg) through its IGD.\n")
    print(table)
    print("\n" + ("The model beats both baselines on depth d1, AbsRel and every pose median."
                  if not failures else f"NOT beaten: {', '.join(failures)}"))
    print(f"\nOutputs in {out}:\n  metrics.json       all figures above\n  {panel.relative_to(out)}  "
          "RGB | true depth | predicted | IGD of predicted pose | error")
    print(f"Took {(time.time() - start) / 60:.1f} min.")
    return 0 if not failures else 1


if __name__ == "__main__":
    debug, arguments = debug_requested(sys.argv[1:])
    raise SystemExit(run_reporting_errors(lambda: main(arguments), debug))


__all__ = ["baselines", "main", "main_checkpoint", "report", "evaluate_checkpoint", "with_telemetry"]
