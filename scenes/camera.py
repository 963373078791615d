"""The sensor of every generated scene: a perspective camera with a 128x128 HDR film.

Positions are world units in Mitsuba's Y-up world; ``fov`` is the horizontal field of view in
degrees. Renders override the film size; the sampler's count is only a default (renders pass spp).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from scenes.transforms import look_at, to_mitsuba

DEFAULT_RESOLUTION = 128
DEFAULT_SPP = 64


def perspective(origin: Sequence[float], target: Sequence[float], fov: float,
                up: Sequence[float] = (0.0, 1.0, 0.0),
                resolution: int = DEFAULT_RESOLUTION) -> dict[str, Any]:
    """A ``perspective`` sensor looking from ``origin`` at ``target`` (box-filtered hdrfilm)."""
    if not 1.0 <= fov <= 170.0:
        raise ValueError(f"fov must be in [1, 170] degrees, got {fov}")
    return {
        "type": "perspective",
        "fov": float(fov),
        "fov_axis": "x",
        "near_clip": 0.01,
        "far_clip": 1000.0,
        "to_world": to_mitsuba(look_at(origin, target, up)),
        "film": {"type": "hdrfilm", "width": resolution, "height": resolution,
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": DEFAULT_SPP},
    }
