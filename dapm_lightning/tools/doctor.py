"""dapm-lightning doctor ROOT: check a UAPD-format data set and report per split (or a Potsdam root's tiles).

Counts, pose distribution against the UAPD ranges, depth range and sky fraction, every unreadable
(each RGB and depth file is decoded) or unpaired file, and the agreement of each file's depth with
the Ideal Ground Depth of its own pose: pixels that see flat ground match the IGD to the grey level,
and nothing is ever seen deeper than the ground. A sample is flagged when a plausible annotation
mistake (roll or pitch sign, pitch and roll swapped, another FoV) explains clearly more of its depth
as flat ground without being contradicted more by depth beyond its ground. Exit status 0 when no
problem is found, 1 when a file is broken or a sample is flagged (or, ROOT checked whole, train/ has no
val/ beside it, which fit needs), 2 when ROOT is not a data set (or on a usage error). The report is
printed, and written as JSON only where asked (--json FILE; nothing is written into the data set).
Settings can come from a YAML file (--config FILE; --print_config shows one). Grey 255 of the depth files
means --max_depth metres: by default the max_depth that ROOT/synth.json records (a set from
`dapm-lightning synth --max_depth`), else UAPD's 1000.
"""

from __future__ import annotations

import math
import sys
import warnings
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from json import dumps
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dapm_lightning.data.depth_kind import (
    AGREE_LEVELS,
    at_check_width,
    depth_kind_mismatch,
    flat_ground_agreement,
    on_flat_ground,
    other_kind,
)
from dapm_lightning.data.errors import DatasetError
from dapm_lightning.data.files import WriteError, check_folder_writable, write_error, write_text
from dapm_lightning.data.potsdam import ISPRS_PRODUCT_DIRS, ISPRS_RGB_DIR, PotsdamCrops, is_potsdam_root
from dapm_lightning.data.uapd import (
    BAD_DEPTH_RECORD_FIX,
    SYNTH_SETTINGS,
    UAPDDataset,
    read_depth_grey,
    read_rgb,
    recorded_depth_limit,
)
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_KEYS, POSE_RANGES, SKY_GREY
from dapm_lightning.geometry.depth_codec import check_depth_limit, depth_to_grey, grey_to_depth
from dapm_lightning.geometry.igd import DepthKind, ideal_ground_depth
from dapm_lightning.tools.progress import progress_bar

EXIT_CLEAN, EXIT_PROBLEMS, EXIT_NOT_A_DATA_SET = 0, 1, 2
"""Exit statuses: no problem; a broken file or a flagged sample; ROOT (or a split asked for) is not a data set."""
NO_VAL_FIX = ("Fix: put a val split in ROOT/val/{rgb,depth}/NAME.png (e.g. move some train pairs there): "
              "`dapm-lightning fit` validates on it and refuses to start without it (`test` reads it too unless "
              "data.init_args.test_split names another); UAPD's layout: docs/data.md.")
"""The fix of a set checked whole (no --splits) that has train/ but no val/ split."""
UNFINISHED_RENDER_FIX = ("Fix: rerun the `dapm-lightning synth` command that rendered it (it replaces the unfinished "
                         "set and writes synth.json last), or wait for a render still running.")
