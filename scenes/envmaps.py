"""Procedural HDR environment maps (lat-long, HxWx3 float32 linear radiance, <= 512x256).

Pixel (row i, column j) of an H x W map holds the radiance arriving from direction
theta = (i + 0.5) / H * pi from +Y, phi = (j + 0.5) / W * 2 pi, i.e. the unit vector
(sin theta sin phi, cos theta, -sin theta cos phi), Mitsuba's ``envmap`` convention.
"""
from __future__ import annotations

import numpy as np

from scenes.colors import hsv_to_rgb, light_tint
from scenes.noise import value_noise
from scenes.sampling import log_uniform

MAX_WIDTH, MAX_HEIGHT = 512, 256


def _directions(height: int, width: int) -> np.ndarray:
    theta = (np.arange(height) + 0.5) / height * np.pi
    phi = (np.arange(width) + 0.5) / width * 2 * np.pi
    t, p = np.meshgrid(theta, phi, indexing="ij")
    return np.stack([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)], axis=-1)


def _check_size(height: int, width: int) -> None:
    if not (4 <= height <= MAX_HEIGHT and 8 <= width <= MAX_WIDTH):
        raise ValueError(f"env map must be at most {MAX_WIDTH}x{MAX_HEIGHT}, got {width}x{height}")


def add_sun(img: np.ndarray, direction: np.ndarray, radiance: float, tint: list[float],
            radius_deg: float) -> None:
    """Add (in place) a bright disc around unit ``direction`` with a soft gaussian edge.

    ``radiance`` is the disc centre's value; ``radius_deg`` its angular radius, widened to at
    least ~1.5 pixels so the sun is never lost between pixels.
    """
    h, w, _ = img.shape
    dirs = _directions(h, w)
    cos = np.clip(dirs @ np.asarray(direction, dtype=np.float64), -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    sigma = max(radius_deg, 1.5 * 180.0 / h)
    img += (radiance * np.exp(-0.5 * (angle / sigma) ** 2))[..., None] * np.asarray(tint)


def sky(rng: np.random.Generator, height: int = 128, sun: bool = True) -> tuple[np.ndarray, list[float]]:
    """A daylight-like sky: zenith-to-horizon gradient, cloudy noise, dim ground, bright sun.

    Returns the (height x 2*height x 3) map and the unit direction *towards* the sun (world
    space before any env-map rotation; elevation 8..70 degrees). Sun centre radiance spans
    1e2..3e4, sky radiance about 0.1..2.
    """
    width = 2 * height
    _check_size(height, width)
    dirs = _directions(height, width)
    up = dirs[..., 1]
    zenith = hsv_to_rgb(rng.uniform(0.55, 0.65), rng.uniform(0.2, 0.8), 1.0)
    horizon = hsv_to_rgb(rng.uniform(0.0, 0.15), rng.uniform(0.0, 0.4), 1.0)
    level = log_uniform(rng, 0.1, 2.0)
    t = np.clip(up, 0.0, 1.0) ** float(rng.uniform(0.3, 0.8))
    img = level * ((1 - t)[..., None] * horizon + t[..., None] * zenith)
    clouds = value_noise(rng, height, width, int(rng.integers(3, 9)), octaves=4, wrap_x=True)
    cover = float(rng.uniform(0.0, 0.8))
    img *= (1.0 + cover * 2.0 * np.clip(clouds - 0.5, 0.0, None))[..., None]
    ground = hsv_to_rgb(rng.uniform(0.05, 0.35), rng.uniform(0.1, 0.6), 1.0) * level * rng.uniform(0.05, 0.4)
    img[up < 0] = ground
    az, el = np.radians(rng.uniform(0.0, 360.0)), np.radians(rng.uniform(8.0, 70.0))
    sun_dir = np.array([np.cos(el) * np.sin(az), np.sin(el), -np.cos(el) * np.cos(az)])
    if sun:
        add_sun(img, sun_dir, log_uniform(rng, 1e2, 3e4), light_tint(rng, 0.6),
                float(rng.uniform(0.5, 2.5)))
    return np.ascontiguousarray(img, dtype=np.float32), [float(v) for v in sun_dir]


def studio(rng: np.random.Generator, height: int = 128) -> np.ndarray:
    """A dim studio: smooth dark backdrop with 1-4 bright rectangular soft boxes (5..300)."""
    width = 2 * height
    _check_size(height, width)
    base = log_uniform(rng, 0.01, 0.3)
    img = np.empty((height, width, 3))
    img[:] = base * (0.5 + value_noise(rng, height, width, 3, octaves=2, wrap_x=True))[..., None]
    for _ in range(int(rng.integers(1, 5))):
        r0 = int(rng.integers(height // 8, height // 2))
        c0 = int(rng.integers(0, width))
        dh, dw = int(rng.integers(2, height // 6)), int(rng.integers(2, width // 8))
        cols = np.arange(c0, c0 + dw) % width
        img[r0:r0 + dh, cols] += np.asarray(light_tint(rng, 0.5)) * log_uniform(rng, 5.0, 300.0)
    return np.ascontiguousarray(img, dtype=np.float32)


def random_envmap(rng: np.random.Generator) -> np.ndarray:
    """A sky (with sun; 70%) or a studio map (30%), 256x128 or 512x256."""
    height = int(rng.choice([128, 256]))
    if rng.random() < 0.7:
        return sky(rng, height)[0]
    return studio(rng, height)
