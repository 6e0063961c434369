"""Materials, sky and camera processing of the synthetic renderer (numpy, per pixel).

Textures are procedural in world metres, so their size is a height cue: lane dashes 3 m long every
9 m, parking stalls 2.6 m, facade windows on storeys of 2.8-4.2 m, crop rows 0.75 m and tractor
tramlines every 20 m. Detail finer than a pixel's footprint fades to its mean (cheap anti-aliasing).
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import numpy as np

from dapm_lightning.data.synthetic.noise import fade, fbm, ihash, value_noise
from dapm_lightning.data.synthetic.objects import (
    BLOB,
    M_BOAT,
    M_CAR,
    M_CONIFER,
    M_CONTAINER,
    M_FACADE,
    M_GLASS,
    M_HALL,
    M_HOUSE,
    M_PERSON,
    M_TREE,
    M_UNIT,
    Objects,
)
from dapm_lightning.data.synthetic.rural import road_distance
from dapm_lightning.data.synthetic.urban import LOT_BUILT, LOT_PARKING, LOT_PLAZA, LOT_YARD, lot_type
from dapm_lightning.data.synthetic.water import water_mask

_ASPHALT = np.array([0.27, 0.27, 0.28])
_PAINT = np.array([0.88, 0.88, 0.84])
_CONCRETE = np.array([0.58, 0.57, 0.54])
_PAVING = np.array([0.66, 0.62, 0.57])
_WALK = np.array([0.63, 0.61, 0.58])
_DIRT = np.array([0.50, 0.42, 0.31])
_SAND = np.array([0.78, 0.72, 0.56])
_WATER = np.array([0.07, 0.15, 0.19])
_FOREST_FLOOR = np.array([0.20, 0.23, 0.12])
_CROPS = np.array([[0.74, 0.64, 0.36], [0.34, 0.50, 0.20], [0.46, 0.36, 0.26], [0.42, 0.52, 0.26],
                   [0.82, 0.76, 0.22], [0.58, 0.55, 0.30]])
_GLASS_DARK = np.array([0.10, 0.13, 0.17])


def _mix(a: np.ndarray, b: np.ndarray, k: np.ndarray) -> np.ndarray:
    return a * (1 - k[..., None]) + b * k[..., None]


def _grass(x: np.ndarray, y: np.ndarray, fp: np.ndarray, look: dict[str, Any], seed: int) -> np.ndarray:
    tone = fbm(x, y, 12.0, seed, fp, octaves=3)
    return look["grass"] * (0.75 + 0.5 * tone)[:, None]


def _fields(x: np.ndarray, y: np.ndarray, fp: np.ndarray, fields: dict[str, Any], seed: int) -> np.ndarray:
    ca, sa = math.cos(fields["angle"]), math.sin(fields["angle"])
    u, v = x * ca + y * sa - fields["ox"], -x * sa + y * ca - fields["oy"]
    fi, fj = np.floor(u / fields["sx"]), np.floor(v / fields["sy"])
    pick = ihash(fi.astype(np.int64), fj.astype(np.int64), fields["seed"])
    color = _CROPS[np.minimum((pick * len(_CROPS)).astype(int), len(_CROPS) - 1)]
    along_u = ihash(fi.astype(np.int64), fj.astype(np.int64), fields["seed"] + 1) < 0.5
    coord = np.where(along_u, v, u)
    rows = fade(0.5 + 0.5 * np.cos(coord * (2 * math.pi / 0.75)), 0.5, fp, 0.75)
    tram = fade((np.abs(np.mod(coord, 20.0) - 10.0) < 0.3).astype(float), 0.03, fp, 0.6)
    local_u, local_v = u - fi * fields["sx"], v - fj * fields["sy"]
    edge = (local_u < 2.0) | (local_v < 2.0)
    color = color * (0.85 + 0.2 * rows - 0.25 * tram)[:, None] * (0.85 + 0.3 * fbm(x, y, 30.0, seed, fp, 2))[:, None]
    return np.where(edge[:, None], np.array([0.33, 0.42, 0.2]), color)


def ground_color(x: np.ndarray, y: np.ndarray, fp: np.ndarray, layout: dict[str, Any], look: dict[str, Any],
                 seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Colour of the ground at world points (footprint ``fp`` metres per pixel) and whether it is water."""
    land = layout["land"]
    if land == "fields":
        color = _fields(x, y, fp, layout["fields"], seed)
    elif land == "forest":
        floor = _FOREST_FLOOR * (0.7 + 0.6 * fbm(x, y, 6.0, seed, fp, 3))[:, None]
        clearing = layout["clearing"]
        open_ = value_noise(x, y, 160.0, clearing["seed"]) > clearing["level"]
        color = np.where(open_[:, None], _grass(x, y, fp, look, seed), floor)
    else:
        color = _grass(x, y, fp, look, seed)
    fine = fade(value_noise(x, y, 0.7, seed + 3), 0.5, fp, 0.7)
    grid = layout.get("grid")
    if grid:
        bx, by, half, walk = grid["bx"], grid["by"], grid["road"] / 2, grid["walk"]
        gx = np.mod(x - grid["ox"], bx)
        gy = np.mod(y - grid["oy"], by)
        cx = np.where(gx > bx / 2, gx - bx, gx)  # offset from the road centre line
        cy = np.where(gy > by / 2, gy - by, gy)
        town = np.hypot(x - grid["cx"], y - grid["cy"]) < grid["radius"]
        kind = lot_type(np.floor((x - grid["ox"]) / bx).astype(np.int64),
                        np.floor((y - grid["oy"]) / by).astype(np.int64), grid)
        lot = {LOT_BUILT: _CONCRETE if grid["built_ground"] == "concrete" else None, LOT_PLAZA: _PAVING,
               LOT_PARKING: _ASPHALT * 1.1, LOT_YARD: _CONCRETE * 1.05}
        lot_color = _grass(x, y, fp, look, seed + 1)
        for k, c in lot.items():
            if c is not None:
                lot_color = np.where((kind == k)[:, None], c * (0.88 + 0.24 * fine)[:, None], lot_color)
        margin = half + walk
        lx, ly = gx - margin, gy - margin  # lot-local coordinates
        stall = ((np.mod(ly, 16.0) < 5.0) | (np.mod(ly, 16.0) > 11.0)) & (np.mod(lx, 2.6) < 0.12)
        stall = fade(stall.astype(float), 0.05, fp, 0.25) * (kind == LOT_PARKING)
        lot_color = _mix(lot_color, _PAINT, stall)
        plaza = fade(((np.mod(lx, 1.2) < 0.06) | (np.mod(ly, 1.2) < 0.06)).astype(float), 0.1, fp, 0.2)
        lot_color = _mix(lot_color, lot_color * 0.8, plaza * (kind == LOT_PLAZA))
        road_x, road_y = np.abs(cx) < half, np.abs(cy) < half  # road along y / along x
        on_road = road_x | road_y
        on_walk = ~on_road & ((np.abs(cx) < margin) | (np.abs(cy) < margin))
        asphalt = _ASPHALT * (0.85 + 0.3 * fine)[:, None]
        if grid["marks"]:
            dash_y = road_x & ~road_y & (np.abs(cx) < 0.08) & (np.mod(y, 9.0) < 3.0)
            dash_x = road_y & ~road_x & (np.abs(cy) < 0.08) & (np.mod(x, 9.0) < 3.0)
            edge = (road_x & ~road_y & (np.abs(np.abs(cx) - (half - 0.4)) < 0.08)) | (
                road_y & ~road_x & (np.abs(np.abs(cy) - (half - 0.4)) < 0.08))
            zebra = ((road_x & (np.abs(cy) > half + 0.5) & (np.abs(cy) < half + 3.5) & (np.mod(cx, 1.0) < 0.5))
                     | (road_y & (np.abs(cx) > half + 0.5) & (np.abs(cx) < half + 3.5) & (np.mod(cy, 1.0) < 0.5)))
            paint = fade((dash_y | dash_x | edge | zebra).astype(float), 0.06, fp, 0.3)
            asphalt = _mix(asphalt, _PAINT, paint)
        city = np.where(on_road[:, None], asphalt, np.where(on_walk[:, None], _WALK * (0.9 + 0.2 * fine)[:, None],
                                                            lot_color))
        color = np.where(town[:, None], city, color)
    road = layout.get("road")
    if road:
        across, along = road_distance(x, y, road)
        on = np.abs(across) < road["width"] / 2
        if road["paved"]:
            paint = ((np.abs(across) < 0.08) & (np.mod(along, 9.0) < 3.0)) | (
                np.abs(np.abs(across) - (road["width"] / 2 - 0.3)) < 0.08)
            surface = _mix(_ASPHALT * (0.85 + 0.3 * fine)[:, None], _PAINT, fade(paint.astype(float), 0.05, fp, 0.3))
        else:
            surface = _DIRT * (0.8 + 0.4 * fine)[:, None]
        color = np.where(on[:, None], surface, color)
    wet, signed = water_mask(x, y, layout.get("water"))
    if layout.get("water"):
        shore = (signed > -(25.0 if layout["water"]["kind"] == "coast" else 4.0)) & ~wet
        color = np.where(shore[:, None], _SAND * (0.85 + 0.3 * fine)[:, None], color)
        ripple = fbm(x, y, 4.0, seed + 9, fp, 2)
        color = np.where(wet[:, None], _WATER * (0.8 + 0.4 * ripple)[:, None], color)
    return color, wet


