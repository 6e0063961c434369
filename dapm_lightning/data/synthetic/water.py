"""Water on the ground plane: a coast, lake or river (``layout["water"]``) and the boats on it."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dapm_lightning.data.synthetic.noise import value_noise
from dapm_lightning.data.synthetic.objects import BOX, M_BOAT, VEHICLE, Collector


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


def sample_water(rng: np.random.Generator, cam: tuple[float, float], yaw: float, big: bool) -> dict[str, Any]:
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


def add_boats(out: Collector, rng: np.random.Generator, water: dict[str, Any], cam: tuple[float, float]) -> None:
    """Boats 5-30 m long on the water near the camera, at least 15 m from the shore."""
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

