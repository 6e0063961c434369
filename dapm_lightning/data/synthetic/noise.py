"""Integer lattice hashing and value noise: exactly reproducible on any machine (no transcendental functions)."""

from __future__ import annotations

import numpy as np

_MASK = np.int64(0xFFFFFFFF)


def ihash(ix: np.ndarray, iy: np.ndarray, seed: int) -> np.ndarray:
    """Uniform ``[0, 1)`` numbers from integer lattice coordinates (int64 arithmetic, bit-exact everywhere)."""
    h = (np.asarray(ix, np.int64) * np.int64(374761393) + np.asarray(iy, np.int64) * np.int64(668265263)
         + np.int64(seed % 2_147_483_647) * np.int64(1442695041)) & _MASK
    h = ((h ^ (h >> 13)) * np.int64(1274126177)) & _MASK
    h = h ^ (h >> 16)
    return h.astype(np.float64) * (1.0 / 4294967296.0)


def value_noise(x: np.ndarray, y: np.ndarray, cell: float, seed: int) -> np.ndarray:
    """Smooth noise in ``[0, 1]`` with features of ``cell`` metres."""
    gx, gy = x * (1.0 / cell), y * (1.0 / cell)
    fx0, fy0 = np.floor(gx), np.floor(gy)
    fx, fy = gx - fx0, gy - fy0
    ix, iy = fx0.astype(np.int64), fy0.astype(np.int64)
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)
    top = ihash(ix, iy, seed) * (1 - fx) + ihash(ix + 1, iy, seed) * fx
    bottom = ihash(ix, iy + 1, seed) * (1 - fx) + ihash(ix + 1, iy + 1, seed) * fx
    return top * (1 - fy) + bottom * fy


def fade(detail: np.ndarray, mean: float, footprint: np.ndarray, cell: float) -> np.ndarray:
    """Blend texture detail towards its mean where a pixel covers more than ``cell`` metres (cheap anti-aliasing)."""
    k = np.clip(footprint * (1.0 / cell) - 0.5, 0.0, 1.0)
    return detail * (1 - k) + mean * k


def fbm(x: np.ndarray, y: np.ndarray, cell: float, seed: int, footprint: np.ndarray, octaves: int = 3) -> np.ndarray:
    """Fractal value noise in about ``[0, 1]``: octaves finer than a pixel fade to their mean."""
    total = np.zeros(np.shape(x))
    amplitude, norm = 1.0, 0.0
    for octave in range(octaves):
        size = cell / 2 ** octave
        total += amplitude * fade(value_noise(x, y, size, seed + 7 * octave), 0.5, footprint, size)
        norm += amplitude
        amplitude *= 0.5
    return total / norm
