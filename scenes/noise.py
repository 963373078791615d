"""Procedural noise fields (fractal value noise) for textures, environment maps and terrain."""
from __future__ import annotations

import numpy as np


def _smooth(t: np.ndarray) -> np.ndarray:
    return t * t * (3.0 - 2.0 * t)


def _octave(rng: np.random.Generator, height: int, width: int, cells_x: int, cells_y: int,
            wrap_x: bool) -> np.ndarray:
    lattice = rng.random((cells_y + 1, cells_x + 1))
    if wrap_x:
        lattice[:, -1] = lattice[:, 0]
    x = (np.arange(width) + 0.5) / width * cells_x
    y = (np.arange(height) + 0.5) / height * cells_y
    x0 = np.minimum(np.floor(x).astype(int), cells_x - 1)
    y0 = np.minimum(np.floor(y).astype(int), cells_y - 1)
    fx = _smooth(x - x0)[None, :]
    fy = _smooth(y - y0)[:, None]
    a = lattice[y0][:, x0]
    b = lattice[y0][:, x0 + 1]
    c = lattice[y0 + 1][:, x0]
    d = lattice[y0 + 1][:, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def value_noise(rng: np.random.Generator, height: int, width: int, cells: int,
                octaves: int = 4, persistence: float = 0.5, wrap_x: bool = False) -> np.ndarray:
    """Fractal value noise: HxW float64 in [0, 1].

    ``cells`` lattice cells span the width in the first octave (the height gets as many as keep
    cells square); each further octave doubles the frequency and scales the amplitude by
    ``persistence``. ``wrap_x`` makes the field tile horizontally (for lat-long env maps).
    """
    if height < 1 or width < 1 or cells < 1 or octaves < 1:
        raise ValueError("value_noise: height, width, cells and octaves must be positive")
    total = np.zeros((height, width))
    norm = 0.0
    amplitude = 1.0
    for octave in range(octaves):
        cx = cells * 2**octave
        cy = max(1, round(cx * height / width))
        total += amplitude * _octave(rng, height, width, cx, cy, wrap_x)
        norm += amplitude
        amplitude *= persistence
    return total / norm


def stretch(field: np.ndarray) -> np.ndarray:
    """Rescale a field linearly to span exactly [0, 1] (a constant field becomes 0.5)."""
    lo, hi = float(field.min()), float(field.max())
    if hi - lo < 1e-12:
        return np.full_like(field, 0.5)
    return (field - lo) / (hi - lo)
