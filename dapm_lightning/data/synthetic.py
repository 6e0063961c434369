"""Synthetic UAPD-format data: ray-cast town scenes seen by the exact camera of design.md §1.

Each image is rendered, not painted: every pixel's ray (``geometry.camera_rays``) is intersected with
a ground plane, box buildings and spherical trees; hits are shaded from world-space textures (roads
on a fixed grid, fields, windows every floor) under a sun; rays that miss see a sky gradient. The
written depth is the *range* to the hit, log-encoded to 8 bits (design.md §3). Pose cues are those
of real aerial images: horizon tilt (roll), horizon height (pitch), perspective (FoV), and the
metric size of roads, blocks and windows (height).
"""

from __future__ import annotations

import json
import math
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from dapm_lightning.geometry.camera import camera_rays
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_KEYS, POSE_RANGES
from dapm_lightning.geometry.depth_codec import depth_to_grey

SKY, GROUND, BUILDING, TREE = 0, 1, 2, 3
"""Values of the hit map :func:`render_scene` returns with each image."""

BLOCK_M = 48.0
"""Town block pitch in metres (road centre to road centre)."""
ROAD_M = 10.0
TOWN_RADIUS_M = 260.0
CLEAR_RADIUS_M = 25.0
"""No building stands within this distance of the point under the camera."""
_SPLIT_IDS = {"train": 0, "val": 1, "test": 2}
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@dataclass(frozen=True)
class Scene:
    """Random content of one picture, in world metres (camera above ``camera_xy``)."""

    camera_xy: tuple[float, float]
    yaw_deg: float
    box_min: np.ndarray  # [N, 3]
    box_max: np.ndarray  # [N, 3]
    box_color: np.ndarray  # [N, 3] wall RGB
    roof_color: np.ndarray  # [N, 3]
    tree_center: np.ndarray  # [M, 3]
    tree_radius: np.ndarray  # [M]
    sun: np.ndarray  # [3] unit vector towards the sun
    grid_offset: tuple[float, float]
    texture_seed: float


def sample_pose(rng: np.random.Generator, ranges: dict[str, tuple[float, float]] = POSE_RANGES) -> np.ndarray:
    """A pose uniform in the given ranges, rounded to 2 decimals (as written in the file name)."""
    return np.array([round(float(rng.uniform(*ranges[key])), 2) for key in POSE_KEYS])


def sample_scene(rng: np.random.Generator) -> Scene:
    """Town blocks around a random camera position: buildings, park trees, a sun."""
    camera_xy = (float(rng.uniform(-50, 50)), float(rng.uniform(-50, 50)))
    offset = (float(rng.uniform(0, BLOCK_M)), float(rng.uniform(0, BLOCK_M)))
    n = int(math.ceil(TOWN_RADIUS_M / BLOCK_M)) + 1
    mins, maxs, walls, roofs, trees, radii = [], [], [], [], [], []
    for i in range(-n, n + 1):
        for j in range(-n, n + 1):
            x0 = camera_xy[0] - camera_xy[0] % BLOCK_M + offset[0] + i * BLOCK_M + ROAD_M / 2
            y0 = camera_xy[1] - camera_xy[1] % BLOCK_M + offset[1] + j * BLOCK_M + ROAD_M / 2
            inner = BLOCK_M - ROAD_M
            centre = np.array([x0 + inner / 2 - camera_xy[0], y0 + inner / 2 - camera_xy[1]])
            if np.hypot(*centre) > TOWN_RADIUS_M:
                continue
            if rng.random() < 0.72:
                sx, sy = rng.uniform(10, inner - 2, size=2)
                bx = x0 + rng.uniform(1, inner - sx - 1)
                by = y0 + rng.uniform(1, inner - sy - 1)
                near_x = np.clip(camera_xy[0], bx, bx + sx) - camera_xy[0]
                near_y = np.clip(camera_xy[1], by, by + sy) - camera_xy[1]
                if np.hypot(near_x, near_y) < CLEAR_RADIUS_M:
                    continue
                height = float(np.exp(rng.uniform(np.log(5.0), np.log(55.0))))
                mins.append((bx, by, 0.0))
                maxs.append((bx + sx, by + sy, height))
                walls.append(rng.uniform([0.55, 0.5, 0.45], [0.9, 0.85, 0.8]))
                roofs.append(rng.uniform([0.3, 0.28, 0.26], [0.6, 0.5, 0.45]))
            else:
                for _ in range(int(rng.integers(2, 6))):
                    radius = float(rng.uniform(2.0, 4.5))
                    tx, ty = x0 + rng.uniform(radius, inner - radius, size=2)
                    if np.hypot(tx - camera_xy[0], ty - camera_xy[1]) < CLEAR_RADIUS_M:
                        continue
                    trees.append((tx, ty, radius + rng.uniform(1.0, 3.0)))
                    radii.append(radius)
    elevation = math.radians(rng.uniform(25, 70))
    azimuth = rng.uniform(0, 2 * math.pi)
    sun = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                    math.sin(elevation)])
    return Scene(camera_xy, float(round(rng.uniform(-180, 180), 2)),
                 np.array(mins, np.float64).reshape(-1, 3), np.array(maxs, np.float64).reshape(-1, 3),
                 np.array(walls).reshape(-1, 3), np.array(roofs).reshape(-1, 3),
                 np.array(trees, np.float64).reshape(-1, 3), np.array(radii, np.float64),
                 sun, offset, float(rng.uniform(0, 1000)))


