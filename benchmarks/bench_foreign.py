"""A checkpoint on a world no generator of this project made: does its depth respect the ground it is told about?

``python -m benchmarks.bench_foreign --checkpoint CKPT --out OUT``: renders ``--count`` UAPD-format images with a
second, deliberately plain renderer written from docs/conventions.md alone (none of :mod:`dapm_lightning.data.synthetic`
or :mod:`dapm_lightning.geometry.igd`): a plane ground (level, or tilted by ``--slope``) with colour bands and
roads, box buildings and cylinder trees, shaded by one sun, a sky gradient and haze; the depth is the exact ray
range. The checkpoint is then
evaluated as ``bench_synth transfer`` does (noisy telemetry σ 3 m, 1°, 1°, 2°, the network told that σ) and the
table names the rows issue 31 is about: the network alone, the IGD of the noisy full telemetry alone (no learning),
the network given that telemetry (what ``predict --telemetry`` does), the height alone, and the true pose's IGD.
The verdict says whether the depth given the full telemetry beats the flat ground of that telemetry, overall and on
the flat-ground pixels. Writes ``foreign.json``.

Not a training set: its point is to be unlike the training's (other shapes, colours and layout), as a user's
renderer or a real flight would be. ``--slope DEG`` tilts every view's ground (the IGD and its bound assume it
level): how much a hillside costs the telemetry's flat ground, and the bound at margins 0, 0.1 (``predict``'s
default) and 0.25.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from dapm_lightning.data.files import write_image, write_text
from dapm_lightning.data.uapd import format_uapd_filename
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_KEYS, POSE_RANGES
from dapm_lightning.geometry.depth_codec import depth_to_grey
from dapm_lightning.models.prior import IGD_BOUND_MARGIN

BOUND_MARGINS = (0.0, IGD_BOUND_MARGIN, 0.25)
"""The IGD bound's margins measured: each pixel capped at ``(1 + margin)`` x the flat ground of the telemetry."""
GROUND_KEPT = 0.02
"""The ground is kept when the network's d1 on it is at most this far below the telemetry's flat ground's."""
ROWS = (("model", "none (the network alone)"), ("full/igd", "full telemetry, IGD alone"),
        ("full/cond+bound", "full telemetry, network"), ("full/cond", "  the same, no IGD bound"),
        ("full/cond+bound@0", "  the same, bound margin 0"), ("full/cond+bound@0.25", "  the same, margin 0.25"),
        ("height/cond+bound", "height only, network"), ("true_pose", "true pose's IGD"))
"""The rows printed: (row of :func:`~dapm_lightning.tools.evaluate.evaluate`, label); the network's full-telemetry
row is what ``predict --telemetry`` gives (the bound at its default margin)."""


def camera_rays(pose: Sequence[float], size: tuple[int, int]) -> np.ndarray:
    """``[H, W, 3]`` world directions of every pixel's ray (not unit length), docs/conventions.md written out."""
    _, pitch, roll, fov = (float(v) for v in pose)
    rows, cols = size
    p, r = math.radians(pitch), math.radians(roll)
    focal = cols / (2.0 * math.tan(math.radians(fov) / 2.0))
    forward = np.array([math.cos(p), 0.0, math.sin(p)])
    right0 = np.array([0.0, -1.0, 0.0])
    down0 = np.cross(forward, right0)
    right = math.cos(r) * right0 + math.sin(r) * down0
    down = -math.sin(r) * right0 + math.cos(r) * down0
    u = (np.arange(cols) + 0.5 - cols / 2.0) / focal
    v = (np.arange(rows) + 0.5 - rows / 2.0) / focal
    return u[None, :, None] * right + v[:, None, None] * down + forward


