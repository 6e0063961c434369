"""One picture of a scene through the exact camera of docs/conventions.md ("Camera"): RGB, range depth and a hit map."""

from __future__ import annotations

import math

import numpy as np
import torch

from dapm_lightning.data.synthetic.engine import REACH_M, RayCaster, clear_of_camera, visible
from dapm_lightning.data.synthetic.scene import BUILDING, GROUND, SKY, WATER, Scene
from dapm_lightning.data.synthetic.shading import camera_effects, ground_color, object_color, sky_color, water_color
from dapm_lightning.geometry.camera import camera_rays
from dapm_lightning.geometry.constants import MAX_DEPTH_M


def camera_frame(pose: np.ndarray, yaw_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World forward, right and down axes of the camera (docs/conventions.md, turned by ``yaw_deg`` about Z)."""
    p, r, y = (math.radians(float(v)) for v in (pose[1], pose[2], yaw_deg))
    sp, cp, sr, cr = math.sin(p), math.cos(p), math.sin(r), math.cos(r)
    forward = np.array([cp, 0.0, sp])
    right = np.array([sr * sp, -cr, -sr * cp])
    down = np.array([cr * sp, sr, -cr * cp])
    turn = np.array([[math.cos(y), -math.sin(y), 0.0], [math.sin(y), math.cos(y), 0.0], [0.0, 0.0, 1.0]])
    return turn @ forward, turn @ right, turn @ down


def unit_rays(pose: np.ndarray, size: tuple[int, int], yaw_deg: float) -> np.ndarray:
    """Unit ray per pixel ``[H*W, 3]`` in the world (float64), from :func:`geometry.camera_rays`."""
    pose_t = torch.as_tensor(np.asarray(pose, np.float64))[None]
    dirs = camera_rays(pose_t[:, 1], pose_t[:, 2], pose_t[:, 3], size)[0].numpy().reshape(-1, 3)
    dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    yaw = math.radians(yaw_deg)
    c, s = math.cos(yaw), math.sin(yaw)
    return np.stack([dirs[:, 0] * c - dirs[:, 1] * s, dirs[:, 0] * s + dirs[:, 1] * c, dirs[:, 2]], -1)


def render_scene(pose: np.ndarray, size: tuple[int, int], scene: Scene, max_depth: float = MAX_DEPTH_M, *,
                 effects: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast one picture.

    Args:
        pose: ``[4]`` (height m, pitch deg, roll deg, fov deg).
        size: ``(H, W)``.
        scene: from :func:`sample_scene`.
        max_depth: unused by the geometry (kept for the API); depth is returned unclamped.
        effects: apply the camera processing of ``scene.look`` (exposure, blur, noise, JPEG).

    Returns:
        ``(rgb [H, W, 3] uint8, range [H, W] metres (inf where nothing is hit), hit map [H, W] uint8)``
        with hit values ``SKY, GROUND, BUILDING, TREE, VEHICLE, PERSON, WATER``. Ground and water
        pixels hold exactly the ideal ground depth of the pose (range kind).
    """
    del max_depth
    height_px, width_px = size
    pose = np.asarray(pose, np.float64)
    dirs = unit_rays(pose, size, scene.yaw_deg)
    origin = np.array([scene.camera_xy[0], scene.camera_xy[1], float(pose[0])])
    forward, right, down = camera_frame(pose, scene.yaw_deg)
    objects = scene.objects.select(clear_of_camera(scene.objects, origin))
    objects = objects.select(visible(objects, origin, forward, right, down, float(pose[3]), size))
    caster = RayCaster(objects, origin, scene.sun)
    t_obj, row, n_obj = caster.intersect(dirs)
    # the ground plane, exactly as geometry.ideal_ground_depth: range = height / (-d_z) for a unit ray
    downward = -dirs[:, 2]
    t_ground = np.where(downward > 1e-6, origin[2] / np.where(downward > 1e-6, downward, 1.0), np.inf)
    on_ground = np.isfinite(t_ground) & (t_ground <= t_obj)
    on_object = ~on_ground & np.isfinite(t_obj)
    t = np.where(on_ground, t_ground, t_obj)
    kind = np.full(len(dirs), SKY, np.uint8)
    kind[on_ground] = GROUND
    kind[on_object] = objects.cls[row[on_object]]
    hit = on_ground | on_object
    points = origin + dirs * np.where(hit, t, 0.0)[:, None]
    pixel_angle = 2 * math.tan(math.radians(float(pose[3])) / 2) / width_px
    normal = np.zeros_like(dirs)
    normal[:, 2] = 1.0
    normal[on_object] = n_obj[on_object]
    incidence = np.maximum(np.abs((normal * dirs).sum(1)), 0.05)
    footprint = np.where(hit, t, 0.0) * pixel_angle / incidence
    look, seed = scene.look, scene.texture_seed
    color = np.zeros_like(dirs)
    wet = np.zeros(len(dirs), bool)
    if on_ground.any():
        ground, water = ground_color(points[on_ground, 0], points[on_ground, 1], footprint[on_ground], scene.layout,
                                     look, seed)
        color[on_ground] = ground
        wet[on_ground] = water
        kind[wet] = WATER
    if on_object.any():
        shade_color, shade_normal = object_color(objects, row[on_object], points[on_object], n_obj[on_object],
                                                 footprint[on_object], seed)
        color[on_object] = shade_color
        normal[on_object] = shade_normal
    # sun light with cast shadows (shadow rays through the same Embree scene), sky light, contact darkening
    lit = hit & (t < REACH_M)
    shadow = np.zeros(len(dirs), bool)
    if scene.sun[2] > 0 and lit.any():
        start = dirs[lit] * t[lit, None] + np.where(on_ground[lit, None], np.array([0.0, 0.0, 0.02]),
                                                    n_obj[lit] * 0.03)
        shadow[lit] = caster.occluded(start, scene.sun)
    sun_term = np.clip(normal @ scene.sun, 0.0, 1.0) * (scene.sun[2] > 0) * ~shadow
    sky_term = 0.78 + 0.22 * normal[:, 2]
    light = look["ambient"] * sky_term + look["sun_strength"] * sun_term
    contact = np.where(on_object & (kind == BUILDING), 0.75 + 0.25 * np.clip(points[:, 2] / 4.0, 0, 1), 1.0)
    color = color * (light * contact)[:, None]
    if wet.any():
        color[wet] = water_color(color[wet], dirs[wet], scene.sun, look, origin, pixel_angle, seed)
    # atmospheric perspective: distant surfaces fade into the haze; rays that miss see the sky
    fog = 1.0 - np.exp(-np.where(hit, t, np.inf) / look["visibility"])
    color = color * (1 - fog[:, None]) + look["haze"] * fog[:, None]
    if (~hit).any():
        color[~hit] = sky_color(dirs[~hit], scene.sun, look, origin, pixel_angle, seed)
    image = color.reshape(height_px, width_px, 3)
    if effects:
        rgb = camera_effects(image, look, np.random.default_rng(seed))
    else:
        rgb = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return rgb, np.where(hit, t, np.inf).reshape(height_px, width_px), kind.reshape(height_px, width_px)