def object_color(objects: Objects, rows: np.ndarray, points: np.ndarray, normal: np.ndarray, fp: np.ndarray,
                 seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Colour of object hits and the shading normal (smooth for tree crowns)."""
    mat = objects.mat[rows]
    base = objects.color[rows].copy()
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    lo, hi = objects.lo[rows], objects.hi[rows]
    nz = normal[:, 2]
    wall = np.abs(nz) < 0.3
    flat_top = nz > 0.9
    pitched = ~wall & ~flat_top
    fine = fade(value_noise(x + z, y - z, 0.8, seed + 5), 0.5, fp, 0.8)
    facade = np.isin(mat, (M_FACADE, M_GLASS, M_HOUSE, M_HALL))
    if facade.any():
        along = np.where(np.abs(normal[:, 0]) > np.abs(normal[:, 1]), y, x)
        floor_h = objects.floor_h[rows]
        share = np.where(mat == M_GLASS, 0.86, objects.window[rows])
        spacing = np.where(mat == M_GLASS, 1.6, np.where(mat == M_HOUSE, 3.2, 2.8))
        level = np.mod(z, floor_h) / floor_h
        column = np.mod(along, spacing) / spacing
        sill = np.where(mat == M_GLASS, 0.06, np.where(mat == M_HALL, 0.6, 0.32))
        window = (np.abs(column - 0.5) < share / 2) & (level > sill) & (level < 0.88) & (z > 0.8)
        window_k = fade(window.astype(float), 0.5 * share * 0.55, fp, np.minimum(spacing, floor_h) * 0.5)
        pane = _GLASS_DARK * (0.8 + 0.6 * fine)[:, None]
        pane = np.where((mat == M_GLASS)[:, None], base * 0.5 + 0.12, pane)
        wall_color = base * (0.9 + 0.2 * fine)[:, None]
        wall_color = np.where((mat == M_HALL)[:, None],
                              wall_color * (0.9 + 0.1 * fade(np.cos(along * 2 * math.pi / 0.6) * 0.5 + 0.5, 0.5, fp,
                                                                  0.6))[:, None], wall_color)
        wall_color = _mix(wall_color, pane, window_k * (wall & facade))
        roof_color = objects.roof[rows] * (0.85 + 0.3 * fine)[:, None]
        tiles = fade(0.5 + 0.5 * np.cos(z * 2 * math.pi / 0.35), 0.5, fp, 0.35)
        roof_color = np.where(pitched[:, None], roof_color * (0.85 + 0.25 * tiles)[:, None], roof_color)
        base = np.where((facade & ~wall)[:, None], roof_color, np.where(facade[:, None], wall_color, base))
    car = mat == M_CAR
    if car.any():
        rel = (z - lo[:, 2]) / np.maximum(hi[:, 2] - lo[:, 2], 1e-6)
        base = np.where((car & wall & (rel > 0.55))[:, None], _GLASS_DARK, base)
        base = np.where((car & flat_top)[:, None], base * 0.95, base)
    person = mat == M_PERSON
    if person.any():
        base = np.where((person & (z > hi[:, 2] - 0.25))[:, None], np.array([0.75, 0.6, 0.5]), base)
    container = mat == M_CONTAINER
    if container.any():
        ribs = fade(0.5 + 0.5 * np.cos(np.where(np.abs(normal[:, 0]) > 0.5, y, x) * 2 * math.pi / 0.3), 0.5, fp, 0.3)
        base = np.where(container[:, None], base * (0.85 + 0.2 * ribs)[:, None], base)
    boat = mat == M_BOAT
    if boat.any():
        base = np.where((boat & flat_top)[:, None], np.array([0.8, 0.75, 0.65]), base)
    unit = mat == M_UNIT
    base = np.where(unit[:, None], base * (0.85 + 0.3 * fine)[:, None], base)
    tree = np.isin(mat, (M_TREE, M_CONIFER))
    shading_normal = normal.copy()
    if tree.any():
        leaves = fade(value_noise(x * 1.7 + z, y * 1.7 - z, 1.0, seed + 11), 0.5, fp, 0.6)
        base = np.where(tree[:, None], base * (0.65 + 0.7 * leaves)[:, None], base)
        blob = tree & (objects.prim[rows] == BLOB)
        if blob.any():
            centre = (lo[blob] + hi[blob]) / 2
            semi = np.maximum((hi[blob] - lo[blob]) / 2, 1e-3)
            smooth = (points[blob] - centre) / semi ** 2
            shading_normal[blob] = smooth / np.maximum(np.linalg.norm(smooth, axis=1, keepdims=True), 1e-9)
    return np.clip(base, 0, 1), shading_normal


def sky_color(dirs: np.ndarray, sun: np.ndarray, look: dict[str, Any], camera: np.ndarray,
              pixel_angle: float, seed: int) -> np.ndarray:
    """Sky seen along unit ``dirs``: zenith-to-haze gradient, sun glow and clouds on a layer at ``cloud_height``.

    The glow has a tight disc, a halo and the look's wide ``bloom`` (a camera's glare).
    """
    up = np.clip(dirs[:, 2], 0.0, 1.0)
    color = _mix(look["haze"][None], look["zenith"][None], up ** 0.5)
    cos_sun = np.clip(dirs @ sun, 0.0, 1.0)
    glow = (0.7 * cos_sun ** 400 + 0.2 * cos_sun ** 12 + look["bloom"] * cos_sun ** 6) * look["sun_strength"]
    color = color + np.array([1.0, 0.93, 0.8]) * glow[:, None]
    cover = look["clouds"]
    if cover > 0:
        rising = up > 0.005
        dist = np.where(rising, (look["cloud_height"] - camera[2]) / np.maximum(up, 0.005), 0.0)
        cx, cy = camera[0] + dirs[:, 0] * dist, camera[1] + dirs[:, 1] * dist
        density = fbm(cx, cy, look["cloud_cell"], seed + 21, dist * pixel_angle / np.maximum(up, 0.05), 4)
        cloud = np.clip((density - (1 - cover) * 0.75 - 0.2) / 0.2, 0.0, 1.0) * np.clip(up * 6, 0, 1) * rising
        cloud_tone = np.array([0.96, 0.96, 0.97]) * (0.75 + 0.25 * density)[:, None] * (
            0.8 + 0.3 * look["sun_strength"])
        color = _mix(color, _mix(cloud_tone, look["haze"][None], 1 - np.clip(up * 4, 0, 1)), cloud)
    return color


def water_color(base: np.ndarray, dirs: np.ndarray, sun: np.ndarray, look: dict[str, Any], camera: np.ndarray,
                pixel_angle: float, seed: int) -> np.ndarray:
    """Water: its own colour plus the sky reflected with Schlick's Fresnel term and a sun glint."""
    reflected = dirs * np.array([1.0, 1.0, -1.0])
    sky = sky_color(reflected, sun, look, camera, pixel_angle, seed)
    cos_i = np.clip(-dirs[:, 2], 0.0, 1.0)
    fresnel = 0.02 + 0.98 * (1 - cos_i) ** 5
    glint = np.clip(reflected @ sun, 0, 1) ** 300 * 2.0 * look["sun_strength"]
    return base * (1 - fresnel[:, None]) + sky * fresnel[:, None] + glint[:, None]