def _hash(ix: np.ndarray, iy: np.ndarray, seed: float) -> np.ndarray:
    return np.modf(np.abs(np.sin(ix * 127.1 + iy * 311.7 + seed) * 43758.5453))[0]


def _value_noise(x: np.ndarray, y: np.ndarray, cell: float, seed: float) -> np.ndarray:
    """Smooth noise in [0, 1] with features of ``cell`` metres."""
    gx, gy = x / cell, y / cell
    ix, iy = np.floor(gx), np.floor(gy)
    fx, fy = gx - ix, gy - iy
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    top = _hash(ix, iy, seed) * (1 - fx) + _hash(ix + 1, iy, seed) * fx
    bottom = _hash(ix, iy + 1, seed) * (1 - fx) + _hash(ix + 1, iy + 1, seed) * fx
    return top * (1 - fy) + bottom * fy


def _fade(detail: np.ndarray, mean: float, footprint: np.ndarray, cell: float) -> np.ndarray:
    """Blend texture detail towards its mean where a pixel covers more than ``cell`` metres (anti-aliasing)."""
    k = np.clip(footprint / cell - 0.5, 0.0, 1.0)
    return detail * (1 - k) + mean * k


def _ground_color(x: np.ndarray, y: np.ndarray, footprint: np.ndarray, scene: Scene) -> np.ndarray:
    seed = scene.texture_seed
    gx = np.mod(x - scene.grid_offset[0], BLOCK_M)
    gy = np.mod(y - scene.grid_offset[1], BLOCK_M)
    town = np.hypot(x - scene.camera_xy[0], y - scene.camera_xy[1]) < TOWN_RADIUS_M + BLOCK_M / 2
    road = town & ((gx < ROAD_M) | (gy < ROAD_M))
    marking = road & (((np.abs(gx - ROAD_M / 2) < 0.2) & (np.mod(y, 6.0) < 3.0))
                      | ((np.abs(gy - ROAD_M / 2) < 0.2) & (np.mod(x, 6.0) < 3.0)))
    fine = _fade(_value_noise(x, y, 1.0, seed), 0.5, footprint, 1.0)
    patches = _fade(_value_noise(x, y, 9.0, seed + 1), 0.5, footprint, 9.0)
    grass = np.stack([0.25 + 0.2 * patches, 0.42 + 0.15 * patches, 0.18 + 0.08 * fine], -1)
    grass *= (0.85 + 0.3 * fine)[..., None]
    field_id = np.floor((x * 0.8 + y * 0.6) / 30.0)
    field_tone = _hash(field_id, field_id * 0.37, seed + 2)
    fields = np.stack([0.45 + 0.25 * field_tone, 0.42 + 0.12 * field_tone, 0.2 + 0.05 * field_tone], -1)
    fields *= (0.9 + 0.2 * fine)[..., None]
    asphalt = (0.28 + 0.06 * fine)[..., None] * np.ones(3)
    marking_fade = _fade(marking.astype(np.float64), 0.05, footprint, 0.4)
    asphalt = asphalt * (1 - marking_fade[..., None]) + 0.9 * marking_fade[..., None]
    color = np.where(town[..., None], grass, fields)
    return np.where(road[..., None], asphalt, color)


def _intersect_boxes(origin: np.ndarray, dirs: np.ndarray, scene: Scene) -> tuple[np.ndarray, ...]:
    """Nearest box hit per ray: distance (inf if none), box index, hit axis."""
    count = len(dirs)
    if len(scene.box_min) == 0:
        return np.full(count, np.inf), np.zeros(count, int), np.zeros(count, int)
    safe = np.where(np.abs(dirs) < 1e-12, 1e-12, dirs)
    inv = (1.0 / safe).astype(np.float32)
    lows, highs = [], []
    for axis in range(3):  # slabs per axis, [P, N] each
        t0 = (scene.box_min[None, :, axis] - origin[axis]).astype(np.float32) * inv[:, axis, None]
        t1 = (scene.box_max[None, :, axis] - origin[axis]).astype(np.float32) * inv[:, axis, None]
        lows.append(np.minimum(t0, t1))
        highs.append(np.maximum(t0, t1))
    t_near = np.maximum(np.maximum(lows[0], lows[1]), lows[2])
    t_far = np.minimum(np.minimum(highs[0], highs[1]), highs[2])
    t_hit = np.where((t_near <= t_far) & (t_near > 1e-4), t_near, np.float32(np.inf))
    index = t_hit.argmin(-1)
    rows = np.arange(count)
    near = t_hit[rows, index]
    axis_of_hit = np.stack([low[rows, index] for low in lows], -1).argmax(-1)
    return near.astype(np.float64), index, axis_of_hit


