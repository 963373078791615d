"""Shared fixtures: a seeded RNG, Mitsuba with the project's variant, tiny test scenes."""
from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from rendering.backend import select_variant


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def mi() -> Any:
    select_variant()
    import mitsuba

    return mitsuba


def lit_plane_scene(mi: Any, size: int = 32, rfilter: str = "gaussian") -> dict[str, Any]:
    """A diffuse plane filling the view, lit by a small sphere light: flat, evenly lit, noisy."""
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 3},
        "sensor": {
            "type": "perspective",
            "fov": 30.0,
            "to_world": T().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
            "sampler": {"type": "independent", "sample_count": 4},
            "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": rfilter}},
        },
        "plane": {
            "type": "rectangle",
            "to_world": T().scale([3, 3, 1]),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.6, 0.5, 0.4]}},
        },
        "light": {
            "type": "sphere",
            "center": [1.5, 1.5, 2.0],
            "radius": 0.4,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [20.0, 20.0, 20.0]}},
        },
    }


@pytest.fixture
def plane_scene(mi: Any) -> dict[str, Any]:
    return lit_plane_scene(mi)
