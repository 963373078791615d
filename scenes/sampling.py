"""Random draws shared by the generators: log-uniform magnitudes and directions.

Directions are in Mitsuba's Y-up world: elevation is the angle above the XZ plane, azimuth is
measured from +Z towards +X; both in degrees.
"""
from __future__ import annotations

import numpy as np


def log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    """A float whose logarithm is uniform in [log lo, log hi] (0 < lo <= hi)."""
    if not 0.0 < lo <= hi:
        raise ValueError(f"log_uniform needs 0 < lo <= hi, got {lo}, {hi}")
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def direction(azimuth_deg: float, elevation_deg: float) -> list[float]:
    """Unit vector at ``azimuth_deg`` around +Y (0 = +Z, 90 = +X) and ``elevation_deg`` up."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return [float(np.cos(el) * np.sin(az)), float(np.sin(el)), float(np.cos(el) * np.cos(az))]


def orbit_point(center: list[float] | tuple[float, ...], distance: float, azimuth_deg: float,
                elevation_deg: float) -> list[float]:
    """The point ``distance`` away from ``center`` in the given direction (world units)."""
    d = direction(azimuth_deg, elevation_deg)
    return [float(c + distance * v) for c, v in zip(center, d)]