def _intersect_trees(origin: np.ndarray, dirs: np.ndarray, scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    count = len(dirs)
    if len(scene.tree_center) == 0:
        return np.full(count, np.inf), np.zeros(count, int)
    oc = origin - scene.tree_center  # [M, 3]
    b = dirs[:, :1] * oc[:, 0] + dirs[:, 1:2] * oc[:, 1] + dirs[:, 2:] * oc[:, 2]  # [P, M], no BLAS threads
    c = (oc * oc).sum(-1) - scene.tree_radius ** 2
    disc = b * b - c
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    t = np.where((disc > 0) & (t > 1e-6), t, np.inf)
    index = t.argmin(-1)
    return t[np.arange(count), index], index


def render_scene(pose: np.ndarray, size: tuple[int, int], scene: Scene,
                 max_depth: float = MAX_DEPTH_M) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast one picture.

    Args:
        pose: ``[4]`` (height m, pitch deg, roll deg, fov deg).
        size: ``(H, W)``.
        scene: from :func:`sample_scene`.

    Returns:
        ``(rgb [H, W, 3] uint8, range [H, W] metres (inf where nothing is hit), hit map [H, W] uint8)``
        with hit values ``SKY, GROUND, BUILDING, TREE``.
    """
    height_px, width_px = size
    pose_t = torch.as_tensor(np.asarray(pose, np.float64))[None]
    cam_dirs = camera_rays(pose_t[:, 1], pose_t[:, 2], pose_t[:, 3], size)[0].numpy().reshape(-1, 3)
    dirs = cam_dirs / np.linalg.norm(cam_dirs, axis=-1, keepdims=True)
    yaw = math.radians(scene.yaw_deg)
    dirs = np.stack([dirs[:, 0] * math.cos(yaw) - dirs[:, 1] * math.sin(yaw),
                     dirs[:, 0] * math.sin(yaw) + dirs[:, 1] * math.cos(yaw), dirs[:, 2]], -1)
    origin = np.array([scene.camera_xy[0], scene.camera_xy[1], float(pose[0])])
    # identical formula to geometry.ideal_ground_depth: range = height / (-d_z) for unit d
    downward = -dirs[:, 2]
    t_ground = np.where(downward > 1e-6, origin[2] / np.where(downward > 1e-6, downward, 1.0), np.inf)
    t_box, box_index, box_axis = _intersect_boxes(origin, dirs, scene)
    t_tree, tree_index = _intersect_trees(origin, dirs, scene)
    t_all = np.stack([t_ground, t_box, t_tree], -1)
    kind = np.where(np.isfinite(t_all.min(-1)), t_all.argmin(-1) + 1, SKY)
    t = t_all.min(-1)
    points = origin + dirs * np.where(np.isfinite(t), t, 0.0)[:, None]
    pixel_angle = math.radians(float(pose[3])) / width_px
    footprint = np.where(np.isfinite(t), t, 0.0) * pixel_angle / np.maximum(downward, 0.05)
    color = np.zeros((len(dirs), 3))
    normal = np.zeros((len(dirs), 3))
    normal[:, 2] = 1.0
    on_ground = kind == GROUND
    color[on_ground] = _ground_color(points[on_ground, 0], points[on_ground, 1], footprint[on_ground], scene)
    on_box = kind == BUILDING
    if on_box.any():
        index, axis = box_index[on_box], box_axis[on_box]
        normal[on_box] = 0.0
        normal[on_box, axis] = -np.sign(dirs[on_box, axis])
        roof = axis == 2
        along = np.where(axis == 0, points[on_box, 1], points[on_box, 0])
        floor_z = np.mod(points[on_box, 2], 3.5)
        window = (np.mod(along, 4.0) > 1.2) & (np.mod(along, 4.0) < 2.8) & (floor_z > 1.0) & (floor_z < 2.4)
        window_fade = _fade(window.astype(np.float64), 0.25, footprint[on_box] * 0.5, 1.0)
        wall = scene.box_color[index] * (1 - 0.55 * window_fade[:, None]) + np.array([0.05, 0.08, 0.15]) * (
            0.55 * window_fade[:, None])
        color[on_box] = np.where(roof[:, None], scene.roof_color[index], wall)
    on_tree = kind == TREE
    if on_tree.any():
        index = tree_index[on_tree]
        normal[on_tree] = (points[on_tree] - scene.tree_center[index]) / scene.tree_radius[index, None]
        leaf = _value_noise(points[on_tree, 0] * 3, points[on_tree, 2] * 3, 1.0, scene.texture_seed)
        color[on_tree] = np.stack([0.1 + 0.1 * leaf, 0.3 + 0.15 * leaf, 0.08 + 0.05 * leaf], -1)
    light = 0.45 + 0.6 * np.clip(normal @ scene.sun, 0.0, 1.0)
    color *= light[:, None]
    haze = np.array([0.74, 0.8, 0.88])
    fog = 1.0 - np.exp(-np.where(np.isfinite(t), t, np.inf) / 900.0)
    color = color * (1 - fog[:, None]) + haze * fog[:, None]
    up = np.clip(dirs[:, 2], 0.0, 1.0) ** 0.6
    sky_color = haze * (1 - up[:, None]) + np.array([0.3, 0.5, 0.85]) * up[:, None]
    color = np.where((kind == SKY)[:, None], sky_color, color)
    rgb = np.clip(color.reshape(height_px, width_px, 3) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return rgb, t.reshape(height_px, width_px), kind.reshape(height_px, width_px).astype(np.uint8)


def image_seed(seed: int, split: str, index: int) -> np.random.Generator:
    """The random generator of one image: depends on (seed, split, index) only, not on worker count."""
    return np.random.default_rng([seed, _SPLIT_IDS.get(split, 9), index])


def uapd_name(index: int, pose: np.ndarray, scene: Scene) -> str:
    """UAPD-style file name carrying the pose (and x, y, yaw as metadata)."""
    height, pitch, roll, fov = (float(v) for v in pose)
    x, y = scene.camera_xy
    return (f"synth_{index:06d}_x_{x:.2f}_y_{y:.2f}_z_{height:.2f}_pitch_{pitch:.2f}_roll_{roll:.2f}"
            f"_yaw_{scene.yaw_deg:.2f}_fov_{fov:.2f}.png")


def _render_one(job: tuple[Path, str, int, int, tuple[int, int]]) -> str:
    out, split, index, seed, size = job
    torch.set_num_threads(1)
    rng = image_seed(seed, split, index)
    pose = sample_pose(rng)
    scene = sample_scene(rng)
    rgb, depth_m, _ = render_scene(pose, size, scene)
    grey = depth_to_grey(np.where(np.isfinite(depth_m), depth_m, MAX_DEPTH_M))
    name = uapd_name(index, pose, scene)
    cv2.imwrite(str(out / split / "rgb" / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(out / split / "depth" / name), grey)
    return name


def generate_uapd(out: str | Path, *, train: int = 200, val: int = 50, size: int | tuple[int, int] = 128,
                  seed: int = 0, workers: int | None = None) -> Path:
    """Write a synthetic UAPD-format data set ``out/{train,val}/{rgb,depth}/NAME.png``.

    Args:
        out: root folder (created).
        train, val: image counts per split.
        size: ``S`` for ``S x S`` or ``(H, W)``.
        seed: same seed, same bytes, whatever the number of workers.
        workers: processes (default: the CPU count, at most 8).

    Returns:
        ``out``; it also holds ``synth.json`` with the arguments and the depth kind ("range").
    """
    out = Path(out)
    hw = (size, size) if isinstance(size, int) else tuple(size)
    jobs = []
    for split, count in (("train", train), ("val", val)):
        for sub in ("rgb", "depth"):
            (out / split / sub).mkdir(parents=True, exist_ok=True)
        jobs += [(out, split, i, seed, hw) for i in range(count)]
    workers = workers or min(os.cpu_count() or 1, 8)
    if workers > 1 and len(jobs) > 1:
        saved = {k: os.environ.get(k) for k in _THREAD_VARS}
        os.environ.update({k: "1" for k in _THREAD_VARS})  # one thread per worker process: no oversubscription
        try:
            with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
                list(pool.map(_render_one, jobs, chunksize=max(1, len(jobs) // (workers * 8))))
        finally:
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value
    else:
        for job in jobs:
            _render_one(job)
    info: dict[str, Any] = {"train": train, "val": val, "size": list(hw), "seed": seed, "depth_kind": "range",
                            "max_depth": MAX_DEPTH_M, "generator": "dapm_lightning.data.synthetic"}
    (out / "synth.json").write_text(json.dumps(info, indent=2) + "\n")
    return out
