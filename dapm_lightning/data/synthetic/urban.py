"""Town families on a street grid: downtown, suburb and industrial estate, with their traffic.

A street grid (``layout["grid"]``) is a lattice of blocks within a radius of a town centre; roads
are 7-18 m wide (lanes 3-4 m, dashes 3 m every 9 m), each block is a lot of one use (:func:`lot_type`,
shared with the ground shader): built, plaza, park, parking (stalls 2.6 m) or yard (containers
12.2 x 2.44 m). Downtown floors are 3.2-4.2 m, houses' 2.8 m.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dapm_lightning.data.synthetic.noise import ihash
from dapm_lightning.data.synthetic.objects import (
    BOX,
    BUILDING,
    GABLE_X,
    GABLE_Y,
    HOUSE_WALLS,
    M_CONTAINER,
    M_FACADE,
    M_GLASS,
    M_HALL,
    M_HOUSE,
    M_UNIT,
    ROOF_TILES,
    Collector,
    add_cars,
    add_people,
    add_trees,
)
from dapm_lightning.data.synthetic.rural import field_layout

LOT_BUILT, LOT_PLAZA, LOT_PARK, LOT_PARKING, LOT_YARD = range(5)
"""Uses of the blocks of a street grid (:func:`lot_type`)."""

_WALLS = np.array([[0.78, 0.75, 0.70], [0.62, 0.60, 0.58], [0.70, 0.64, 0.55], [0.55, 0.50, 0.46],
                   [0.82, 0.80, 0.76], [0.66, 0.55, 0.47], [0.48, 0.48, 0.50], [0.74, 0.70, 0.62]])
_GLASS = np.array([[0.30, 0.42, 0.50], [0.25, 0.32, 0.38], [0.40, 0.50, 0.55], [0.22, 0.30, 0.30]])
_FLAT_ROOFS = np.array([[0.45, 0.45, 0.44], [0.35, 0.35, 0.36], [0.55, 0.54, 0.50], [0.30, 0.31, 0.33]])
_CONTAINERS = np.array([[0.65, 0.18, 0.12], [0.12, 0.30, 0.60], [0.15, 0.45, 0.25], [0.85, 0.50, 0.10],
                        [0.55, 0.55, 0.55], [0.80, 0.78, 0.72]])


# ------------------------------------------------------------------------------------------------- street grid

def lot_type(i: np.ndarray, j: np.ndarray, grid: dict[str, Any]) -> np.ndarray:
    """Use of block ``(i, j)`` of a street grid (LOT_*), the same for the object sampler and the ground shader."""
    u = ihash(i, j, grid["seed"])
    kinds = np.full(np.shape(u), LOT_BUILT, np.int64)
    edge = 0.0
    for kind, share in ((LOT_PLAZA, grid["plaza"]), (LOT_PARK, grid["park"]), (LOT_PARKING, grid["parking"]),
                        (LOT_YARD, grid["yard"])):
        kinds = np.where((u >= edge) & (u < edge + share), kind, kinds)
        edge += share
    return kinds


def _blocks(grid: dict[str, Any], centre: tuple[float, float], radius: float) -> dict[str, np.ndarray]:
    """Blocks of a street grid within ``radius`` of ``centre``: indices and lot rectangles (world)."""
    bx, by, ox, oy = grid["bx"], grid["by"], grid["ox"], grid["oy"]
    i0, i1 = math.floor((centre[0] - radius - ox) / bx), math.floor((centre[0] + radius - ox) / bx)
    j0, j1 = math.floor((centre[1] - radius - oy) / by), math.floor((centre[1] + radius - oy) / by)
    ii, jj = np.meshgrid(np.arange(i0, i1 + 1), np.arange(j0, j1 + 1), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    cx, cy = ox + (ii + 0.5) * bx, oy + (jj + 0.5) * by
    keep = (np.hypot(cx - centre[0], cy - centre[1]) < radius) & (np.hypot(cx - grid["cx"], cy - grid["cy"])
                                                                   < grid["radius"])
    ii, jj = ii[keep], jj[keep]
    margin = grid["road"] / 2 + grid["walk"]
    return {"i": ii, "j": jj, "x0": ox + ii * bx + margin, "x1": ox + (ii + 1) * bx - margin,
            "y0": oy + jj * by + margin, "y1": oy + (jj + 1) * by - margin, "type": lot_type(ii, jj, grid)}


def _grid(rng: np.random.Generator, cam: tuple[float, float], bx: tuple[float, float], by: tuple[float, float],
          road: tuple[float, float], walk: tuple[float, float], radius: tuple[float, float],
          shares: dict[str, float], marks: bool, built_ground: str) -> dict[str, Any]:
    return {"bx": float(rng.uniform(*bx)), "by": float(rng.uniform(*by)), "ox": float(rng.uniform(0, 500)),
            "oy": float(rng.uniform(0, 500)), "road": float(rng.uniform(*road)), "walk": float(rng.uniform(*walk)),
            "radius": float(rng.uniform(*radius)), "cx": cam[0] + float(rng.uniform(-150, 150)),
            "cy": cam[1] + float(rng.uniform(-150, 150)), "marks": marks, "built_ground": built_ground,
            "seed": int(rng.integers(1 << 30)), **{k: shares.get(k, 0.0) for k in ("plaza", "park", "parking", "yard")}}


def on_road(x: np.ndarray, y: np.ndarray,
            grid: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Offsets from the nearest road centre lines (along x and y) and whether a point is on a road."""
    gx = np.mod(x - grid["ox"], grid["bx"])
    gy = np.mod(y - grid["oy"], grid["by"])
    gx = np.where(gx > grid["bx"] / 2, gx - grid["bx"], gx)
    gy = np.where(gy > grid["by"] / 2, gy - grid["by"], gy)
    inside = np.hypot(x - grid["cx"], y - grid["cy"]) < grid["radius"]
    return gx, gy, inside & (np.abs(gx) < grid["road"] / 2), inside & (np.abs(gy) < grid["road"] / 2)


