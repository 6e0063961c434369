"""Scene families: random worlds in metres, objects (boxes, gabled houses, trees, vehicles, people) on a ground layout.

Every family is sampled by vectorised numpy from one ``numpy.random.Generator``, so a scene depends
on the generator state only. The ground is an infinite plane at ``z = 0`` (it reaches the horizon);
what covers it (roads, lots, fields, water, forest floor) is a function of ``(x, y)`` described by
``Scene.layout`` and evaluated per pixel by :mod:`.shading`. Objects are axis-aligned in the world;
the camera's yaw turns the view instead. Metric sizes are real ones: cars 4.2-4.9 m, people 1.6-1.9 m,
floors 2.8-4.2 m, lanes 3-4 m, dashes 3 m every 9 m, parking stalls 2.6 m, containers 12.2 x 2.44 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dapm_lightning.data.synthetic.noise import ihash, value_noise

SKY, GROUND, BUILDING, TREE, VEHICLE, PERSON, WATER = 0, 1, 2, 3, 4, 5, 6
"""Values of the hit map :func:`render_scene` returns with each image (GROUND and WATER are the plane z = 0)."""
CLASS_NAMES = ("sky", "ground", "building", "tree", "vehicle", "person", "water")

BOX, GABLE_X, GABLE_Y, BLOB, CONE = 0, 1, 2, 3, 4
"""Primitive shapes: box, house with its roof ridge along x or y, rounded tree crown, cone (conifer, canopy)."""

(M_FACADE, M_GLASS, M_HOUSE, M_HALL, M_UNIT, M_CAR, M_PERSON, M_TREE, M_CONTAINER, M_BOAT,
 M_CONIFER) = range(11)
"""Materials of objects (see :mod:`.shading`)."""

FAMILIES = ("downtown", "suburb", "industrial", "farmland", "forest", "water")
"""Scene families, each sampled by its own function; ``water`` puts a coast, lake or river in front of the camera."""

LOT_BUILT, LOT_PLAZA, LOT_PARK, LOT_PARKING, LOT_YARD = range(5)

_WALLS = np.array([[0.78, 0.75, 0.70], [0.62, 0.60, 0.58], [0.70, 0.64, 0.55], [0.55, 0.50, 0.46],
                   [0.82, 0.80, 0.76], [0.66, 0.55, 0.47], [0.48, 0.48, 0.50], [0.74, 0.70, 0.62]])
_GLASS = np.array([[0.30, 0.42, 0.50], [0.25, 0.32, 0.38], [0.40, 0.50, 0.55], [0.22, 0.30, 0.30]])
_HOUSE = np.array([[0.92, 0.90, 0.85], [0.88, 0.80, 0.66], [0.80, 0.74, 0.70], [0.70, 0.72, 0.74],
                   [0.86, 0.78, 0.62], [0.66, 0.52, 0.44]])
_TILES = np.array([[0.55, 0.25, 0.18], [0.35, 0.33, 0.33], [0.45, 0.30, 0.22], [0.25, 0.25, 0.27],
                   [0.62, 0.38, 0.26]])
_FLAT_ROOFS = np.array([[0.45, 0.45, 0.44], [0.35, 0.35, 0.36], [0.55, 0.54, 0.50], [0.30, 0.31, 0.33]])
_CARS = np.array([[0.92, 0.92, 0.92], [0.08, 0.08, 0.09], [0.55, 0.56, 0.58], [0.35, 0.36, 0.38],
                  [0.65, 0.10, 0.10], [0.12, 0.22, 0.55], [0.80, 0.80, 0.78], [0.20, 0.35, 0.22]])
_CONTAINERS = np.array([[0.65, 0.18, 0.12], [0.12, 0.30, 0.60], [0.15, 0.45, 0.25], [0.85, 0.50, 0.10],
                        [0.55, 0.55, 0.55], [0.80, 0.78, 0.72]])
_CLOTHES = np.array([[0.1, 0.1, 0.12], [0.8, 0.8, 0.8], [0.6, 0.1, 0.1], [0.1, 0.2, 0.5], [0.4, 0.35, 0.3],
                     [0.85, 0.7, 0.2]])


@dataclass
class Objects:
    """Objects of a scene, one row each (world metres): shape, bounding box, class, material, colours."""

    prim: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int8))
    lo: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    hi: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    eave: np.ndarray = field(default_factory=lambda: np.zeros(0))  # wall top of gabled houses (z)
    cls: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    mat: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    color: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    roof: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    floor_h: np.ndarray = field(default_factory=lambda: np.zeros(0))  # storey height (m) of facades
    window: np.ndarray = field(default_factory=lambda: np.zeros(0))  # window share of the facade width

    def __len__(self) -> int:
        return len(self.prim)

    def select(self, keep: np.ndarray) -> Objects:
        """The rows where ``keep`` is true (or the given indices)."""
        return Objects(**{name: getattr(self, name)[keep] for name in self.__dataclass_fields__})


class _Collector:
    """Accumulates object rows (arrays) and concatenates them once."""

    def __init__(self) -> None:
        self.parts: list[dict[str, np.ndarray]] = []

    def add(self, prim: int | np.ndarray, lo: np.ndarray, hi: np.ndarray, cls: int, mat: int | np.ndarray,
            color: np.ndarray, roof: np.ndarray | None = None, eave: np.ndarray | None = None,
            floor_h: np.ndarray | float = 3.0, window: np.ndarray | float = 0.0) -> None:
        n = len(lo)
        if n == 0:
            return
        color = np.broadcast_to(color, (n, 3))
        self.parts.append({
            "prim": np.broadcast_to(np.asarray(prim, np.int8), (n,)).copy(), "lo": np.asarray(lo, float),
            "hi": np.asarray(hi, float),
            "eave": np.asarray(hi, float)[:, 2].copy() if eave is None else np.broadcast_to(eave, (n,)).astype(float),
            "cls": np.full(n, cls, np.uint8), "mat": np.broadcast_to(np.asarray(mat, np.uint8), (n,)).copy(),
            "color": np.asarray(color, float), "roof": color if roof is None else np.broadcast_to(roof, (n, 3)),
            "floor_h": np.broadcast_to(np.asarray(floor_h, float), (n,)).copy(),
            "window": np.broadcast_to(np.asarray(window, float), (n,)).copy()})

    def objects(self) -> Objects:
        if not self.parts:
            return Objects()
        return Objects(**{k: np.concatenate([p[k] for p in self.parts]) for k in self.parts[0]})


@dataclass(frozen=True)
class Scene:
    """Random content of one picture, in world metres (camera above ``camera_xy``, looking along ``yaw_deg``)."""

    family: str
    camera_xy: tuple[float, float]
    yaw_deg: float
    objects: Objects
    layout: dict[str, Any]
    look: dict[str, Any]
    sun: np.ndarray  # [3] unit vector towards the sun
    texture_seed: int


# ----------------------------------------------------------------------------------------- ground layout helpers

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


def water_mask(x: np.ndarray, y: np.ndarray, water: dict[str, Any] | None) -> tuple[np.ndarray, np.ndarray]:
    """``(is_water, signed distance to the shore in metres, > 0 in the water)`` at ground points."""
    if not water:
        return np.zeros(np.shape(x), bool), np.full(np.shape(x), -1e9)
    px, py = x - water["x"], y - water["y"]
    ca, sa = math.cos(water["angle"]), math.sin(water["angle"])
    along, across = px * ca + py * sa, -px * sa + py * ca
    wobble = (value_noise(along, np.zeros_like(along), water["wobble_cell"], water["seed"]) - 0.5) * water["wobble"]
    if water["kind"] == "coast":
        signed = across + wobble
    elif water["kind"] == "lake":
        signed = water["radius"] + wobble - np.hypot(px, py)
    else:  # river
        centre = water["meander"] * np.sin(along * (2 * math.pi / water["wavelength"]) + water["phase"])
        signed = water["width"] / 2 + wobble * 0.3 - np.abs(across - centre)
    return signed > 0, signed


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


def _on_road(x: np.ndarray, y: np.ndarray,
             grid: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Offsets from the nearest road centre lines (along x and y) and whether a point is on a road."""
    gx = np.mod(x - grid["ox"], grid["bx"])
    gy = np.mod(y - grid["oy"], grid["by"])
    gx = np.where(gx > grid["bx"] / 2, gx - grid["bx"], gx)
    gy = np.where(gy > grid["by"] / 2, gy - grid["by"], gy)
    inside = np.hypot(x - grid["cx"], y - grid["cy"]) < grid["radius"]
    return gx, gy, inside & (np.abs(gx) < grid["road"] / 2), inside & (np.abs(gy) < grid["road"] / 2)