"""The fix of a set whose synthetic images have no ``synth.json``."""
BEYOND_LEVELS = 1
"""A pixel lies beyond the ground of a pose when it is deeper than the pose's IGD by more than one grey level
(more than the 8-bit rounding). Nothing is seen through the ground: such pixels contradict the pose."""
FLAG_MARGIN = 0.1
"""An alternative pose is preferred when its evidence reaches this share of the non-sky pixels. Evidence is
counted only where the two poses can be told apart (their IGDs differ by more than AGREE_LEVELS there): the
pixels that agree with the alternative less those that agree with the annotated pose, plus the pixels beyond
the annotated pose's ground less those beyond the alternative's. A near-identical alternative (pitch close
to roll, a FoV close to the annotated one) thus never wins by objects that happen to lie near its ground."""
MIN_GROUND_PIXELS = 32
"""The evidence, and the pixels of flat ground the alternative explains beyond the annotated pose, must also
reach this many pixels (at the checked resolution), however small the image or its visible ground."""
MIN_AGREEMENT = 0.02
"""Below this share (or MIN_GROUND_PIXELS) no pose makes flat ground visible (e.g. a street canyon): such a
sample is listed as unchecked."""
FOV_STEP = 5.0
"""The FoVs tried as alternatives: the UAPD range in steps of this many degrees."""
FOV_CROP = 0.5
"""The FoV is judged on the central part of the image, this share of its width and height: radial lens
distortion (which UAPD randomises, and no file name records) grows with the distance from the centre."""
LENS_K_MAX, LENS_KCUBE_MAX = 0.5, 0.2
"""UAPD's lens distortion range (|k|, |kcube|): a pixel at radius r (in half-diagonals) shows the pinhole
camera's r (1 + k r^2 + kcube r^3). Inside FOV_CROP this rescales radii by at most 15 %, so only FoVs whose
focal length differs from the annotated one by more than that are tried."""


def alternatives(pose: np.ndarray) -> dict[str, np.ndarray]:
    """Plausible annotation mistakes to test against, on the whole image: roll sign, pitch sign, swapped pitch/roll."""
    height, pitch, roll, fov = pose
    return {"roll negated": np.array([height, pitch, -roll, fov]),
            "pitch negated": np.array([height, -pitch, roll, fov]),
            "pitch and roll swapped": np.array([height, roll, pitch, fov])}


def fov_alternatives(pose: np.ndarray) -> dict[str, np.ndarray]:
    """Other FoVs to test against, on the image's centre.

    The UAPD range in FOV_STEP steps, less the FoVs whose focal length is within the lens distortion's reach
    (LENS_K_MAX, LENS_KCUBE_MAX) of the annotated one.
    """
    height, pitch, roll, fov = pose
    lo, hi = POSE_RANGES["fov"]
    reach = 1.0 + LENS_K_MAX * (FOV_CROP ** 2) + LENS_KCUBE_MAX * (FOV_CROP ** 3)
    alts = {}
    for other in np.arange(lo, hi + FOV_STEP / 2, FOV_STEP):
        scale = math.tan(math.radians(other) / 2) / math.tan(math.radians(min(max(fov, 1.0), 179.0)) / 2)
        if not 1.0 / reach <= scale <= reach:
            alts[f"FoV {other:g}"] = np.array([height, pitch, roll, other])
    return alts


def crop_fov(fov: np.ndarray | float, width: int, crop_width: int) -> np.ndarray:
    """The FoV across a centred crop ``crop_width`` wide of an image ``width`` wide (same focal length)."""
    return np.degrees(2.0 * np.arctan(np.tan(np.radians(fov) / 2.0) * crop_width / width))


