"""Textures: procedural checkerboards and generated bitmap images (HxWx3 float32 albedo).

Bitmaps are linear RGB reflectances in [0.02, 0.9], at most 256x256, saved as EXR assets and
referenced by a ``bitmap`` texture dict. ``tiles`` is how often a texture repeats across a
shape's [0, 1]^2 UV square.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from scenes.colors import random_albedo, rgb
from scenes.noise import stretch, value_noise
from scenes.transforms import scale, to_mitsuba

ALBEDO_MIN, ALBEDO_MAX = 0.02, 0.9
MAX_TEXTURE_SIZE = 256


def uv_scale(tiles: float) -> Any:
    """``to_uv`` matrix repeating a texture ``tiles`` times in u and v."""
    return to_mitsuba(scale((tiles, tiles, 1.0)))


def checkerboard(rng: np.random.Generator, tiles: float) -> dict[str, Any]:
    """A ``checkerboard`` texture of two contrasting random albedos."""
    light = random_albedo(rng, 0.45, 0.85, max_saturation=0.5)
    dark = random_albedo(rng, 0.03, 0.25, max_saturation=0.7)
    return {"type": "checkerboard", "color0": rgb(light), "color1": rgb(dark),
            "to_uv": uv_scale(tiles)}


def bitmap(filename: str, tiles: float = 1.0, nearest: bool = False) -> dict[str, Any]:
    """A ``bitmap`` texture reading an EXR asset, repeated ``tiles`` times."""
    return {"type": "bitmap", "filename": filename,
            "filter_type": "nearest" if nearest else "bilinear",
            "wrap_mode": "repeat", "to_uv": uv_scale(tiles)}


def _mix(t: np.ndarray, a: list[float], b: list[float]) -> np.ndarray:
    return (1.0 - t)[..., None] * np.asarray(a) + t[..., None] * np.asarray(b)


def _finish(img: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(np.clip(img, ALBEDO_MIN, ALBEDO_MAX), dtype=np.float32)


def noise_image(rng: np.random.Generator, size: int) -> np.ndarray:
    """Two-colour fractal noise (marble/wood-like blotches)."""
    t = stretch(value_noise(rng, size, size, int(rng.integers(2, 8)), octaves=5))
    if rng.random() < 0.5:  # banded, wood-like
        t = 0.5 + 0.5 * np.sin(t * float(rng.uniform(8.0, 30.0)))
    return _finish(_mix(t, random_albedo(rng, 0.05, 0.4), random_albedo(rng, 0.4, 0.85)))


def brick_image(rng: np.random.Generator, size: int) -> np.ndarray:
    """Running-bond bricks with mortar lines and per-brick colour variation."""
    rows = int(rng.integers(4, 12))
    cols = max(1, rows // 2)
    y, x = np.mgrid[0:size, 0:size] / size
    row = np.floor(y * rows).astype(int)
    xs = x * cols + 0.5 * (row % 2)
    col = np.floor(xs).astype(int)
    mortar_w = float(rng.uniform(0.03, 0.1))
    fy, fx = y * rows - row, xs - col
    mortar = (fy < mortar_w) | (fx < mortar_w * rows / cols / 2)
    brick_color = np.asarray(random_albedo(rng, 0.2, 0.6))
    jitter = rng.uniform(0.7, 1.3, size=(rows, cols + 2))[row, col % (cols + 2)]
    img = brick_color * jitter[..., None]
    img[mortar] = random_albedo(rng, 0.4, 0.8, max_saturation=0.2)
    grain = value_noise(rng, size, size, 16, octaves=2)
    return _finish(img * (0.85 + 0.3 * grain)[..., None])


def stripe_image(rng: np.random.Generator, size: int) -> np.ndarray:
    """Sharp-edged stripes (or plaid) at a random angle: high-frequency detail."""
    y, x = np.mgrid[0:size, 0:size] / size
    angle = float(rng.uniform(0.0, np.pi))
    freq = float(rng.integers(3, 16))
    t = (np.sin(2 * np.pi * freq * (x * np.cos(angle) + y * np.sin(angle))) > 0).astype(float)
    img = _mix(t, random_albedo(rng, 0.05, 0.35), random_albedo(rng, 0.5, 0.85))
    if rng.random() < 0.5:
        s = (np.sin(2 * np.pi * freq * (x * np.sin(angle) - y * np.cos(angle))) > 0.5)
        img[s] *= 0.5
    return _finish(img)


def tile_image(rng: np.random.Generator, size: int) -> np.ndarray:
    """Square tiles of random colours from a small palette, with grout."""
    n = int(rng.integers(3, 10))
    palette = np.array([random_albedo(rng, 0.1, 0.85) for _ in range(int(rng.integers(2, 5)))])
    idx = rng.integers(0, len(palette), size=(n, n))
    y, x = np.mgrid[0:size, 0:size] * n // size
    img = palette[idx[y, x]]
    grout = float(rng.uniform(0.02, 0.08))
    fy, fx = (np.mgrid[0:size, 0:size] * n / size) % 1.0
    img[(fy < grout) | (fx < grout)] = random_albedo(rng, 0.05, 0.5, max_saturation=0.2)
    return _finish(img)


def dot_image(rng: np.random.Generator, size: int) -> np.ndarray:
    """Polka dots on a noisy background."""
    n = int(rng.integers(3, 10))
    fy, fx = (np.mgrid[0:size, 0:size] * n / size) % 1.0
    r = float(rng.uniform(0.15, 0.45))
    inside = (fx - 0.5) ** 2 + (fy - 0.5) ** 2 < r * r
    base = value_noise(rng, size, size, 4, octaves=3)
    img = _mix(base, random_albedo(rng, 0.3, 0.6), random_albedo(rng, 0.5, 0.85))
    img[inside] = random_albedo(rng, 0.02, 0.4)
    return _finish(img)


PATTERNS: dict[str, Callable[[np.random.Generator, int], np.ndarray]] = {
    "noise": noise_image, "brick": brick_image, "stripes": stripe_image, "tiles": tile_image,
    "dots": dot_image,
}


def random_image(rng: np.random.Generator, size: int = 128) -> np.ndarray:
    """A size x size albedo image of a random pattern (HxWx3 float32 in [0.02, 0.9])."""
    if not 8 <= size <= MAX_TEXTURE_SIZE:
        raise ValueError(f"texture size must be in [8, {MAX_TEXTURE_SIZE}], got {size}")
    names = sorted(PATTERNS)
    return PATTERNS[names[int(rng.integers(len(names)))]](rng, size)