# ------------------------------------------------------------------------------------------------ object helpers

def _trees(out: _Collector, rng: np.random.Generator, x: np.ndarray, y: np.ndarray, radius: tuple[float, float],
           conifer_share: float = 0.0, base: tuple[float, float] = (1.5, 3.0)) -> None:
    n = len(x)
    if n == 0:
        return
    r = rng.uniform(*radius, size=n)
    z0 = rng.uniform(*base, size=n)
    tall = r * 2 * rng.uniform(0.85, 1.25, size=n)
    conifer = rng.random(n) < conifer_share
    tall = np.where(conifer, tall * 2.2, tall)
    r = np.where(conifer, r * 0.8, r)
    green = np.stack([rng.uniform(0.10, 0.26, n), rng.uniform(0.26, 0.42, n), rng.uniform(0.06, 0.16, n)], -1)
    green = np.where(conifer[:, None], green * np.array([0.7, 0.85, 0.9]), green)
    lo = np.stack([x - r, y - r, z0], -1)
    hi = np.stack([x + r, y + r, z0 + tall], -1)
    out.add(np.where(conifer, CONE, BLOB), lo, hi, TREE, np.where(conifer, M_CONIFER, M_TREE), green)


def _cars(out: _Collector, rng: np.random.Generator, x: np.ndarray, y: np.ndarray, along_x: np.ndarray,
          big_share: float = 0.08) -> None:
    n = len(x)
    if n == 0:
        return
    length = rng.uniform(4.2, 4.9, n)
    width = rng.uniform(1.75, 1.9, n)
    height = rng.uniform(1.4, 1.6, n)
    big = rng.random(n) < big_share  # vans, trucks and buses
    length = np.where(big, rng.uniform(6.5, 12.0, n), length)
    width = np.where(big, 2.5, width)
    height = np.where(big, rng.uniform(2.6, 3.4, n), height)
    hx = np.where(along_x, length, width) / 2
    hy = np.where(along_x, width, length) / 2
    color = _CARS[rng.integers(len(_CARS), size=n)] * rng.uniform(0.9, 1.05, (n, 1))
    out.add(BOX, np.stack([x - hx, y - hy, np.full(n, 0.25)], -1), np.stack([x + hx, y + hy, 0.25 + height], -1),
            VEHICLE, M_CAR, np.clip(color, 0, 1))