def camera_effects(rgb: np.ndarray, look: dict[str, Any], rng: np.random.Generator) -> np.ndarray:
    """Exposure, white balance, gamma, vignetting, blur, sensor noise and JPEG artefacts; float ``[H, W, 3]`` in."""
    height, width = rgb.shape[:2]
    image = rgb * (look["exposure"] * look["white_balance"])
    yy, xx = np.meshgrid((np.arange(height) + 0.5) / height - 0.5, (np.arange(width) + 0.5) / width - 0.5,
                         indexing="ij")
    image = image * (1 - look["vignette"] * (xx ** 2 + yy ** 2) * 2)[..., None]
    image = np.clip(image, 0.0, 1.0) ** look["gamma"]
    if look["blur"] > 0:
        image = cv2.GaussianBlur(image.astype(np.float32), (0, 0), look["blur"])
    image = image + rng.normal(0.0, look["noise"], image.shape)
    out = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if look["jpeg"]:
        ok, buffer = cv2.imencode(".jpg", np.ascontiguousarray(out[..., ::-1]),
                                  [cv2.IMWRITE_JPEG_QUALITY, look["jpeg"]])
        if ok:
            out = np.ascontiguousarray(cv2.imdecode(buffer, cv2.IMREAD_COLOR)[..., ::-1])
    return out
