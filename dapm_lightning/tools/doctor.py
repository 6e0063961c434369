"""dapm-lightning doctor ROOT: check a UAPD-format data set and report per split.

Counts, pose distribution against the UAPD ranges, depth range and sky fraction, unreadable or
unpaired files, and the agreement of each file's depth with the Ideal Ground Depth of its own
pose: pixels that see flat ground match the IGD exactly, so a pose whose roll sign is wrong, or
whose fields are swapped, explains the depth worse than the corrected pose would. Exit status 1
when a file is broken or a sample is flagged. The report is printed, and written as JSON only where
asked (--json FILE; nothing is written into the data set). Settings can come from a YAML file
(--config FILE; --print_config shows one).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from json import dumps
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from dapm_lightning.data.errors import DatasetError
from dapm_lightning.data.uapd import UAPDDataset, read_depth_grey
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_KEYS, POSE_RANGES, SKY_GREY
from dapm_lightning.geometry.depth_codec import grey_to_depth
from dapm_lightning.geometry.igd import DepthKind, ideal_ground_depth

AGREE_TOLERANCE = 0.05
"""A pixel agrees with the flat ground when ``|depth / IGD - 1| < 5 %`` (two 8-bit grey levels)."""
FLAG_MARGIN = 0.1
"""A sample is flagged when an alternative annotation makes this much more of its pixels agree."""
MIN_AGREEMENT = 0.02
"""Below this share no flat ground is visible (e.g. a street canyon): such a sample is listed as unchecked."""
CHECK_WIDTH = 128
"""Depth maps are checked at this width at most (nearest-neighbour downsampling keeps grey levels)."""


def alternatives(pose: np.ndarray) -> dict[str, np.ndarray]:
    """Plausible annotation mistakes to test against: roll sign, pitch sign, swapped pitch/roll."""
    height, pitch, roll, fov = pose
    return {"roll negated": np.array([height, pitch, -roll, fov]),
            "pitch negated": np.array([height, -pitch, roll, fov]),
            "pitch and roll swapped": np.array([height, roll, pitch, fov])}


def agreement(depth_m: np.ndarray, poses: np.ndarray, depth_kind: DepthKind) -> tuple[np.ndarray, np.ndarray]:
    """Share of non-sky pixels matching the IGD of each pose, and the median depth/IGD ratio on the lower half.

    Args:
        depth_m: ``[H, W]`` metres. poses: ``[K, 4]``.
    """
    size = depth_m.shape
    igd = ideal_ground_depth(torch.from_numpy(poses).double(), size, depth_kind=depth_kind)[:, 0].numpy()
    seen = depth_m < MAX_DEPTH_M  # not sky in the label
    ratio = depth_m[None] / np.maximum(igd, 1e-6)
    agree = (np.abs(ratio - 1.0) < AGREE_TOLERANCE) & seen[None] & (igd < MAX_DEPTH_M)
    share = agree.reshape(len(poses), -1).sum(1) / max(int(seen.sum()), 1)
    lower = np.zeros(size, bool)
    lower[size[0] // 2:] = True
    usable = lower & seen
    median = np.array([float(np.median(r[usable & (g < MAX_DEPTH_M)])) if (usable & (g < MAX_DEPTH_M)).any()
                       else math.nan for r, g in zip(ratio, igd)])
    return share, median


def check_sample(depth_grey: np.ndarray, pose: np.ndarray, depth_kind: DepthKind) -> dict[str, Any]:
    """Agreement of one sample with its pose and with each alternative; the flag and why."""
    if depth_grey.shape[1] > CHECK_WIDTH:
        scale = CHECK_WIDTH / depth_grey.shape[1]
        depth_grey = cv2.resize(depth_grey, (CHECK_WIDTH, max(1, round(depth_grey.shape[0] * scale))),
                                interpolation=cv2.INTER_NEAREST)
    depth = grey_to_depth(depth_grey).astype(np.float64)
    alts = alternatives(pose)
    shares, medians = agreement(depth, np.stack([pose, *alts.values()]), depth_kind)
    best_name, best_share = max(zip(alts, shares[1:]), key=lambda item: item[1])
    reason = None
    if best_share > shares[0] + FLAG_MARGIN:
        reason = f"{best_name} fits the depth better ({best_share:.2f} vs {shares[0]:.2f} of pixels agree)"
    return {"agreement": float(shares[0]), "lower_median_ratio": float(medians[0]), "flag": reason,
            "unchecked": bool(max(shares) < MIN_AGREEMENT)}


def diagnose_split(root: Path, split: str, depth_kind: DepthKind) -> dict[str, Any]:
    """The report of one split."""
    try:
        dataset = UAPDDataset(root, split, on_bad_file="skip")
    except DatasetError as error:
        return {"split": split, "count": 0, "errors": error.problems, "flagged": []}
    errors = list(dataset.skipped)
    poses = dataset.poses.astype(np.float64)
    pose_stats = {}
    for k, key in enumerate(POSE_KEYS):
        lo, hi = POSE_RANGES[key]
        values = poses[:, k]
        pose_stats[key] = {"min": float(values.min()), "q25": float(np.quantile(values, 0.25)),
                           "median": float(np.median(values)), "q75": float(np.quantile(values, 0.75)),
                           "max": float(values.max()), "range": [lo, hi],
                           "outside_range": int(((values < lo) | (values > hi)).sum())}
    sky_fractions, agreements, ratios, flagged, unchecked = [], [], [], [], []
    depth_min, depth_max = math.inf, 0.0
    for index, name in enumerate(dataset.names):
        path = root / split / dataset.depth_dir / name
        try:
            grey = read_depth_grey(path)
        except ValueError as error:
            errors.append(str(error))
            continue
        sky = grey == SKY_GREY
        sky_fractions.append(float(sky.mean()))
        if (~sky).any():
            seen = grey_to_depth(grey[~sky])
            depth_min, depth_max = min(depth_min, float(seen.min())), max(depth_max, float(seen.max()))
        result = check_sample(grey, poses[index], depth_kind)
        agreements.append(result["agreement"])
        ratios.append(result["lower_median_ratio"])
        if result["flag"]:
            flagged.append({"name": name, "reason": result["flag"]})
        elif result["unchecked"]:
            unchecked.append(name)
    return {"split": split, "count": len(dataset), "errors": errors, "flagged": flagged, "unchecked": unchecked,
            "pose": pose_stats,
            "depth_m": {"min": depth_min if sky_fractions else None, "max": depth_max},
            "sky_fraction": {"mean": float(np.mean(sky_fractions)) if sky_fractions else None},
            "ground_agreement": {"median": float(np.median(agreements)) if agreements else None,
                                 "lower_half_median_ratio": float(np.nanmedian(ratios)) if ratios else None},
            "depth_kind": depth_kind}


def format_report(reports: list[dict[str, Any]]) -> str:
    """Terminal table of the split reports."""
    lines = []
    for r in reports:
        lines.append(f"== {r['split']}: {r['count']} pairs, {len(r['errors'])} error(s), "
                     f"{len(r['flagged'])} flagged")
        if r.get("pose"):
            lines.append(f"   {'pose':<8}{'min':>9}{'q25':>9}{'median':>9}{'q75':>9}{'max':>9}   UAPD range  outside")
            for key, s in r["pose"].items():
                lines.append(f"   {key:<8}{s['min']:>9.1f}{s['q25']:>9.1f}{s['median']:>9.1f}{s['q75']:>9.1f}"
                             f"{s['max']:>9.1f}   {s['range'][0]:>5.0f}..{s['range'][1]:<5.0f}{s['outside_range']:>6}")
            depth, agree = r["depth_m"], r["ground_agreement"]
            if depth["min"] is not None:
                lines.append(f"   depth {depth['min']:.2f} .. {depth['max']:.1f} m (below sky); "
                             f"mean sky fraction {r['sky_fraction']['mean']:.3f}")
            if agree["median"] is not None:
                lines.append(f"   flat-ground agreement ({r['depth_kind']} IGD of each file's pose): median "
                             f"{agree['median']:.3f} of non-sky pixels within 5 %; lower-half depth/IGD "
                             f"median ratio {agree['lower_half_median_ratio']:.3f}")
        lines += [f"   ERROR   {e}" for e in r["errors"]]
        lines += [f"   FLAGGED {f['name']}: {f['reason']}" for f in r["flagged"]]
        if r.get("unchecked"):
            lines.append(f"   note: {len(r['unchecked'])} sample(s) show no flat ground (pose not checkable), "
                         "listed in the JSON report (--json FILE)")
    return "\n".join(lines)


def doctor(root: Path, splits: list[str] | None = None, depth_kind: DepthKind = "range",
           json: Path | None = None) -> int:
    """Check a UAPD-format data set (ROOT/SPLIT/rgb, ROOT/SPLIT/depth) and print a report per split.

    Args:
        root: the data set's folder.
        splits: splits to check (default: every sub-folder with rgb/ and depth/).
        depth_kind: what the depth maps hold: range (lens to point) or planar (along the optical axis;
            CARLA's depth camera).
        json: also write the report as JSON to this file (nothing is written otherwise).

    Returns:
        the exit status: 0 clean, 1 a broken file or a flagged sample, 2 no data set at ROOT.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such folder (give the data set's root, which holds train/ and val/)")
    splits = splits or sorted(p.name for p in root.iterdir() if (p / "rgb").is_dir() or (p / "depth").is_dir())
    if not splits:
        raise FileNotFoundError(f"{root}: no split folders with rgb/ and depth/ (expected ROOT/train, ROOT/val)")
    reports = [diagnose_split(root, split, depth_kind) for split in splits]
    print(format_report(reports))
    bad = sum(len(r["errors"]) + len(r["flagged"]) for r in reports)
    where = ""
    if json is not None:
        Path(json).parent.mkdir(parents=True, exist_ok=True)
        Path(json).write_text(dumps(reports, indent=2) + "\n")
        where = f"report: {json}; "
    print(f"\n{where}{'no problems found' if not bad else f'{bad} problem(s)'}")
    return 1 if bad else 0


def doctor_main(argv: Sequence[str]) -> int:
    """Entry point of ``dapm-lightning doctor``; returns the exit status."""
    from jsonargparse import auto_cli

    return int(auto_cli(doctor, args=list(argv), prog="dapm-lightning doctor", description=__doc__))