def _people(out: _Collector, rng: np.random.Generator, x: np.ndarray, y: np.ndarray) -> None:
    n = len(x)
    if n == 0:
        return
    h = rng.uniform(1.6, 1.9, n)
    out.add(BOX, np.stack([x - 0.25, y - 0.2, np.zeros(n)], -1), np.stack([x + 0.25, y + 0.2, h], -1), PERSON,
            M_PERSON, _CLOTHES[rng.integers(len(_CLOTHES), size=n)])


def _road_traffic(out: _Collector, rng: np.random.Generator, grid: dict[str, Any], cam: tuple[float, float],
                  reach: float, count: int, people: int) -> None:
    """Vehicles in the lanes of a street grid and pedestrians on its pavements, near the camera."""
    x = cam[0] + rng.uniform(-reach, reach, count)
    y = cam[1] + rng.uniform(-reach, reach, count)
    gx, gy, road_x, road_y = _on_road(x, y, grid)
    lane = grid["road"] / 4
    vertical = road_x & ~road_y  # a road running along y (constant x)
    horizontal = road_y & ~road_x
    xs = np.where(vertical, x - gx + np.sign(gx + 1e-9) * lane, x)
    ys = np.where(horizontal, y - gy + np.sign(gy + 1e-9) * lane, y)
    keep = vertical | horizontal
    _cars(out, rng, xs[keep], ys[keep], horizontal[keep])
    if people:
        px = cam[0] + rng.uniform(-reach / 2, reach / 2, people)
        py = cam[1] + rng.uniform(-reach / 2, reach / 2, people)
        gx, gy, _, _ = _on_road(px, py, grid)
        half, walk = grid["road"] / 2, grid["walk"]
        on_walk = (((np.abs(gx) > half + 0.3) & (np.abs(gx) < half + walk - 0.3))
                   | ((np.abs(gy) > half + 0.3) & (np.abs(gy) < half + walk - 0.3)))
        inside = np.hypot(px - grid["cx"], py - grid["cy"]) < grid["radius"]
        _people(out, rng, px[on_walk & inside], py[on_walk & inside])