def sample_world(rng: np.random.Generator, pose: Sequence[float], slope: float = 0.0) -> dict[str, Any]:
    """Buildings (boxes), trees (vertical cylinders), roads and colours around what the camera sees.

    ``slope``: the ground is a plane through the point under the camera tilted by this many degrees, downhill in a
    random direction (0: level, what the IGD assumes); the camera's height is above that point.
    """
    height, pitch = float(pose[0]), float(pose[1])
    ahead = min(height / math.tan(math.radians(max(-pitch, 5.0))), 600.0) if pitch < 0 else 600.0
    reach = 1.5 * height + 1.5 * ahead + 30.0

    def spots(count: int, clearance: float) -> np.ndarray:
        xy = np.stack([rng.uniform(-reach, reach + ahead, count), rng.uniform(-reach, reach, count)], axis=1)
        return xy[np.hypot(xy[:, 0], xy[:, 1]) > clearance]  # nothing stands over the camera's nadir

    density = rng.uniform(0.3, 1.0)
    centres = spots(int(density * 120), 25.0)
    half = rng.uniform(4.0, 20.0, (len(centres), 2))
    clear = (np.abs(centres) > half + 3.0).any(axis=1)  # no building around the camera's nadir
    centres, half = centres[clear], half[clear]
    tops = np.minimum(rng.lognormal(math.log(12.0), 0.7, len(centres)), 120.0)
    trees = spots(int(rng.uniform(0.2, 1.0) * 200), 8.0)
    world = {
        "boxes": np.column_stack([centres - half, centres + half, tops]),  # x0 y0 x1 y1 top (above the ground)
        "trees": np.column_stack([trees, rng.uniform(1.5, 5.0, len(trees)), rng.uniform(4.0, 22.0, len(trees))]),
        "ground": rng.uniform(0.15, 0.6, 3) * np.array([1.0, 1.1, 0.8]),
        "ground_bands": rng.uniform(5.0, 60.0, 3),
        "road_angle": rng.uniform(0.0, math.pi),
        "road_offsets": rng.uniform(-reach, reach, int(rng.integers(0, 4))),
        "walls": rng.uniform(0.35, 0.9, (len(centres), 3)),
        "roofs": rng.uniform(0.15, 0.6, (len(centres), 3)),
        "leaves": np.column_stack([rng.uniform(0.05, 0.25, len(trees)), rng.uniform(0.25, 0.55, len(trees)),
                                   rng.uniform(0.05, 0.2, len(trees))]),
        "sun": _unit(np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(0.4, 1.5)])),
        "visibility": rng.uniform(800.0, 4000.0),
        "ground_normal": np.array([0.0, 0.0, 1.0]),
    }
    if slope:  # drawn last, so that a level world is the same with or without this option
        tilt, azimuth = math.radians(slope), rng.uniform(0.0, 2 * math.pi)
        world["ground_normal"] = np.array([math.sin(tilt) * math.cos(azimuth), math.sin(tilt) * math.sin(azimuth),
                                           math.cos(tilt)])
    return world