def _road_traffic(out: Collector, rng: np.random.Generator, grid: dict[str, Any], cam: tuple[float, float],
                  reach: float, count: int, people: int) -> None:
    """Vehicles in the lanes of a street grid and pedestrians on its pavements, near the camera."""
    x = cam[0] + rng.uniform(-reach, reach, count)
    y = cam[1] + rng.uniform(-reach, reach, count)
    gx, gy, road_x, road_y = on_road(x, y, grid)
    lane = grid["road"] / 4
    vertical = road_x & ~road_y  # a road running along y (constant x)
    horizontal = road_y & ~road_x
    xs = np.where(vertical, x - gx + np.sign(gx + 1e-9) * lane, x)
    ys = np.where(horizontal, y - gy + np.sign(gy + 1e-9) * lane, y)
    keep = vertical | horizontal
    add_cars(out, rng, xs[keep], ys[keep], horizontal[keep])
    if people:
        px = cam[0] + rng.uniform(-reach / 2, reach / 2, people)
        py = cam[1] + rng.uniform(-reach / 2, reach / 2, people)
        gx, gy, _, _ = on_road(px, py, grid)
        half, walk = grid["road"] / 2, grid["walk"]
        on_walk = (((np.abs(gx) > half + 0.3) & (np.abs(gx) < half + walk - 0.3))
                   | ((np.abs(gy) > half + 0.3) & (np.abs(gy) < half + walk - 0.3)))
        inside = np.hypot(px - grid["cx"], py - grid["cy"]) < grid["radius"]
        add_people(out, rng, px[on_walk & inside], py[on_walk & inside])