def _parking_cars(out: _Collector, rng: np.random.Generator, x0: float, y0: float, x1: float, y1: float,
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
    _cars(out, rng, gx[keep], gy[keep], np.zeros(int(keep.sum()), bool), big_share=0.03)


# ------------------------------------------------------------------------------------------------------ families

def _downtown(rng: np.random.Generator, cam: tuple[float, float], out: _Collector) -> dict[str, Any]:
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


def _lot_fill(out: _Collector, rng: np.random.Generator, b: dict[str, np.ndarray], cam: tuple[float, float],
              trees_per_park: int) -> None:
    """Trees in parks and plazas, cars in parking lots."""
    near = np.hypot((b["x0"] + b["x1"]) / 2 - cam[0], (b["y0"] + b["y1"]) / 2 - cam[1]) < 700
    for kind, count in ((LOT_PARK, trees_per_park), (LOT_PLAZA, 2)):
        sel = (b["type"] == kind) & near
        owner = np.repeat(np.flatnonzero(sel), count)
        tx = b["x0"][owner] + 4 + rng.random(len(owner)) * np.maximum(b["x1"][owner] - b["x0"][owner] - 8, 0)
        ty = b["y0"][owner] + 4 + rng.random(len(owner)) * np.maximum(b["y1"][owner] - b["y0"][owner] - 8, 0)
        _trees(out, rng, tx, ty, (2.0, 4.5))
    for index in np.flatnonzero((b["type"] == LOT_PARKING) & (np.hypot((b["x0"] + b["x1"]) / 2 - cam[0],
                                                                        (b["y0"] + b["y1"]) / 2 - cam[1]) < 450)):
        _parking_cars(out, rng, b["x0"][index], b["y0"][index], b["x1"][index], b["y1"][index], 0.7, [])


def _suburb(rng: np.random.Generator, cam: tuple[float, float], out: _Collector) -> dict[str, Any]:
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
    color = _HOUSE[rng.integers(len(_HOUSE), size=n)] * rng.uniform(0.92, 1.05, (n, 1))
    roof = _TILES[rng.integers(len(_TILES), size=n)] * rng.uniform(0.85, 1.1, (n, 1))
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
    _trees(out, rng, tx[ok], ty[ok], (1.8, 4.2), conifer_share=0.2)
    car = h & (rng.random(n) < 0.5) & (setback > 5.5)
    cx = np.minimum(hx0 + width + 2.0, lx0 + lot_w - 1.2)
    cy = np.where(side == 0, y0[owner] + setback / 2, y1[owner] - setback / 2)
    _cars(out, rng, cx[car], cy[car], np.zeros(int(car.sum()), bool), big_share=0.0)
    _lot_fill(out, rng, b, cam, trees_per_park=14)
    _road_traffic(out, rng, grid, cam, reach=300, count=250, people=80)
    return {"land": "fields", "grid": grid, "fields": _fields(rng)}


def _industrial(rng: np.random.Generator, cam: tuple[float, float], out: _Collector) -> dict[str, Any]:
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


def _fields(rng: np.random.Generator) -> dict[str, Any]:
    return {"angle": float(rng.uniform(0, math.pi / 2)), "sx": float(rng.uniform(80, 300)),
            "sy": float(rng.uniform(60, 250)), "ox": float(rng.uniform(0, 300)), "oy": float(rng.uniform(0, 300)),
            "seed": int(rng.integers(1 << 30))}


def _line_road(rng: np.random.Generator, cam: tuple[float, float], width: tuple[float, float],
               paved: bool) -> dict[str, Any]:
    angle = float(rng.uniform(0, math.pi))
    offset = float(rng.uniform(-150, 150))
    return {"x": cam[0] - math.sin(angle) * offset, "y": cam[1] + math.cos(angle) * offset, "angle": angle,
            "width": float(rng.uniform(*width)), "paved": paved}


def _road_distance(x: np.ndarray, y: np.ndarray, road: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(signed distance across a straight road, position along it)."""
    ca, sa = math.cos(road["angle"]), math.sin(road["angle"])
    px, py = x - road["x"], y - road["y"]
    return -px * sa + py * ca, px * ca + py * sa


def _farmland(rng: np.random.Generator, cam: tuple[float, float], out: _Collector) -> dict[str, Any]:
    fields = _fields(rng)
    road = _line_road(rng, cam, (5, 7.5), True)
    # farmsteads: a house, a barn, sheds and trees
    n = int(rng.integers(2, 7))
    fx = cam[0] + rng.uniform(-900, 900, n)
    fy = cam[1] + rng.uniform(-900, 900, n)
    across, _ = _road_distance(fx, fy, road)
    fy = np.where(np.abs(across) < 30, fy + 60, fy)
    w, d = rng.uniform(9, 13, n), rng.uniform(7, 10, n)
    walls = rng.integers(1, 3, n) * 2.8 + 0.4
    out.add(GABLE_X, np.stack([fx, fy, np.zeros(n)], -1), np.stack([fx + w, fy + d, walls + rng.uniform(2, 4, n)], -1),
            BUILDING, M_HOUSE, _HOUSE[rng.integers(len(_HOUSE), size=n)], _TILES[rng.integers(len(_TILES), size=n)],
            eave=walls, floor_h=2.8, window=0.35)
    bw, bd = rng.uniform(18, 35, n), rng.uniform(10, 18, n)
    bx0, by0 = fx + rng.uniform(-40, 20, n), fy + d + rng.uniform(8, 20, n)
    bwall = rng.uniform(5, 9, n)
    barn_color = np.array([[0.55, 0.2, 0.15], [0.6, 0.6, 0.58], [0.45, 0.35, 0.25]])[rng.integers(3, size=n)]
    out.add(GABLE_Y, np.stack([bx0, by0, np.zeros(n)], -1),
            np.stack([bx0 + bw, by0 + bd, bwall + rng.uniform(3, 6, n)], -1), BUILDING, M_HALL, barn_color,
            _TILES[rng.integers(len(_TILES), size=n)], eave=bwall, floor_h=5.0, window=0.1)
    owner = np.repeat(np.arange(n), 8)
    _trees(out, rng, fx[owner] + rng.uniform(-30, 45, len(owner)), fy[owner] + rng.uniform(-25, -3, len(owner)),
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
    across, _ = _road_distance(hx, hy, road)
    near_road = np.abs(across) < road["width"] / 2 + 3
    _trees(out, rng, hx[~near_road], hy[~near_road], (2.5, 4.5), conifer_share=0.1)
    # traffic on the road
    m = int(rng.integers(4, 25))
    along = rng.uniform(-600, 600, m)
    lane = np.where(rng.random(m) < 0.5, -1, 1) * road["width"] / 4
    ca_r, sa_r = math.cos(road["angle"]), math.sin(road["angle"])
    cx = road["x"] + along * ca_r - lane * sa_r
    cy = road["y"] + along * sa_r + lane * ca_r
    along_x = abs(ca_r) > abs(sa_r)
    _cars(out, rng, cx, cy, np.full(m, along_x), big_share=0.2)
    return {"land": "fields", "fields": fields, "road": road}


def _forest(rng: np.random.Generator, cam: tuple[float, float], out: _Collector) -> dict[str, Any]:
    road = _line_road(rng, cam, (4, 6.5), bool(rng.random() < 0.5))
    seed = int(rng.integers(1 << 30))
    conifer = float(rng.uniform(0.0, 1.0))
    clearing = float(rng.uniform(0.62, 0.8))

    def open_ground(x: np.ndarray, y: np.ndarray, margin: float) -> np.ndarray:
        across, _ = _road_distance(x, y, road)
        return (np.abs(across) < road["width"] / 2 + margin) | (value_noise(x, y, 160.0, seed) > clearing)

    spacing = float(rng.uniform(5.5, 8.0))
    reach = 200.0
    axis = np.arange(-reach, reach, spacing)
    gx, gy = np.meshgrid(axis, axis)
    gx = gx.ravel() + cam[0] + rng.uniform(-spacing / 2, spacing / 2, gx.size)
    gy = gy.ravel() + cam[1] + rng.uniform(-spacing / 2, spacing / 2, gy.size)
    near = np.hypot(gx - cam[0], gy - cam[1]) < reach
    keep = near & ~open_ground(gx, gy, 2.0)
    _trees(out, rng, gx[keep], gy[keep], (2.2, 4.0), conifer_share=conifer, base=(2.0, 5.0))
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


_SAMPLERS = {"downtown": _downtown, "suburb": _suburb, "industrial": _industrial, "farmland": _farmland,
             "forest": _forest}


def _water(rng: np.random.Generator, cam: tuple[float, float], yaw: float, big: bool) -> dict[str, Any]:
    """A coast, lake or river placed ahead of the camera (``big``) or anywhere nearby (a river through town)."""
    fwd = np.array([math.cos(yaw), math.sin(yaw)])
    kind = str(rng.choice(["coast", "lake", "river"])) if big else "river"
    ahead = float(rng.uniform(-50, 400)) if big else float(rng.uniform(-300, 600))
    x, y = cam[0] + fwd[0] * ahead, cam[1] + fwd[1] * ahead
    common = {"kind": kind, "seed": int(rng.integers(1 << 30)), "wobble": float(rng.uniform(10, 80)),
              "wobble_cell": float(rng.uniform(80, 300))}
    if kind == "coast":
        angle = yaw - math.pi / 2 + float(rng.uniform(-0.6, 0.6))  # "across" > 0 lies ahead of the camera
        return {**common, "x": x, "y": y, "angle": angle}
    if kind == "lake":
        radius = float(rng.uniform(150, 600))
        return {**common, "x": x + fwd[0] * radius * 0.8, "y": y + fwd[1] * radius * 0.8, "angle": 0.0,
                "radius": radius}
    return {**common, "x": x, "y": y, "angle": yaw + math.pi / 2 + float(rng.uniform(-0.5, 0.5)),
            "width": float(rng.uniform(30, 200) if big else rng.uniform(25, 80)),
            "meander": float(rng.uniform(0, 80)), "wavelength": float(rng.uniform(300, 1200)),
            "phase": float(rng.uniform(0, 2 * math.pi))}


def _boats(out: _Collector, rng: np.random.Generator, water: dict[str, Any], cam: tuple[float, float]) -> None:
    n = 60
    x = cam[0] + rng.uniform(-700, 700, n)
    y = cam[1] + rng.uniform(-700, 700, n)
    inside, signed = water_mask(x, y, water)
    keep = inside & (signed > 15) & (rng.random(n) < 0.4)
    x, y = x[keep], y[keep]
    m = len(x)
    length = np.exp(rng.uniform(math.log(5), math.log(30), m))
    width = length * rng.uniform(0.28, 0.38, m)
    along_x = rng.random(m) < 0.5
    hx, hy = np.where(along_x, length, width) / 2, np.where(along_x, width, length) / 2
    color = np.array([[0.92, 0.92, 0.9], [0.7, 0.15, 0.1], [0.15, 0.2, 0.35]])[rng.integers(3, size=m)]
    out.add(BOX, np.stack([x - hx, y - hy, np.zeros(m)], -1), np.stack([x + hx, y + hy, 0.1 * length + 0.6], -1),
            VEHICLE, M_BOAT, color)


def _look(rng: np.random.Generator) -> dict[str, Any]:
    """Appearance of one picture: sun, sky, haze, clouds and the camera's processing."""
    overcast = rng.random() < 0.2
    return {
        "sun_strength": float(rng.uniform(0.25, 0.5) if overcast else rng.uniform(0.75, 1.1)),
        "ambient": float(rng.uniform(0.5, 0.7) if overcast else rng.uniform(0.28, 0.45)),
        "haze": np.clip(np.array([0.74, 0.79, 0.86]) + rng.uniform(-0.07, 0.07, 3), 0, 1),
        "visibility": float(math.exp(rng.uniform(math.log(1500), math.log(30000)))),
        "zenith": np.clip(np.array([0.22, 0.42, 0.82]) + rng.uniform(-0.08, 0.08, 3), 0, 1),
        "clouds": float(rng.uniform(0.5, 0.95) if overcast else (0.0 if rng.random() < 0.3 else rng.uniform(0, 0.7))),
        "cloud_cell": float(rng.uniform(300, 1500)),
        "cloud_height": float(rng.uniform(1500, 3000)),
        "exposure": float(rng.uniform(0.8, 1.25)),
        "white_balance": rng.uniform(0.93, 1.07, 3),
        "gamma": float(rng.uniform(0.9, 1.1)),
        "vignette": float(rng.uniform(0.0, 0.35)),
        "blur": 0.0 if rng.random() < 0.5 else float(rng.uniform(0.3, 1.0)),
        "noise": float(rng.uniform(0.0, 0.03)),
        "jpeg": 0 if rng.random() < 0.4 else int(rng.integers(35, 96)),
        "grass": np.clip(np.array([0.30, 0.42, 0.18]) + rng.uniform(-0.06, 0.06, 3), 0, 1),
    }


def normalize_families(families: dict[str, float] | str | None) -> dict[str, float]:
    """Family weights as ``{name: share}`` (summing to 1) from a dict or ``"downtown=2,suburb=1"`` (default: equal)."""
    if families is None:
        weights = dict.fromkeys(FAMILIES, 1.0)
    elif isinstance(families, str):
        weights = {}
        for item in filter(None, (part.strip() for part in families.split(","))):
            name, _, value = item.partition("=")
            weights[name.strip()] = float(value) if value else 1.0
    else:
        weights = {str(k): float(v) for k, v in families.items()}
    unknown = sorted(set(weights) - set(FAMILIES))
    if unknown:
        raise ValueError(f"unknown scene famil{'y' if len(unknown) == 1 else 'ies'} {unknown}; choose from {FAMILIES}")
    if any(v < 0 or not math.isfinite(v) for v in weights.values()) or sum(weights.values()) <= 0:
        raise ValueError(f"family weights must be finite, >= 0 and not all 0, got {weights}")
    total = sum(weights.values())
    return {name: weights.get(name, 0.0) / total for name in FAMILIES if weights.get(name, 0.0) > 0}


def draw_family(rng: np.random.Generator, families: dict[str, float] | str | None = None) -> str:
    """A family drawn with the given weights (one uniform number from ``rng``)."""
    weights = normalize_families(families)
    names = list(weights)
    edges = np.cumsum([weights[n] for n in names])
    return names[min(int(np.searchsorted(edges, rng.random() * edges[-1], side="right")), len(names) - 1)]


def sample_scene(rng: np.random.Generator, family: str | None = None,
                 families: dict[str, float] | str | None = None) -> Scene:
    """One random scene: of ``family``, or of a family drawn with the weights ``families`` (default: all equal)."""
    if family is None:
        family = draw_family(rng, families)
    elif family not in FAMILIES:
        raise ValueError(f"unknown scene family {family!r}; choose from {FAMILIES}")
    cam = (float(rng.uniform(-400, 400)), float(rng.uniform(-400, 400)))
    yaw_deg = float(round(rng.uniform(-180, 180), 2))
    out = _Collector()
    base = str(rng.choice(["suburb", "farmland", "forest"])) if family == "water" else family
    layout = _SAMPLERS[base](rng, cam, out)
    water = None
    if family == "water":
        water = _water(rng, cam, math.radians(yaw_deg), big=True)
    elif family in ("downtown", "suburb", "industrial", "farmland") and rng.random() < 0.12:
        water = _water(rng, cam, math.radians(yaw_deg), big=False)
    if water is not None:
        _boats(out, rng, water, cam)
    objects = out.objects()
    if water is not None and len(objects):  # nothing but boats stands in the water
        corners = [(objects.lo[:, 0], objects.lo[:, 1]), (objects.hi[:, 0], objects.hi[:, 1]),
                   (objects.lo[:, 0], objects.hi[:, 1]), (objects.hi[:, 0], objects.lo[:, 1])]
        wet = np.zeros(len(objects), bool)
        for cx, cy in corners:
            wet |= water_mask(cx, cy, water)[1] > -3
        objects = objects.select(~wet | (objects.mat == M_BOAT))
    layout["water"] = water
    elevation = math.radians(rng.uniform(8, 75))
    azimuth = rng.uniform(0, 2 * math.pi)
    sun = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                    math.sin(elevation)])
    return Scene(family, cam, yaw_deg, objects, layout, _look(rng), sun, int(rng.integers(1 << 30)))
