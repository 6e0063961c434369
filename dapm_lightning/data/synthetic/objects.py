"""What stands in a scene: hit classes, primitive shapes, materials, the ``Objects`` table and its builders.

Objects are axis-aligned boxes in world metres (the camera's yaw turns the view instead), each with a
shape drawn inside it (:mod:`.engine` meshes them). Sizes are real ones: cars 4.2-4.9 m (vans,
trucks and buses 6.5-12 m), people 1.6-1.9 m. The helpers here add the objects every family shares
(trees, vehicles, people) to a :class:`Collector`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SKY, GROUND, BUILDING, TREE, VEHICLE, PERSON, WATER = 0, 1, 2, 3, 4, 5, 6
"""Values of the hit map :func:`render_scene` returns with each image (GROUND and WATER are the plane z = 0)."""
CLASS_NAMES = ("sky", "ground", "building", "tree", "vehicle", "person", "water")

BOX, GABLE_X, GABLE_Y, BLOB, CONE = 0, 1, 2, 3, 4
"""Primitive shapes: box, house with its roof ridge along x or y, rounded tree crown, cone (conifer, canopy)."""

(M_FACADE, M_GLASS, M_HOUSE, M_HALL, M_UNIT, M_CAR, M_PERSON, M_TREE, M_CONTAINER, M_BOAT,
 M_CONIFER) = range(11)
"""Materials of objects (see :mod:`.shading`)."""

HOUSE_WALLS = np.array([[0.92, 0.90, 0.85], [0.88, 0.80, 0.66], [0.80, 0.74, 0.70], [0.70, 0.72, 0.74],
                        [0.86, 0.78, 0.62], [0.66, 0.52, 0.44]])
ROOF_TILES = np.array([[0.55, 0.25, 0.18], [0.35, 0.33, 0.33], [0.45, 0.30, 0.22], [0.25, 0.25, 0.27],
                       [0.62, 0.38, 0.26]])
"""Colours of house walls and tiled roofs (houses in suburbs and on farms, barn roofs)."""
_CARS = np.array([[0.92, 0.92, 0.92], [0.08, 0.08, 0.09], [0.55, 0.56, 0.58], [0.35, 0.36, 0.38],
                  [0.65, 0.10, 0.10], [0.12, 0.22, 0.55], [0.80, 0.80, 0.78], [0.20, 0.35, 0.22]])
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


class Collector:
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

    def add_objects(self, objects: Objects) -> None:
        """The rows of a table already built, as they are."""
        if len(objects):
            self.parts.append({name: getattr(objects, name) for name in objects.__dataclass_fields__})

    def objects(self) -> Objects:
        if not self.parts:
            return Objects()
        return Objects(**{k: np.concatenate([p[k] for p in self.parts]) for k in self.parts[0]})


# ------------------------------------------------------------------------------------------------ object helpers

def add_trees(out: Collector, rng: np.random.Generator, x: np.ndarray, y: np.ndarray, radius: tuple[float, float],
              conifer_share: float = 0.0, base: tuple[float, float] = (1.5, 3.0)) -> None:
    """Trees at ``(x, y)``: round crowns of ``radius`` above a trunk of ``base`` metres, a share of them conifers."""
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


def add_cars(out: Collector, rng: np.random.Generator, x: np.ndarray, y: np.ndarray, along_x: np.ndarray,
             big_share: float = 0.08) -> None:
    """Cars centred at ``(x, y)``, lengthwise along x where ``along_x``; ``big_share`` of them vans, trucks, buses."""
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


def add_people(out: Collector, rng: np.random.Generator, x: np.ndarray, y: np.ndarray) -> None:
    """People standing at ``(x, y)``."""
    n = len(x)
    if n == 0:
        return
    h = rng.uniform(1.6, 1.9, n)
    out.add(BOX, np.stack([x - 0.25, y - 0.2, np.zeros(n)], -1), np.stack([x + 0.25, y + 0.2, h], -1), PERSON,
            M_PERSON, _CLOTHES[rng.integers(len(_CLOTHES), size=n)])