def ground_evidence(depth_grey: np.ndarray, igd: np.ndarray,
                    max_depth: float = MAX_DEPTH_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pose, the grey level of its IGD, the pixels that agree with that ground, those that lie beyond it.

    Args:
        depth_grey: ``[H, W]`` uint8, the data set's encoding (grey 255 at ``max_depth`` metres).
        igd: ``[K, H, W]`` metres, the IGD of K poses.

    Returns:
        ``(igd_grey [K, H, W] int16, agree [K, H, W] bool, beyond [K, H, W] bool)``: ``agree`` counts non-sky
        pixels only; ``beyond`` includes sky (seen where the pose has ground nearer than ``max_depth``).
    """
    igd_grey = depth_to_grey(igd, max_depth).astype(np.int16)
    above = depth_grey.astype(np.int16)[None] - igd_grey  # > 0: deeper than the ground of the pose
    agree = on_flat_ground(depth_grey, igd_grey)
    beyond = (above > BEYOND_LEVELS) & (igd_grey < SKY_GREY)  # where the pose has ground nearer than max_depth
    return igd_grey, agree, beyond


def compare_poses(depth_grey: np.ndarray, poses: np.ndarray, depth_kind: DepthKind, *,
                  contradicted: bool = False, max_depth: float = MAX_DEPTH_M) -> dict[str, Any]:
    """The annotated pose ``poses[0]`` against each alternative ``poses[1:]`` on one depth map.

    Args:
        max_depth: the metres grey 255 of ``depth_grey`` means.
        contradicted: prefer an alternative only where the depth contradicts the annotated pose more than the
            alternative (more pixels lie beyond its ground), as for the FoV: see :func:`check_sample`.

    Returns:
        ``igd`` (``[H, W]`` metres, of the annotated pose), ``seen`` (non-sky pixels), ``agree`` and ``beyond``
        (``[K]`` pixel counts), ``evidence`` and ``preferred`` (``[K - 1]``: for each alternative, see
        :func:`check_sample`).
    """
    igd = ideal_ground_depth(torch.from_numpy(poses).double(), depth_grey.shape, depth_kind=depth_kind,
                             max_depth=max_depth)[:, 0].numpy()
    igd_grey, agree, beyond = ground_evidence(depth_grey, igd, max_depth)
    seen = max(int((depth_grey < SKY_GREY).sum()), 1)
    n_agree, n_beyond = agree.sum((1, 2)), beyond.sum((1, 2))
    apart = np.abs(igd_grey[1:] - igd_grey[:1]) > AGREE_LEVELS  # where the data can tell the two grounds apart
    gained = (agree[1:] & apart).sum((1, 2)) - (agree[:1] & apart).sum((1, 2))
    cleared = (beyond[:1] & apart).sum((1, 2)) - (beyond[1:] & apart).sum((1, 2))
    evidence = gained + cleared
    preferred = ((gained >= MIN_GROUND_PIXELS) & (evidence >= max(FLAG_MARGIN * seen, MIN_GROUND_PIXELS))
                 & (n_beyond[1:] < n_beyond[0] if contradicted else n_beyond[1:] <= n_beyond[0]))
    return {"igd": igd[0], "seen": seen, "pixels": depth_grey.size, "agree": n_agree, "beyond": n_beyond,
            "evidence": evidence, "preferred": preferred}


def lower_median_ratio(depth_m: np.ndarray, igd: np.ndarray, max_depth: float = MAX_DEPTH_M) -> float:
    """Median depth/IGD ratio on the pixels of the lower half of the image where both are below ``max_depth``."""
    usable = (depth_m < max_depth) & (igd < max_depth)
    usable[: depth_m.shape[0] // 2] = False
    return float(np.median(depth_m[usable] / np.maximum(igd[usable], 1e-6))) if usable.any() else math.nan


def check_sample(depth_grey: np.ndarray, pose: np.ndarray, depth_kind: DepthKind,
                 max_depth: float = MAX_DEPTH_M) -> dict[str, Any]:
    """Agreement of one sample with its pose and with each alternative; the flag and why.

    ``max_depth``: the metres grey 255 of ``depth_grey`` means (the limit the set was written with).

    An alternative is preferred, and the sample flagged, when (1) it explains at least MIN_GROUND_PIXELS more
    pixels as flat ground, and its evidence (:data:`FLAG_MARGIN`) reaches ``max(FLAG_MARGIN * non-sky pixels,
    MIN_GROUND_PIXELS)``, and (2) no more pixels lie beyond its ground than beyond the annotated pose's. (2) rules
    out a pose that fits a raised surface (a forest canopy, roofs near the horizon) instead of the ground: the
    real ground lies beyond it.

    Roll, pitch and their swap are judged on the whole image. The FoV is judged on the image's centre
    (:data:`FOV_CROP`), where lens distortion is small, and (3) only where the depth contradicts the annotated
    FoV: of the many FoVs tried, one often fits a large flat roof in a band, but a raised surface never lies
    beyond the ground, so on exact data a right pose is never contradicted. A FoV too wide for a nadir view,
    whose ground then lies nowhere beyond the depth, goes unnoticed.
    """
    depth_grey = at_check_width(depth_grey)
    height, width = depth_grey.shape
    alts, fov_alts = alternatives(pose), fov_alternatives(pose)
    whole = compare_poses(depth_grey, np.stack([pose, *alts.values()]), depth_kind, max_depth=max_depth)
    top, left = round(height * (1 - FOV_CROP) / 2), round(width * (1 - FOV_CROP) / 2)
    centre_grey = depth_grey[top:height - top, left:width - left]  # centred: the principal point stays
    centre_poses = np.stack([pose, *fov_alts.values()])
    centre_poses[:, 3] = crop_fov(centre_poses[:, 3], width, centre_grey.shape[1])
    centre = compare_poses(centre_grey, centre_poses, depth_kind, contradicted=True, max_depth=max_depth)
    candidates = [(whole["evidence"][k] / whole["seen"], name, whole, k) for k, name in enumerate(alts)
                  if whole["preferred"][k]]
    candidates += [(centre["evidence"][k] / centre["seen"], name, centre, k) for k, name in enumerate(fov_alts)
                   if centre["preferred"][k]]
    reason = None
    if candidates:
        _, name, on, k = max(candidates, key=lambda c: c[0])
        where = " of the image's centre" if on is centre else ""
        reason = (f"{name} fits the depth better ({on['agree'][k + 1] / on['seen']:.2f} vs "
                  f"{on['agree'][0] / on['seen']:.2f} of the non-sky pixels{where} agree; "
                  f"{on['beyond'][k + 1] / on['pixels']:.2f} vs {on['beyond'][0] / on['pixels']:.2f} of all pixels"
                  f"{where} lie beyond the ground)")
    depth = grey_to_depth(depth_grey, max_depth).astype(np.float64)
    visible = any(c["agree"].max() >= max(MIN_AGREEMENT * c["seen"], MIN_GROUND_PIXELS) for c in (whole, centre))
    return {"agreement": float(whole["agree"][0] / whole["seen"]),
            "agreement_other_kind": flat_ground_agreement(depth_grey, pose, other_kind(depth_kind), max_depth),
            "beyond": float(whole["beyond"][0] / whole["pixels"]),
            "lower_median_ratio": lower_median_ratio(depth, whole["igd"], max_depth), "flag": reason,
            "unchecked": not visible}


@contextmanager
def one_torch_thread() -> Iterator[None]:
    """Torch on one thread meanwhile: the checks are small tensors, which threads slow down (a lot on a busy CPU)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def diagnose_split(root: Path, split: str, depth_kind: DepthKind, quiet: bool = True,
                   max_depth: float = MAX_DEPTH_M) -> dict[str, Any]:
    """The report of one split (with a progress bar on a terminal unless ``quiet``); grey 255 is ``max_depth`` m."""
    try:
        with warnings.catch_warnings():  # the files skipped are listed as errors below
            warnings.simplefilter("ignore")
            dataset = UAPDDataset(root, split, on_bad_file="skip", max_depth=max_depth)
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
    containers = dict(zip(dataset.names, dataset.depth_containers))
    sky_fractions, agreements, agreements_other, ratios, flagged, unchecked = [], [], [], [], [], []
    depth_min, depth_max = math.inf, 0.0
    with one_torch_thread(), progress_bar(len(dataset.names), quiet=quiet, what=f"checking {split}") as bar:
        for index, name in enumerate(dataset.names):
            bar.update()
            grey = None
            try:  # both files are decoded: every one that fails is listed (the scan checks structure and CRCs only)
                grey = read_depth_grey(root / split / dataset.depth_dir / name)
            except ValueError as error:
                errors.append(str(error))
            try:
                read_rgb(root / split / dataset.rgb_dir / name, expected_hw=None if grey is None else grey.shape[:2])
            except ValueError as error:
                errors.append(str(error))
            if grey is None:
                continue
            sky = grey == SKY_GREY
            sky_fractions.append(float(sky.mean()))
            if (~sky).any():
                seen = grey_to_depth(grey[~sky], max_depth)
                depth_min, depth_max = min(depth_min, float(seen.min())), max(depth_max, float(seen.max()))
            result = check_sample(grey, poses[index], depth_kind, max_depth)
            agreements.append(result["agreement"])
            agreements_other.append(result["agreement_other_kind"])
            ratios.append(result["lower_median_ratio"])
            if result["flag"]:
                flagged.append({"name": name, "reason": result["flag"]})
            elif result["unchecked"]:
                unchecked.append(name)
    mismatch = (depth_kind_mismatch(depth_kind, float(np.median(agreements)), float(np.median(agreements_other)))
                if agreements else None)
    return {"split": split, "count": len(dataset), "errors": errors, "flagged": flagged, "unchecked": unchecked,
            "depth_kind_problem": mismatch,
            "pose": pose_stats,
            "depth_m": {"min": depth_min if sky_fractions else None, "max": depth_max},
            "sky_fraction": {"mean": float(np.mean(sky_fractions)) if sky_fractions else None},
            "ground_agreement": {"median": float(np.median(agreements)) if agreements else None,
                                 "median_other_kind": float(np.median(agreements_other)) if agreements else None,
                                 "lower_half_median_ratio": float(np.nanmedian(ratios)) if ratios else None},
            "depth_kind": depth_kind, "max_depth": max_depth,
            "depth_container": containers,
            "depth_containers": {kind: n for kind in sorted(set(containers.values()))
                                 if (n := sum(c == kind for c in containers.values()))}}


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
            if r.get("depth_containers"):
                kinds = ", ".join(f"{n} {kind}" for kind, n in r["depth_containers"].items())
                lines.append(f"   depth PNGs: {kinds} (per file: depth_container in the JSON report)")
            depth, agree = r["depth_m"], r["ground_agreement"]
            if depth["min"] is not None:
                lines.append(f"   depth {depth['min']:.2f} .. {depth['max']:.1f} m (below sky); "
                             f"mean sky fraction {r['sky_fraction']['mean']:.3f}")
            if agree["median"] is not None:
                lines.append(f"   flat-ground agreement ({r['depth_kind']} IGD of each file's pose): median "
                             f"{agree['median']:.3f} of non-sky pixels within 2 grey levels (5 %); lower-half "
                             f"depth/IGD median ratio {agree['lower_half_median_ratio']:.3f} (exact depth reads "
                             "about 0.99: the encoding rounds down)")
                if agree.get("median_other_kind") is not None:
                    lines.append(f"   with the {other_kind(r['depth_kind'])} IGD instead: median "
                                 f"{agree['median_other_kind']:.3f}")
        if r.get("depth_kind_problem"):
            lines.append(f"   PROBLEM depth kind: {r['depth_kind_problem']}")
        lines += [f"   ERROR   {e}" for e in r["errors"]] + ([f"   {r['fix']}"] if r.get("fix") else [])
        lines += [f"   FLAGGED {f['name']}: {f['reason']}" for f in r["flagged"]]
        if r.get("unchecked"):
            lines.append(f"   note: {len(r['unchecked'])} sample(s) show no flat ground (pose not checkable), "
                         "listed in the JSON report (--json FILE)")
    return "\n".join(lines)


def depth_limit(root: Path, max_depth: float | None) -> tuple[float, str]:
    """The metres grey 255 means, and where that comes from: ``max_depth``, else ROOT/synth.json's, else UAPD's.

    Raises:
        ValueError: a limit that is not finite or too small (:func:`check_depth_limit`), naming where it came from.
    """
    if max_depth is not None:
        return check_depth_limit(max_depth, "max_depth"), "given by --max_depth"
    record = root / SYNTH_SETTINGS
    try:
        recorded = recorded_depth_limit(root)
    except ValueError as error:
        raise ValueError(f"{error}.\nFix: {BAD_DEPTH_RECORD_FIX} (--max_depth)") from None
    if recorded is None:
        return MAX_DEPTH_M, f"UAPD's, the default: no {record.name} records another"
    return recorded, f"recorded in {record}"


def check_potsdam(root: Path) -> list[dict[str, Any]]:
    """Per height product found (one for the flat rgb/ + height/ layout): the tile pairs and every tile problem.

    A tile is checked as the crops are cut: paired, RGB and height decodable, of one size (nothing is written).
    """
    isprs = (root / ISPRS_RGB_DIR).is_dir()
    products = [p for p, folder in ISPRS_PRODUCT_DIRS.items() if (root / folder).is_dir()] if isprs else ["ndsm"]
    reports = []
    for product in products or ["ndsm"]:  # no product folder: the missing folder is the problem reported
        tiles = PotsdamCrops(root, product=product)  # type: ignore[arg-type]
        try:
            count, problems = tiles.check_tiles()
        except DatasetError as error:
            count, problems = 0, error.problems
        reports.append({"layout": "isprs" if isprs else "flat", "product": product if isprs else None,
                        "height_dir": str(tiles.height_dir), "pairs": count, "errors": problems})
    return reports


def doctor(root: Path, splits: list[str] | None = None, depth_kind: DepthKind = "range",
           json: Path | None = None, quiet: bool = False, max_depth: float | None = None) -> int:
    """Check a UAPD-format data set (ROOT/SPLIT/rgb, ROOT/SPLIT/depth) and print a report per split.

    Args:
        root: the data set's folder.
        splits: splits to check (default: every sub-folder with rgb/ and depth/).
        depth_kind: what the depth maps hold: range (lens to point) or planar (along the optical axis;
            CARLA's depth camera).
        max_depth: the metres grey 255 of the depth files means (METRES). Default: the max_depth recorded in
            ROOT/synth.json (a set rendered with `dapm-lightning synth --max_depth`), else UAPD's 1000.
        json: also write the report as JSON to this file (nothing is written otherwise).
        quiet: no progress bar (there is none off a terminal).

    Returns:
        the exit status: 0 clean, 1 a broken file, a flagged sample or (``splits`` not given) a train split
        without a val split, 2 no data set at ROOT (ROOT is not a
        folder, holds no split folder, or a split asked for has neither rgb/ nor depth/), a depth limit that is
        not finite or too small, or a ``json`` path that cannot be written (checked before the scan; a write that
        fails after it, e.g. on a full disk, leaves no partial file); the reason is then printed to stderr.
    """
    root = Path(root)
    problem, asked = None, splits
    if not root.is_dir():
        what = "a file, not a folder" if root.exists() else "no such folder"
        problem = f"{root}: {what} (give the data set's root, which holds train/ and val/)"
    elif is_potsdam_root(root):
        return _doctor_potsdam(root, json)
    else:
        found = sorted(p.name for p in root.iterdir() if (p / "rgb").is_dir() or (p / "depth").is_dir())
        missing = [split for split in splits or [] if split not in found]
        splits = splits or found
        if not splits:
            problem = f"{root}: not a data set: no split folders with rgb/ and depth/ (expected ROOT/train, ROOT/val)"
        elif missing:
            problem = (f"{root}: no split {', '.join(missing)} (a folder with rgb/ and depth/); "
                       f"splits found: {', '.join(found) or 'none'}")
    limit, limit_from = MAX_DEPTH_M, ""
    if problem is None:
        try:
            limit, limit_from = depth_limit(root, max_depth)
        except ValueError as error:
            problem = str(error)
    if problem is None and json is not None:
        problem = _unwritable_report(Path(json))
    if problem is not None:
        print(f"error: {problem}", file=sys.stderr)
        return EXIT_NOT_A_DATA_SET
    print(f"depth limit: grey 255 = {limit:g} m, {limit_from}" + ("" if max_depth is not None else
                                                                   " (--max_depth METRES sets another)"))
    reports = [diagnose_split(root, split, depth_kind, quiet, limit) for split in splits]
    rendered = [r for r in reports if any((root / r["split"] / "rgb").glob("synth_*.png"))]
    if rendered and not (root / "synth.json").is_file():  # synth writes it last, once the set is whole
        rendered[0]["errors"].append(f"{root}: synthetic images (synth_*.png) but no synth.json: a render cut short "
                                     "(a full disk, Ctrl-C) or still running, so the set is not whole")
        rendered[0]["fix"] = UNFINISHED_RENDER_FIX
    no_val = "train" in splits and "val" not in found  # `fit` validates on ROOT/val and refuses to start without it
    if no_val and not asked:  # the whole set checked: a problem (its missing folder), with the fix
        reports.append({**diagnose_split(root, "val", depth_kind, quiet, limit), "fix": NO_VAL_FIX})
    print(format_report(reports))
    if no_val and asked:
        print(f"note: {root} has no val/ split: `dapm-lightning fit` validates on ROOT/val and refuses to start "
              "without it (`test` reads it too unless data.init_args.test_split names another)")
    bad = sum(len(r["errors"]) + len(r["flagged"]) + bool(r.get("depth_kind_problem")) for r in reports)
    return _conclude(reports, bad, json)


def _conclude(reports: list[dict[str, Any]], bad: int, json: Path | None) -> int:
    """Write the JSON report when asked (whole or not at all), print the closing line, and return the exit status."""
    where = ""
    if json is not None:
        try:  # atomically: a full disk leaves no half report, and an earlier one whole
            Path(json).parent.mkdir(parents=True, exist_ok=True)
            write_text(json, dumps(reports, indent=2) + "\n")
        except OSError as error:
            print(f"error: {write_error(Path(json), error)}", file=sys.stderr)
            return EXIT_NOT_A_DATA_SET
        where = f"report: {json}; "
    print(f"\n{where}{'no problems found' if not bad else f'{bad} problem(s)'}")
    return EXIT_PROBLEMS if bad else EXIT_CLEAN


def _doctor_potsdam(root: Path, json: Path | None) -> int:
    """:func:`doctor` on a Potsdam root (the ISPRS download, or rgb/ + height/ tiles): its tiles are checked."""
    if json is not None and (problem := _unwritable_report(Path(json))):
        print(f"error: {problem}", file=sys.stderr)
        return EXIT_NOT_A_DATA_SET
    reports = check_potsdam(root)
    print(f"{root}: Potsdam tiles ({'ISPRS download' if reports[0]['layout'] == 'isprs' else 'rgb/ + height/'}): "
          "each pair checked as the crops are cut (paired, decodable, of one size); the pose and depth checks are "
          "for UAPD-format sets")
    for r in reports:
        lines = [f"== {r['height_dir']}: {r['pairs']} tile pair(s), {len(r['errors'])} error(s)"]
        print("\n".join(lines + [f"   ERROR   {e}" for e in r["errors"]]))
    return _conclude(reports, sum(len(r["errors"]) for r in reports), json)


def _unwritable_report(path: Path) -> str | None:
    """Why the JSON report could not be written to ``path`` (checked before the scan), or None."""
    if path.is_dir():
        return f"--json {path} is a folder (give the report's file, e.g. {path / 'doctor.json'})"
    try:
        check_folder_writable(path.parent, "--json")
    except WriteError as error:
        return f"--json {path}: {error.path} cannot be written ({error.reason}; give a file in a folder you can write)"
    return None


def doctor_main(argv: Sequence[str]) -> int:
    """Entry point of ``dapm-lightning doctor``; returns the exit status."""
    from jsonargparse import auto_cli

    from dapm_lightning.tools.argv import flag_options, list_options

    args = flag_options(list_options(argv, ["--splits"]), ["--quiet"])
    return int(auto_cli(doctor, args=args, prog="dapm-lightning doctor", description=__doc__))
