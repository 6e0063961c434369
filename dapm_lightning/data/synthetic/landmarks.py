"""Tall structures outside downtown: tower blocks, office blocks, chimneys, silos, masts.

Towers of 20-150 m were downtown's alone, so a model that never saw downtown took its towers for the
ground behind them (docs/transfer.md, "The grid"). Real towns and countryside put tall things
anywhere: tower blocks among houses, chimneys and silos beside halls, grain silos on farms, masts in
forests. :func:`add_landmarks` stands 3-8 of them (each kind with real sizes) near the camera of most
scenes of every family but downtown, clear of roads, and removes what they would stand in. A dose of
1-4 in a third to a half of the scenes did not change what a model that never saw downtown makes of it;
this one did (docs/transfer.md, "Landmarks").
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dapm_lightning.data.synthetic.objects import (
    BOX,
    BUILDING,
    M_FACADE,
    M_GLASS,
    M_HALL,
    M_UNIT,
    Collector,
    Objects,
)
from dapm_lightning.data.synthetic.rural import road_distance
from dapm_lightning.data.synthetic.urban import on_road

# kind: (footprint x range m, footprint y range m, height range m, material, storey height m, window share)
_KINDS: dict[str, tuple[tuple[float, float], tuple[float, float], tuple[float, float], int, float, float]] = {
    "tower_block": ((16, 40), (12, 20), (24, 75), M_FACADE, 2.9, 0.45),
    "office": ((18, 35), (18, 35), (25, 90), M_GLASS, 3.8, 0.7),
    "chimney": ((3, 6), (3, 6), (35, 120), M_UNIT, 3.0, 0.0),
    "silo": ((6, 12), (6, 12), (15, 40), M_HALL, 5.0, 0.0),
    "mast": ((1.8, 3.5), (1.8, 3.5), (40, 110), M_UNIT, 3.0, 0.0),
}

LANDMARKS: dict[str, tuple[float, dict[str, float]]] = {
    "suburb": (0.95, {"tower_block": 0.7, "office": 0.2, "mast": 0.1}),
    "industrial": (0.95, {"chimney": 0.35, "silo": 0.3, "office": 0.25, "tower_block": 0.1}),
    "farmland": (0.9, {"silo": 0.6, "mast": 0.3, "tower_block": 0.1}),
    "forest": (0.8, {"mast": 0.7, "silo": 0.3}),
}
"""Per family (of the scene's land; water scenes take their base family's): the share of scenes with landmarks and
the weights of the kinds. Downtown has towers of its own."""

_WALLS = np.array([[0.80, 0.78, 0.74], [0.68, 0.64, 0.58], [0.58, 0.56, 0.55], [0.74, 0.66, 0.56],
                   [0.86, 0.84, 0.80], [0.60, 0.50, 0.44]])
_GLASS = np.array([[0.30, 0.42, 0.50], [0.25, 0.32, 0.38], [0.40, 0.50, 0.55]])
_METAL = np.array([[0.62, 0.62, 0.60], [0.72, 0.70, 0.66], [0.55, 0.50, 0.46], [0.78, 0.78, 0.76]])
_ROOFS = np.array([[0.45, 0.45, 0.44], [0.35, 0.35, 0.36], [0.55, 0.54, 0.50]])


def _clear_of_roads(x0: float, y0: float, x1: float, y1: float, layout: dict[str, Any]) -> bool:
    """Whether a footprint stays off the roads: those of a street grid and the country road (4 m from its edge).

    The grid is tested at points every <= 6.7 m (its roads are >= 7 m wide).
    """
    xs, ys = (v.ravel() for v in np.meshgrid(np.linspace(x0, x1, 7), np.linspace(y0, y1, 7)))
    if "grid" in layout:
        _, _, road_x, road_y = on_road(xs, ys, layout["grid"])
        if (road_x | road_y).any():
            return False
    if layout.get("road") is not None:
        across, _ = road_distance(xs, ys, layout["road"])
        clear = np.abs(across) > layout["road"]["width"] / 2 + 4
        if not clear.all() or len(np.unique(np.sign(across))) > 1:
            return False
    return True


def add_landmarks(objects: Objects, rng: np.random.Generator, cam: tuple[float, float], yaw: float, family: str,
                  layout: dict[str, Any]) -> Objects:
    """``objects`` with 3-8 landmarks of ``family``'s kinds added (in a share of scenes) and what they cover removed.

    They stand 40-400 m from the camera, three in four within 45 degrees of where it looks (``yaw``, radians).
    """
    share, kinds = LANDMARKS.get(family, (0.0, {}))
    if rng.random() >= share:
        return objects
    names = list(kinds)
    weights = np.array([kinds[n] for n in names])
    wanted = int(rng.integers(3, 9))
    rows: list[tuple[float, ...]] = []
    for _ in range(4 * wanted):
        if len(rows) == wanted:
            break
        kind = names[int(rng.choice(len(names), p=weights / weights.sum()))]
        (wx, wy, hz, mat, storey, window) = _KINDS[kind]
        distance = math.exp(rng.uniform(math.log(40), math.log(400)))
        bearing = yaw + (rng.uniform(-math.pi / 4, math.pi / 4) if rng.random() < 0.75 else rng.uniform(0, 2 * math.pi))
        cx, cy = cam[0] + distance * math.cos(bearing), cam[1] + distance * math.sin(bearing)
        sx, sy = rng.uniform(*wx) / 2, rng.uniform(*wy) / 2
        box = (cx - sx, cy - sy, cx + sx, cy + sy)
        overlaps = any(box[0] < r[2] + 8 and r[0] < box[2] + 8 and box[1] < r[3] + 8 and r[1] < box[3] + 8
                       for r in rows)
        if overlaps or not _clear_of_roads(*box, layout):
            continue
        rows.append((*box, float(rng.uniform(*hz)), mat, storey, window))
    if not rows:
        return objects
    table = np.array(rows)
    n = len(table)
    x0, y0, x1, y1, height, mat, storey, window = table.T
    mat = mat.astype(np.uint8)
    palette = [_GLASS if m == M_GLASS else _METAL if m == M_UNIT else _WALLS for m in mat]
    color = np.array([p[rng.integers(len(p))] for p in palette]) * rng.uniform(0.9, 1.08, (n, 1))
    roof = _ROOFS[rng.integers(len(_ROOFS), size=n)]
    # what the landmarks would stand in (houses, trees, cars) is removed, 2 m around them
    inside = np.zeros(len(objects), bool)
    for i in range(n):
        inside |= ((objects.lo[:, 0] < x1[i] + 2) & (objects.hi[:, 0] > x0[i] - 2)
                   & (objects.lo[:, 1] < y1[i] + 2) & (objects.hi[:, 1] > y0[i] - 2))
    out = Collector()
    out.add_objects(objects.select(~inside))
    out.add(BOX, np.stack([x0, y0, np.zeros(n)], -1), np.stack([x1, y1, height], -1), BUILDING, mat,
            np.clip(color, 0, 1), roof, floor_h=storey, window=window)
    return out.objects()