def ground_z(world: dict[str, Any], x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray | float:
    """Height of the ground plane at ``(x, y)`` (0 under the camera)."""
    nx, ny, nz = world["ground_normal"]
    return -(nx * x + ny * y) / nz


BURIED = 1e4
"""Buildings and trees reach this far below the ground, so that on a slope they meet it on every side."""


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def render(pose: Sequence[float], size: tuple[int, int], world: dict[str, Any],
           noise: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(rgb uint8 [H, W, 3], range depth m [H, W], inf where the ray meets nothing)`` of one view."""
    rays = camera_rays(pose, size).reshape(-1, 3)
    origin = np.array([0.0, 0.0, float(pose[0])])
    count = len(rays)
    t_hit = np.full(count, np.inf)
    normal = np.zeros((count, 3))
    colour = np.zeros((count, 3))
    with np.errstate(divide="ignore", invalid="ignore"):
        towards = rays @ world["ground_normal"]
        t_ground = np.where(towards < 0, -(origin @ world["ground_normal"]) / towards, np.inf)
    t_hit[:] = t_ground
    normal[:] = world["ground_normal"]
    point = origin + np.where(np.isfinite(t_ground), t_ground, 0.0)[:, None] * rays
    along = point[:, 0] * math.cos(world["road_angle"]) + point[:, 1] * math.sin(world["road_angle"])
    across = -point[:, 0] * math.sin(world["road_angle"]) + point[:, 1] * math.cos(world["road_angle"])
    shade = 1.0 + 0.25 * sum(np.sin(2 * math.pi * c / w + k)
                             for k, (c, w) in enumerate(zip((along, across, along + across), world["ground_bands"])))
    colour[:] = np.clip(world["ground"][None] * shade[:, None] / 1.5, 0, 1)
    for offset in world["road_offsets"]:
        colour[np.abs(across - offset) < 6.0] = (0.22, 0.22, 0.24)
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, (x0, y0, x1, y1, top) in enumerate(world["boxes"]):  # slab test per box, all rays at once
            base = ground_z(world, (x0 + x1) / 2, (y0 + y1) / 2)  # its roof is `top` above the ground at its centre
            lo = (np.array([x0, y0, base - BURIED]) - origin) / rays
            hi = (np.array([x1, y1, base + top]) - origin) / rays
            near, far = np.minimum(lo, hi), np.maximum(lo, hi)
            near = np.nan_to_num(near, nan=-np.inf)
            far = np.nan_to_num(far, nan=np.inf)
            t_near, t_far = near.max(axis=1), far.min(axis=1)
            hit = (t_near <= t_far) & (t_near > 0) & (t_near < t_hit)
            axis = near.argmax(axis=1)[hit]
            face = np.zeros((int(hit.sum()), 3))
            face[np.arange(len(axis)), axis] = -np.sign(rays[hit, axis])
            t_hit[hit], normal[hit] = t_near[hit], face
            colour[hit] = np.where((axis == 2)[:, None], world["roofs"][k], world["walls"][k])
        a = rays[:, 0] ** 2 + rays[:, 1] ** 2  # the rays' horizontal part, the same for every tree
        for k, (cx, cy, radius, top) in enumerate(world["trees"]):
            ox, oy = origin[0] - cx, origin[1] - cy
            b = 2 * (ox * rays[:, 0] + oy * rays[:, 1])
            c = ox * ox + oy * oy - radius * radius
            t_side = (-b - np.sqrt(b * b - 4 * a * c)) / (2 * a)
            z_side = origin[2] + t_side * rays[:, 2]
            base = ground_z(world, cx, cy)
            side = (t_side > 0) & (z_side >= base - BURIED) & (z_side <= base + top)
            t_top = (base + top - origin[2]) / rays[:, 2]
            on_top = (t_top > 0) & ((ox + t_top * rays[:, 0]) ** 2 + (oy + t_top * rays[:, 1]) ** 2 <= radius ** 2)
            t = np.where(side, t_side, np.where(on_top, t_top, np.inf))
            hit = t < t_hit
            if not hit.any():
                continue
            at = origin + t[hit, None] * rays[hit]
            n = np.where(side[hit, None], np.column_stack([at[:, 0] - cx, at[:, 1] - cy, np.zeros(len(at))]),
                         np.array([0.0, 0.0, 1.0]))
            t_hit[hit], normal[hit], colour[hit] = t[hit], _unit(n), world["leaves"][k]
    length = np.linalg.norm(rays, axis=1)
    depth = t_hit * length
    light = 0.45 + 0.55 * np.clip(normal @ world["sun"], 0, 1)
    lit = colour * light[:, None]
    elevation = np.clip(rays[:, 2] / length, -1, 1)
    sky = np.array([0.78, 0.85, 0.95]) - np.clip(elevation, 0, 1)[:, None] * np.array([0.45, 0.3, 0.05])
    haze = 1.0 - np.exp(-np.nan_to_num(depth, posinf=1e9) / world["visibility"])
    rgb = np.where(np.isfinite(depth)[:, None], lit * (1 - haze[:, None]) + np.array([0.8, 0.84, 0.9]) * haze[:, None],
                   sky)
    if noise is not None:
        rgb = rgb + noise.normal(0.0, 0.015, rgb.shape)
    image = (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8).reshape(*size, 3)
    return image, depth.reshape(size)


def view(seed: int, index: int, size: int, slope: float = 0.0) -> tuple[str, np.ndarray, np.ndarray]:
    """``(UAPD file name, rgb, range depth)`` of view ``index`` of a set: a pose uniform in the UAPD ranges."""
    rng = np.random.default_rng([seed, index])
    pose = np.array([round(float(rng.uniform(*POSE_RANGES[key])), 2) for key in POSE_KEYS])
    rgb, depth = render(pose, (size, size), sample_world(rng, pose, slope), rng)
    return format_uapd_filename(["foreign", f"{index:05d}"], pose), rgb, depth


def write_set(out: Path, count: int, size: int, seed: int, slope: float = 0.0) -> list[str]:
    """``count`` views in UAPD layout under ``out/val`` (and an empty ``out/train``); returns the file names."""
    for split in ("train", "val"):
        for kind in ("rgb", "depth"):
            (out / split / kind).mkdir(parents=True, exist_ok=True)
    names = []
    for index in range(count):
        name, rgb, depth = view(seed, index, size, slope)
        write_image(out / "val" / "rgb" / name, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        write_image(out / "val" / "depth" / name, depth_to_grey(depth, MAX_DEPTH_M))
        names.append(name)
    return names


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Render, evaluate the checkpoint, print the table and the verdict, write ``foreign.json``."""
    from dapm_lightning.tools.evaluate import evaluate
    from dapm_lightning.training.checkpointing import load_dapm_module

    out = args.out.resolve()
    root = out / "foreign_data"
    module = load_dapm_module(args.checkpoint).eval()  # first: a wrong path fails before any rendering
    write_set(root, args.count, args.size, args.seed, args.slope)
    mean_pose = torch.tensor([(lo + hi) / 2 for lo, hi in (POSE_RANGES[k] for k in POSE_KEYS)], dtype=torch.float64)
    with torch.no_grad():
        rows = evaluate(module, root, mean_pose, bound_margins=BOUND_MARGINS)
    print(f"\n{args.count} views of {args.size}x{args.size} from a renderer this project's models never trained on; "
          "d1 / AbsRel, and d1 on the flat-ground pixels and on what stands on them")
    print(f"{'row':<30}{'d1':>8}{'AbsRel':>8}{'ground':>8}{'objects':>9}")
    for key, label in ROWS:
        r = rows[key]
        print(f"{label:<30}{r['d1']:>8.3f}{r['abs_rel']:>8.3f}{r.get('d1_ground', float('nan')):>8.3f}"
              f"{r.get('d1_objects', float('nan')):>9.3f}")
    told, alone = rows["full/cond+bound"], rows["full/igd"]
    verdict = {"beats_igd": told["d1"] >= alone["d1"],
               "keeps_ground": told["d1_ground"] >= alone["d1_ground"] - GROUND_KEPT}
    print("\nGiven the full telemetry the depth " + ("beats" if verdict["beats_igd"] else "falls below")
          + f" the flat ground of that telemetry (d1 {told['d1']:.3f} against {alone['d1']:.3f}); on the ground "
          + ("it keeps" if verdict["keeps_ground"] else "it loses")
          + f" the telemetry's accuracy ({told['d1_ground']:.3f} against {alone['d1_ground']:.3f}).")
    report = {"checkpoint": str(args.checkpoint), "count": args.count, "size": args.size, "seed": args.seed,
              "slope": args.slope,
              "results": rows, "verdict": verdict}
    write_text(out / "foreign.json", json.dumps(report, indent=2, default=float) + "\n")
    print(f"report in {out / 'foreign.json'}")
    return report


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Command line: ``--checkpoint CKPT [--out OUT --count N --size S --seed K]``; returns the report."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True, help="a DAPM checkpoint (.ckpt)")
    parser.add_argument("--out", type=Path, default=Path("outputs/bench_foreign"))
    parser.add_argument("--count", type=int, default=200, help="views rendered (default 200)")
    parser.add_argument("--size", type=int, default=64, help="image side in pixels (default 64, the quickstart's)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--slope", type=float, default=0.0,
                        help="degrees the ground of every view is tilted, downhill in a random direction (default 0: "
                             "level, as the IGD assumes)")
    args = parser.parse_args(argv)
    if not args.checkpoint.exists():
        parser.error(f"{args.checkpoint}: no such checkpoint. Fix: pass a .ckpt (make demo writes one under "
                     "outputs/quickstart) or a shipped model's folder (models/dapm-synthetic-r18-256)")
    if args.count < 1 or args.size < 16 or not 0 <= args.slope < 60:
        parser.error("--count must be at least 1, --size at least 16 and --slope from 0 to below 60 degrees")
    return run(args)


if __name__ == "__main__":
    main()