def _parking_cars(out: Collector, rng: np.random.Generator, x0: float, y0: float, x1: float, y1: float,
                  occupancy: float, avoid: list[tuple[float, float, float, float]]) -> None:
    """Cars in the stalls of a parking lot (stall rows every 16 m: 5 m stall, 6 m aisle, 5 m stall)."""
    xs = x0 + 1.3 + np.arange(max(0, int((x1 - x0 - 2.6) / 2.6)) + 1) * 2.6
    rows = np.arange(max(0, int((y1 - y0) / 16.0)))
    ys = np.concatenate([y0 + rows * 16.0 + 2.5, y0 + rows * 16.0 + 13.5])
    if not len(xs) or not len(ys):
        return
    gx, gy = np.meshgrid(xs, ys)
    gx, gy = gx.ravel(), gy.ravel()
    keep = (rng.random(len(gx)) < occupancy) & (gy < y1 - 2.5) & (gx < x1 - 1.3)
    for ax0, ay0, ax1, ay1 in avoid:
        keep &= ~((gx > ax0 - 3) & (gx < ax1 + 3) & (gy > ay0 - 3) & (gy < ay1 + 3))
    add_cars(out, rng, gx[keep], gy[keep], np.zeros(int(keep.sum()), bool), big_share=0.03)


# ------------------------------------------------------------------------------------------------------ families

def downtown(rng: np.random.Generator, cam: tuple[float, float], out: Collector) -> dict[str, Any]:
    """Blocks of towers 20-150 m (taller towards the centre, some with setbacks and rooftop units), busy streets."""
    grid = _grid(rng, cam, (55, 95), (45, 85), (10, 18), (2.5, 4.5), (600, 1100),
                 {"plaza": 0.08, "park": 0.07, "parking": 0.05}, True, "concrete")
    b = _blocks(grid, cam, 1100)
    built = b["type"] == LOT_BUILT
    n = int(built.sum())
    x0, x1, y0, y1 = (b[k][built] for k in ("x0", "x1", "y0", "y1"))
    fx, fy = rng.uniform(0.35, 0.65, n), rng.uniform(0.35, 0.65, n)
    xm, ym = x0 + fx * (x1 - x0), y0 + fy * (y1 - y0)
    px0 = np.concatenate([x0, xm, x0, xm])
    px1 = np.concatenate([xm, x1, xm, x1])
    py0 = np.concatenate([y0, y0, ym, ym])
    py1 = np.concatenate([ym, ym, y1, y1])
    m = len(px0)
    gap = rng.uniform(0.0, 2.5, (m, 4))
    keep = rng.random(m) < 0.9
    lo_x, hi_x = px0 + gap[:, 0], px1 - gap[:, 1]
    lo_y, hi_y = py0 + gap[:, 2], py1 - gap[:, 3]
    keep &= (hi_x - lo_x > 8) & (hi_y - lo_y > 8)
    lo_x, hi_x, lo_y, hi_y = lo_x[keep], hi_x[keep], lo_y[keep], hi_y[keep]
    m = len(lo_x)
    dist = np.hypot((lo_x + hi_x) / 2 - grid["cx"], (lo_y + hi_y) / 2 - grid["cy"])
    core = np.exp(-dist / grid["radius"] * 1.5)  # taller towards the centre of the town
    height = np.clip(np.exp(rng.uniform(math.log(20), math.log(150), m)) * (0.55 + 0.9 * core), 20, 150)
    glass = rng.random(m) < 0.35
    color = np.where(glass[:, None], _GLASS[rng.integers(len(_GLASS), size=m)],
                     _WALLS[rng.integers(len(_WALLS), size=m)]) * rng.uniform(0.9, 1.08, (m, 1))
    roof = _FLAT_ROOFS[rng.integers(len(_FLAT_ROOFS), size=m)]
    floor_h = rng.uniform(3.2, 4.2, m)
    window = rng.uniform(0.35, 0.8, m)
    mat = np.where(glass, M_GLASS, M_FACADE)
    # setbacks: some buildings end in a narrower tower (the top stays within 20-150 m)
    s = (rng.random(m) < 0.45) & (hi_x - lo_x > 16) & (hi_y - lo_y > 16)
    inset = rng.uniform(0.15, 0.3, m)[:, None] * np.minimum(hi_x - lo_x, hi_y - lo_y)[:, None]
    top = height
    height = np.where(s, height * rng.uniform(0.45, 0.85, m), height)
    out.add(BOX, np.stack([lo_x, lo_y, np.zeros(m)], -1), np.stack([hi_x, hi_y, height], -1), BUILDING, mat,
            np.clip(color, 0, 1), roof, floor_h=floor_h, window=window)
    out.add(BOX, np.stack([lo_x + inset[:, 0], lo_y + inset[:, 0], height], -1)[s],
            np.stack([hi_x - inset[:, 0], hi_y - inset[:, 0], top], -1)[s], BUILDING, mat[s],
            np.clip(color[s], 0, 1), roof[s], floor_h=floor_h[s], window=window[s])
    # rooftop units on the highest roof
    roof_lo_x = np.where(s, lo_x + inset[:, 0], lo_x)
    roof_hi_x = np.where(s, hi_x - inset[:, 0], hi_x)
    roof_lo_y = np.where(s, lo_y + inset[:, 0], lo_y)
    roof_hi_y = np.where(s, hi_y - inset[:, 0], hi_y)
    roof_z = np.where(s, top, height)
    owner = np.repeat(np.arange(m), 3)
    unit = rng.random(len(owner)) < 0.6
    owner = owner[unit]
    k = len(owner)
    ux, uy, uz = rng.uniform(2, 6, k), rng.uniform(2, 6, k), rng.uniform(1.5, 4, k)
    room_x = roof_hi_x[owner] - roof_lo_x[owner] - ux - 2
    room_y = roof_hi_y[owner] - roof_lo_y[owner] - uy - 2
    fits = (room_x > 0) & (room_y > 0)
    cx = roof_lo_x[owner] + 1 + rng.random(k) * np.maximum(room_x, 0)
    cy = roof_lo_y[owner] + 1 + rng.random(k) * np.maximum(room_y, 0)
    out.add(BOX, np.stack([cx, cy, roof_z[owner]], -1)[fits],
            np.stack([cx + ux, cy + uy, roof_z[owner] + uz], -1)[fits],
            BUILDING, M_UNIT, np.array([0.6, 0.6, 0.6]))
    _lot_fill(out, rng, b, cam, trees_per_park=10)
    _road_traffic(out, rng, grid, cam, reach=350, count=900, people=500)
    return {"land": "grass", "grid": grid}


