"""Emitter dicts: area, point, spot, directional, constant and environment-map lights.

Radiance is W/(m^2 sr) (area, constant, envmap scale multiplies the map), intensity W/sr (point,
spot), irradiance W/m^2 (directional); all linear RGB. Positions/directions are world units in
Mitsuba's Y-up world; angles in degrees.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from scenes.colors import rgb, scaled
from scenes.transforms import compose, look_at, rotate, to_mitsuba


def area(radiance: Sequence[float]) -> dict[str, Any]:
    """An ``area`` emitter to nest in a shape under the key ``'emitter'``."""
    return {"type": "area", "radiance": rgb(radiance)}


def point(position: Sequence[float], intensity: Sequence[float]) -> dict[str, Any]:
    """An isotropic point light."""
    return {"type": "point", "position": [float(v) for v in position], "intensity": rgb(intensity)}


def spot(origin: Sequence[float], target: Sequence[float], intensity: Sequence[float],
         cutoff_angle: float, beam_width: float) -> dict[str, Any]:
    """A spot light at ``origin`` aimed at ``target``; full intensity within ``beam_width``
    degrees of the axis, falling to zero at ``cutoff_angle`` degrees."""
    if not 0.0 < beam_width <= cutoff_angle < 90.0:
        raise ValueError(f"need 0 < beam_width <= cutoff_angle < 90, got {beam_width}, {cutoff_angle}")
    up = (0.0, 0.0, 1.0) if abs(target[0] - origin[0]) + abs(target[2] - origin[2]) < 1e-6 \
        else (0.0, 1.0, 0.0)
    return {"type": "spot", "to_world": to_mitsuba(look_at(origin, target, up)),
            "intensity": rgb(intensity), "cutoff_angle": float(cutoff_angle),
            "beam_width": float(beam_width)}


def directional(direction: Sequence[float], irradiance: Sequence[float]) -> dict[str, Any]:
    """A distant light travelling along ``direction`` (from the light towards the scene)."""
    return {"type": "directional", "direction": [float(v) for v in direction],
            "irradiance": rgb(irradiance)}


def constant(radiance: Sequence[float]) -> dict[str, Any]:
    """Uniform environment light."""
    return {"type": "constant", "radiance": rgb(radiance)}


def envmap(filename: str, scale: float = 1.0, rotation_deg: float = 0.0) -> dict[str, Any]:
    """A lat-long environment map from an EXR asset, rotated ``rotation_deg`` about +Y."""
    return {"type": "envmap", "filename": filename, "scale": float(scale),
            "to_world": to_mitsuba(compose(rotate((0.0, 1.0, 0.0), rotation_deg)))}


def radiance_for_power(color: Sequence[float], power: float, area_m2: float) -> list[float]:
    """Radiance of a Lambertian emitter of ``area_m2`` emitting ``power`` W (per channel scale)."""
    return scaled(color, power / (3.141592653589793 * area_m2))
