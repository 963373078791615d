"""Random colours: surface albedos in linear RGB, emitter tints, and the ``rgb`` dict form."""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


def rgb(value: Sequence[float] | float) -> dict[str, Any]:
    """Mitsuba's ``{'type': 'rgb', 'value': [r, g, b]}`` with plain Python floats."""
    if isinstance(value, (int, float, np.number)):
        value = [value] * 3
    return {"type": "rgb", "value": [float(v) for v in value]}


def hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    """HSV (each in [0, 1]) to an RGB triple in [0, 1] (float64)."""
    k = (np.array([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    return v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def random_albedo(rng: np.random.Generator, lo: float = 0.05, hi: float = 0.85,
                  max_saturation: float = 0.9) -> list[float]:
    """A diffuse reflectance: linear RGB, each channel in [0, hi], brightness in [lo, hi]."""
    h = rng.random()
    s = rng.uniform(0.0, max_saturation)
    v = rng.uniform(lo, hi)
    return [float(c) for c in hsv_to_rgb(h, s, v)]


def light_tint(rng: np.random.Generator, spread: float = 1.0) -> list[float]:
    """An emitter colour between warm (~2700 K) and cool (~8000 K) white, max channel 1.

    ``spread`` in [0, 1] scales how far from neutral white the tint may go.
    """
    warm = np.array([1.0, 0.72, 0.45])
    cool = np.array([0.75, 0.85, 1.0])
    t = rng.random()
    tint = 1.0 + spread * ((warm if t < 0.5 else cool) - 1.0) * abs(2.0 * t - 1.0)
    return [float(c) for c in tint / tint.max()]


def scaled(color: Sequence[float], factor: float) -> list[float]:
    """``color`` times ``factor``, as Python floats."""
    return [float(c) * float(factor) for c in color]