def _lot_fill(out: Collector, rng: np.random.Generator, b: dict[str, np.ndarray], cam: tuple[float, float],
              trees_per_park: int) -> None:
    """Trees in parks and plazas, cars in parking lots."""
    near = np.hypot((b["x0"] + b["x1"]) / 2 - cam[0], (b["y0"] + b["y1"]) / 2 - cam[1]) < 700
    for kind, count in ((LOT_PARK, trees_per_park), (LOT_PLAZA, 2)):
        sel = (b["type"] == kind) & near
        owner = np.repeat(np.flatnonzero(sel), count)
        tx = b["x0"][owner] + 4 + rng.random(len(owner)) * np.maximum(b["x1"][owner] - b["x0"][owner] - 8, 0)
        ty = b["y0"][owner] + 4 + rng.random(len(owner)) * np.maximum(b["y1"][owner] - b["y0"][owner] - 8, 0)
        add_trees(out, rng, tx, ty, (2.0, 4.5))
    for index in np.flatnonzero((b["type"] == LOT_PARKING) & (np.hypot((b["x0"] + b["x1"]) / 2 - cam[0],
                                                                        (b["y0"] + b["y1"]) / 2 - cam[1]) < 450)):
        _parking_cars(out, rng, b["x0"][index], b["y0"][index], b["x1"][index], b["y1"][index], 0.7, [])


