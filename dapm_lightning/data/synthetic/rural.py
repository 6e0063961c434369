"""Country families: farmland (fields, farmsteads, hedgerows) and forest, each crossed by a straight road.

Fields (``layout["fields"]``) are a rotated lattice of 60-300 m plots; a road (``layout["road"]``)
is a straight band through the camera's neighbourhood, paved (lines every 9 m) or dirt.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dapm_lightning.data.synthetic.noise import ihash, value_noise
from dapm_lightning.data.synthetic.objects import (
    BUILDING,
    CONE,
    GABLE_X,
    GABLE_Y,
    HOUSE_WALLS,
    M_CONIFER,
    M_HALL,
    M_HOUSE,
    ROOF_TILES,
    TREE,
    Collector,
    add_cars,
    add_trees,
)


def field_layout(rng: np.random.Generator) -> dict[str, Any]:
    """A lattice of fields (``layout["fields"]``), rotated, with plots of random size (also beyond suburbs)."""
    return {"angle": float(rng.uniform(0, math.pi / 2)), "sx": float(rng.uniform(80, 300)),
            "sy": float(rng.uniform(60, 250)), "ox": float(rng.uniform(0, 300)), "oy": float(rng.uniform(0, 300)),
            "seed": int(rng.integers(1 << 30))}


def _line_road(rng: np.random.Generator, cam: tuple[float, float], width: tuple[float, float],
               paved: bool) -> dict[str, Any]:
    angle = float(rng.uniform(0, math.pi))
    offset = float(rng.uniform(-150, 150))
    return {"x": cam[0] - math.sin(angle) * offset, "y": cam[1] + math.cos(angle) * offset, "angle": angle,
            "width": float(rng.uniform(*width)), "paved": paved}


def road_distance(x: np.ndarray, y: np.ndarray, road: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(signed distance across a straight road, position along it)."""
    ca, sa = math.cos(road["angle"]), math.sin(road["angle"])
    px, py = x - road["x"], y - road["y"]
    return -px * sa + py * ca, px * ca + py * sa


def farmland(rng: np.random.Generator, cam: tuple[float, float], out: Collector) -> dict[str, Any]:
    """Fields with hedgerows along some of their edges, farmsteads (house, barn, trees), a paved road."""
    fields = field_layout(rng)
    road = _line_road(rng, cam, (5, 7.5), True)
    # farmsteads: a house, a barn, sheds and trees
    n = int(rng.integers(2, 7))
    fx = cam[0] + rng.uniform(-900, 900, n)
    fy = cam[1] + rng.uniform(-900, 900, n)
    across, _ = road_distance(fx, fy, road)
    fy = np.where(np.abs(across) < 30, fy + 60, fy)
    w, d = rng.uniform(9, 13, n), rng.uniform(7, 10, n)
    walls = rng.integers(1, 3, n) * 2.8 + 0.4
    out.add(GABLE_X, np.stack([fx, fy, np.zeros(n)], -1), np.stack([fx + w, fy + d, walls + rng.uniform(2, 4, n)], -1),
            BUILDING, M_HOUSE, HOUSE_WALLS[rng.integers(len(HOUSE_WALLS), size=n)],
            ROOF_TILES[rng.integers(len(ROOF_TILES), size=n)], eave=walls, floor_h=2.8, window=0.35)
    bw, bd = rng.uniform(18, 35, n), rng.uniform(10, 18, n)
    bx0, by0 = fx + rng.uniform(-40, 20, n), fy + d + rng.uniform(8, 20, n)
    bwall = rng.uniform(5, 9, n)
    barn_color = np.array([[0.55, 0.2, 0.15], [0.6, 0.6, 0.58], [0.45, 0.35, 0.25]])[rng.integers(3, size=n)]
    out.add(GABLE_Y, np.stack([bx0, by0, np.zeros(n)], -1),
            np.stack([bx0 + bw, by0 + bd, bwall + rng.uniform(3, 6, n)], -1), BUILDING, M_HALL, barn_color,
            ROOF_TILES[rng.integers(len(ROOF_TILES), size=n)], eave=bwall, floor_h=5.0, window=0.1)
    owner = np.repeat(np.arange(n), 8)
    add_trees(out, rng, fx[owner] + rng.uniform(-30, 45, len(owner)), fy[owner] + rng.uniform(-25, -3, len(owner)),
           (2.5, 5.0), conifer_share=0.2)
    # hedgerows along some field edges
    ca, sa = math.cos(fields["angle"]), math.sin(fields["angle"])
    reach = 600.0
    cu, cv = cam[0] * ca + cam[1] * sa, -cam[0] * sa + cam[1] * ca  # the camera in the field frame
    lines = []
    for axis, spacing, offset, centre, other in ((0, fields["sx"], fields["ox"], cu, cv),
                                                  (1, fields["sy"], fields["oy"], cv, cu)):
        ks = np.arange(math.floor((centre - reach - offset) / spacing), math.ceil((centre + reach - offset) / spacing))
        steps = other + np.arange(-reach, reach, 7.0)
        kk, ss = np.meshgrid(ks, steps, indexing="ij")
        kk, ss = kk.ravel(), ss.ravel()
        keep = ihash(kk, np.floor(ss / 120).astype(np.int64), fields["seed"] + axis) < 0.3
        edge = offset + kk * spacing
        u, v = (edge, ss) if axis == 0 else (ss, edge)
        lines.append((u[keep] * ca - v[keep] * sa, u[keep] * sa + v[keep] * ca))
    hx = np.concatenate([p[0] for p in lines]) + rng.uniform(-1, 1, sum(len(p[0]) for p in lines))
    hy = np.concatenate([p[1] for p in lines]) + rng.uniform(-1, 1, len(hx))
    across, _ = road_distance(hx, hy, road)
    near_road = np.abs(across) < road["width"] / 2 + 3
    add_trees(out, rng, hx[~near_road], hy[~near_road], (2.5, 4.5), conifer_share=0.1)
    # traffic on the road
    m = int(rng.integers(4, 25))
    along = rng.uniform(-600, 600, m)
    lane = np.where(rng.random(m) < 0.5, -1, 1) * road["width"] / 4
    ca_r, sa_r = math.cos(road["angle"]), math.sin(road["angle"])
    cx = road["x"] + along * ca_r - lane * sa_r
    cy = road["y"] + along * sa_r + lane * ca_r
    along_x = abs(ca_r) > abs(sa_r)
    add_cars(out, rng, cx, cy, np.full(m, along_x), big_share=0.2)
    return {"land": "fields", "fields": fields, "road": road}


