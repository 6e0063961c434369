"""Scenes: random worlds in metres, objects (boxes, gabled houses, trees, vehicles, people) on a ground layout.

Every family is sampled by vectorised numpy from one ``numpy.random.Generator``, so a scene depends
on the generator state only. The ground is an infinite plane at ``z = 0`` (it reaches the horizon);
what covers it (roads, lots, fields, water, forest floor) is a function of ``(x, y)`` described by
``Scene.layout`` and evaluated per pixel by :mod:`.shading`. The families live in :mod:`.urban`
(downtown, suburb, industrial), :mod:`.rural` (farmland, forest) and :mod:`.water` (coast, lake,
river, in front of any of them); what they place is described in :mod:`.objects`, and the tall structures
any family but downtown may hold in :mod:`.landmarks`. This module draws
the family, the camera position, the sun and the picture's look, and keeps everything out of the water.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dapm_lightning.data.synthetic.landmarks import add_landmarks
from dapm_lightning.data.synthetic.objects import (
    BUILDING,
    CLASS_NAMES,
    GROUND,
    M_BOAT,
    M_CAR,
    PERSON,
    SKY,
    TREE,
    VEHICLE,
    WATER,
    Collector,
    Objects,
)
from dapm_lightning.data.synthetic.rural import farmland, forest
from dapm_lightning.data.synthetic.urban import downtown, industrial, suburb
from dapm_lightning.data.synthetic.water import add_boats, sample_water, water_mask

__all__ = ["BUILDING", "CLASS_NAMES", "FAMILIES", "GROUND", "M_CAR", "PERSON", "SKY", "TREE", "VEHICLE", "WATER",
           "Objects", "Scene", "draw_family", "normalize_families", "sample_scene"]
"""The hit classes and ``M_CAR`` are re-exported: they were imported from here before the split."""

FAMILIES = ("downtown", "suburb", "industrial", "farmland", "forest", "water")
"""Scene families, each sampled by its own function; ``water`` puts a coast, lake or river in front of the camera."""


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


_SAMPLERS = {"downtown": downtown, "suburb": suburb, "industrial": industrial, "farmland": farmland,
             "forest": forest}
"""The sampler of each family but water (which samples one of suburb, farmland or forest, then adds the water)."""


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


SKY_KINDS = {"clear": 0.45, "hazy": 0.35, "white": 0.20}
"""Shares of the sky's kinds (generator version 4): the deep blue of a clear day, a pale hazy blue, and the grey-white
of an overcast or bright hazy day. Version 3's skies were all deep blue; the UAPD frames in ``../shared/uapd_figure``
(CARLA renders) show pale and white ones, which a model trained on version 3 took for distant ground."""


def _sky_look(rng: np.random.Generator, look: dict[str, Any]) -> dict[str, Any]:
    """The sky's colours of one picture and the sun's bloom, from a stream of their own.

    The rest of the scene is what it was without them. ``haze``: the horizon's colour, also what distant surfaces
    fade into; ``zenith``; ``bloom``: a wide glare around the sun, 0 in 60 % of the pictures.
    """
    kind = rng.choice(list(SKY_KINDS), p=list(SKY_KINDS.values()))
    haze, zenith = look["haze"], look["zenith"]
    if kind == "hazy":  # the haze brightens and the zenith pales towards it
        haze = np.clip(haze + (1 - haze) * rng.uniform(0.0, 0.6), 0, 1)
        zenith = zenith + (haze - zenith) * rng.uniform(0.5, 0.95)
    elif kind == "white":
        haze = np.clip(rng.uniform(0.7, 0.97) + rng.uniform(-0.03, 0.03, 3), 0, 1)
        zenith = np.clip(haze * rng.uniform(0.85, 1.05), 0, 1)
    bloom = float(rng.uniform(0.2, 0.9)) if rng.random() < 0.4 else 0.0
    return {"haze": haze, "zenith": zenith, "bloom": bloom}


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
    out = Collector()
    base = str(rng.choice(["suburb", "farmland", "forest"])) if family == "water" else family
    layout = _SAMPLERS[base](rng, cam, out)
    water = None
    if family == "water":
        water = sample_water(rng, cam, math.radians(yaw_deg), big=True)
    elif family in ("downtown", "suburb", "industrial", "farmland") and rng.random() < 0.12:
        water = sample_water(rng, cam, math.radians(yaw_deg), big=False)
    if water is not None:
        add_boats(out, rng, water, cam)
    elevation = math.radians(rng.uniform(8, 75))
    azimuth = rng.uniform(0, 2 * math.pi)
    sun = np.array([math.cos(elevation) * math.cos(azimuth), math.cos(elevation) * math.sin(azimuth),
                    math.sin(elevation)])
    look, texture_seed = _look(rng), int(rng.integers(1 << 30))
    # landmarks draw from a stream of their own, last: the rest of the scene is what it was without them
    objects = add_landmarks(out.objects(), np.random.default_rng(rng.integers(1 << 62)), cam,
                            math.radians(yaw_deg), base, layout)
    look.update(_sky_look(np.random.default_rng(rng.integers(1 << 62)), look))  # its own stream, after the rest
    if water is not None and len(objects):  # nothing but boats stands in the water
        corners = [(objects.lo[:, 0], objects.lo[:, 1]), (objects.hi[:, 0], objects.hi[:, 1]),
                   (objects.lo[:, 0], objects.hi[:, 1]), (objects.hi[:, 0], objects.lo[:, 1])]
        wet = np.zeros(len(objects), bool)
        for cx, cy in corners:
            wet |= water_mask(cx, cy, water)[1] > -3
        objects = objects.select(~wet | (objects.mat == M_BOAT))
    layout["water"] = water
    return Scene(family, cam, yaw_deg, objects, layout, look, sun, texture_seed)