def suburb(rng: np.random.Generator, cam: tuple[float, float], out: Collector) -> dict[str, Any]:
    """Rows of gabled houses with gardens and cars on their lots, quiet streets, fields beyond the town."""
    grid = _grid(rng, cam, (70, 110), (38, 56), (7, 10), (1.2, 2.5), (400, 900), {"park": 0.07, "plaza": 0.02},
                 True, "lawn")
    b = _blocks(grid, cam, 900)
    built = b["type"] == LOT_BUILT
    lot_w = float(rng.uniform(14, 22))
    x0, x1, y0, y1 = (b[k][built] for k in ("x0", "x1", "y0", "y1"))
    per_row = np.maximum(((x1 - x0) // lot_w).astype(int), 0)
    owner = np.repeat(np.arange(len(x0)), per_row * 2)
    slot = np.concatenate([np.arange(2 * c) for c in per_row]) if len(per_row) else np.zeros(0, int)
    side = slot % 2  # 0: facing the road at y0, 1: facing the road at y1
    col = slot // 2
    lx0 = x0[owner] + col * lot_w
    n = len(owner)
    width = np.minimum(rng.uniform(8, 13, n), lot_w - 3)
    depth = rng.uniform(7, 11, n)
    setback = rng.uniform(3, 7, n)
    hx0 = lx0 + rng.uniform(1.0, 2.0, n) + rng.random(n) * np.maximum(lot_w - width - 3, 0)
    hy0 = np.where(side == 0, y0[owner] + setback, y1[owner] - setback - depth)
    half_depth = (y1[owner] - y0[owner]) / 2
    house = (rng.random(n) < 0.9) & (depth + setback < half_depth)
    walls = rng.integers(1, 3, n) * 2.8 + 0.4
    ridge = walls + rng.uniform(1.5, 3.5, n)
    color = HOUSE_WALLS[rng.integers(len(HOUSE_WALLS), size=n)] * rng.uniform(0.92, 1.05, (n, 1))
    roof = ROOF_TILES[rng.integers(len(ROOF_TILES), size=n)] * rng.uniform(0.85, 1.1, (n, 1))
    prim = np.where(width >= depth, GABLE_X, GABLE_Y)
    h = house
    out.add(prim[h], np.stack([hx0, hy0, np.zeros(n)], -1)[h], np.stack([hx0 + width, hy0 + depth, ridge], -1)[h],
            BUILDING, M_HOUSE, np.clip(color[h], 0, 1), np.clip(roof[h], 0, 1), eave=walls[h], floor_h=2.8,
            window=rng.uniform(0.25, 0.45, int(h.sum())))
    # garden trees behind the houses, cars in front
    tree_owner = np.repeat(np.arange(n), 2)
    has_tree = rng.random(len(tree_owner)) < 0.65
    t_own = tree_owner[has_tree]
    tx = lx0[t_own] + rng.uniform(2, lot_w - 2, len(t_own))
    back = np.where(side[t_own] == 0, hy0[t_own] + depth[t_own] + 2, hy0[t_own] - 2)
    ty = back + np.where(side[t_own] == 0, 1, -1) * rng.uniform(0, 5, len(t_own))
    ok = (ty > y0[owner][t_own] + 1) & (ty < y1[owner][t_own] - 1)
    add_trees(out, rng, tx[ok], ty[ok], (1.8, 4.2), conifer_share=0.2)
    car = h & (rng.random(n) < 0.5) & (setback > 5.5)
    cx = np.minimum(hx0 + width + 2.0, lx0 + lot_w - 1.2)
    cy = np.where(side == 0, y0[owner] + setback / 2, y1[owner] - setback / 2)
    add_cars(out, rng, cx[car], cy[car], np.zeros(int(car.sum()), bool), big_share=0.0)
    _lot_fill(out, rng, b, cam, trees_per_park=14)
    _road_traffic(out, rng, grid, cam, reach=300, count=250, people=80)
    return {"land": "fields", "grid": grid, "fields": field_layout(rng)}


def industrial(rng: np.random.Generator, cam: tuple[float, float], out: Collector) -> dict[str, Any]:
    """Large halls with skylights, parking lots and container yards beside them, traffic on the roads."""
    grid = _grid(rng, cam, (120, 220), (100, 180), (12, 18), (0.0, 1.5), (500, 900),
                 {"parking": 0.3, "yard": 0.3, "park": 0.05}, True, "concrete")
    b = _blocks(grid, cam, 900)
    has_hall = b["type"] != LOT_PARK
    idx = np.flatnonzero(has_hall)
    n = len(idx)
    x0, x1, y0, y1 = (b[k][idx] for k in ("x0", "x1", "y0", "y1"))
    fx, fy = rng.uniform(0.4, 0.8, n), rng.uniform(0.45, 0.9, n)
    hx0 = x0 + rng.uniform(3, 8, n)
    hy0 = y0 + rng.uniform(3, 8, n)
    hx1 = np.minimum(hx0 + fx * (x1 - x0), x1 - 3)
    hy1 = np.minimum(hy0 + fy * (y1 - y0), y1 - 3)
    height = rng.uniform(6, 18, n)
    color = np.clip(_WALLS[rng.integers(len(_WALLS), size=n)] * rng.uniform(0.85, 1.15, (n, 1)), 0, 1)
    roof = _FLAT_ROOFS[rng.integers(len(_FLAT_ROOFS), size=n)]
    out.add(BOX, np.stack([hx0, hy0, np.zeros(n)], -1), np.stack([hx1, hy1, height], -1), BUILDING, M_HALL, color, roof,
            floor_h=rng.uniform(4.5, 6.0, n), window=rng.uniform(0.1, 0.3, n))
    # skylight strips across the roofs
    owner = np.repeat(np.arange(n), 6)
    k = np.tile(np.arange(6), n)
    strips = rng.integers(0, 7, n)[owner] > k
    owner, k = owner[strips], k[strips]
    span = (hy1 - hy0)[owner]
    sy = hy0[owner] + (k + 0.5) * span / 7
    out.add(BOX, np.stack([hx0[owner] + 3, sy - 1, height[owner]], -1),
            np.stack([hx1[owner] - 3, sy + 1, height[owner] + 0.9], -1), BUILDING, M_UNIT, np.array([0.75, 0.78, 0.8]))
    cam_d = np.hypot((x0 + x1) / 2 - cam[0], (y0 + y1) / 2 - cam[1])
    kind = b["type"][idx]
    for j in np.flatnonzero((kind == LOT_PARKING) & (cam_d < 500)):  # cars beside the halls
        _parking_cars(out, rng, x0[j], y0[j], x1[j], y1[j], 0.65, [(hx0[j], hy0[j], hx1[j], hy1[j])])
    for j in np.flatnonzero((kind == LOT_YARD) & (cam_d < 600)):  # container stacks beside the halls
        cols = np.arange(int((x1[j] - x0[j] - 4) // 13.0))
        rows = np.arange(int((y1[j] - y0[j] - 4) // 3.2))
        gx, gy = np.meshgrid(x0[j] + 2 + cols * 13.0, y0[j] + 2 + rows * 3.2)
        gx, gy = gx.ravel(), gy.ravel()
        free = ~((gx + 12.2 > hx0[j] - 3) & (gx < hx1[j] + 3) & (gy + 2.44 > hy0[j] - 3) & (gy < hy1[j] + 3))
        free &= rng.random(len(gx)) < 0.6
        gx, gy = gx[free], gy[free]
        levels = rng.integers(1, 4, len(gx))
        for level in range(3):
            sel = levels > level
            m = int(sel.sum())
            out.add(BOX, np.stack([gx[sel], gy[sel], np.full(m, level * 2.6)], -1),
                    np.stack([gx[sel] + 12.2, gy[sel] + 2.44, np.full(m, level * 2.6 + 2.59)], -1), BUILDING,
                    M_CONTAINER, _CONTAINERS[rng.integers(len(_CONTAINERS), size=m)])
    _lot_fill(out, rng, {k: v[~has_hall] for k, v in b.items()}, cam, trees_per_park=8)
    _road_traffic(out, rng, grid, cam, reach=400, count=300, people=20)
    return {"land": "grass", "grid": grid}