def forest(rng: np.random.Generator, cam: tuple[float, float], out: Collector) -> dict[str, Any]:
    """Trees near the camera, canopy cones farther out, clearings and a paved or dirt road through it."""
    road = _line_road(rng, cam, (4, 6.5), bool(rng.random() < 0.5))
    seed = int(rng.integers(1 << 30))
    conifer = float(rng.uniform(0.0, 1.0))
    clearing = float(rng.uniform(0.62, 0.8))

    def open_ground(x: np.ndarray, y: np.ndarray, margin: float) -> np.ndarray:
        across, _ = road_distance(x, y, road)
        return (np.abs(across) < road["width"] / 2 + margin) | (value_noise(x, y, 160.0, seed) > clearing)

    spacing = float(rng.uniform(5.5, 8.0))
    reach = 200.0
    axis = np.arange(-reach, reach, spacing)
    gx, gy = np.meshgrid(axis, axis)
    gx = gx.ravel() + cam[0] + rng.uniform(-spacing / 2, spacing / 2, gx.size)
    gy = gy.ravel() + cam[1] + rng.uniform(-spacing / 2, spacing / 2, gy.size)
    near = np.hypot(gx - cam[0], gy - cam[1]) < reach
    keep = near & ~open_ground(gx, gy, 2.0)
    add_trees(out, rng, gx[keep], gy[keep], (2.2, 4.0), conifer_share=conifer, base=(2.0, 5.0))
    # beyond: canopy as wide cones standing on the ground (crowns merge at a distance), coarser farther out
    for spacing, inner, outer, radius, top in ((22.0, reach, 520.0, (12, 15), (16, 26)),
                                               (44.0, 520.0, 1100.0, (24, 29), (18, 28))):
        axis = np.arange(-outer, outer, spacing)
        fx, fy = np.meshgrid(axis, axis)
        fx = fx.ravel() + cam[0] + rng.uniform(-spacing / 4, spacing / 4, fx.size)
        fy = fy.ravel() + cam[1] + rng.uniform(-spacing / 4, spacing / 4, fy.size)
        dist = np.hypot(fx - cam[0], fy - cam[1])
        keep = (dist >= inner) & (dist < outer) & ~open_ground(fx, fy, 10.0)
        k = int(keep.sum())
        r = rng.uniform(*radius, k)
        tops = rng.uniform(*top, k)
        green = np.stack([rng.uniform(0.1, 0.2, k), rng.uniform(0.24, 0.36, k), rng.uniform(0.07, 0.14, k)], -1)
        out.add(CONE, np.stack([fx[keep] - r, fy[keep] - r, np.zeros(k)], -1),
                np.stack([fx[keep] + r, fy[keep] + r, tops], -1), TREE, M_CONIFER, green)
    return {"land": "forest", "road": road, "clearing": {"seed": seed, "level": clearing}}


