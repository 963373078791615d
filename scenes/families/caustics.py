"""Glass and metal objects casting caustics from a small, bright light onto a diffuse floor.

The light is a small sphere (radius 0.02..0.15) or rectangle of power 20..400 W (radiance up to
~1e4), so caustics reach the camera only through rare BSDF-sampled paths: the firefly-heavy
case. Varies per seed: 1-4 objects, each smooth or rough glass (IOR 1.3..1.9) or metal (smooth,
rough, or a two-sided metal ring that casts a cardioid), a back wall or not, floor colour
(sometimes a checkerboard), optional dim ambient (constant 0.005..0.1), light position/tint,
camera orbit and fov, path depth 6..12.
"""
from __future__ import annotations

import numpy as np

from scenes import camera, integrator, lights, materials, textures
from scenes.colors import light_tint, random_albedo, scaled
from scenes.rooms import room
from scenes.sampling import log_uniform, orbit_point
from scenes.shapes import random_object, scatter_positions, sphere, transformed
from scenes.spec import GeneratedScene
from scenes.transforms import compose, look_at, rotate, scale, translate

FAMILY = "caustics"
OBJECT_BSDFS = {"dielectric": 3.0, "roughdielectric": 1.0, "conductor": 1.5, "roughconductor": 1.0}


def _ring(rng: np.random.Generator, name: str, x: float, z: float) -> dict:
    """A short, two-sided metal cylinder: the classic coffee-cup cardioid caustic."""
    r, h = float(rng.uniform(0.3, 0.6)), float(rng.uniform(0.1, 0.35))
    m = compose(translate((x, 0.0, z)), rotate((1, 0, 0), -90.0), scale((r, r, h)))
    bsdf = materials.twosided(materials.conductor(rng) if rng.random() < 0.6
                              else materials.roughconductor(rng, (0.01, 0.1)))
    return {name: transformed("cylinder", m, bsdf)}


def _light(rng: np.random.Generator) -> dict:
    position = orbit_point([0, 0, 0], float(rng.uniform(1.5, 4.0)), float(rng.uniform(0, 360)),
                           float(rng.uniform(15, 75)))
    power = log_uniform(rng, 20.0, 400.0)
    tint = light_tint(rng, 0.7)
    if rng.random() < 0.6:
        radius = log_uniform(rng, 0.02, 0.15)
        area_m2 = 4 * np.pi * radius**2
        return sphere(position, radius, None, lights.area(lights.radiance_for_power(tint, power, area_m2)))
    half = log_uniform(rng, 0.03, 0.2)
    m = compose(look_at(position, [0, 0, 0], (0, 1, 0)),
                scale((half, half, 1.0)))
    return transformed("rectangle", m, None,
                       lights.area(lights.radiance_for_power(tint, power, 4 * half * half)))


def generate(seed: int) -> GeneratedScene:
    """A caustics scene for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    scene: dict = {"type": "scene", "integrator": integrator.path(rng, 6, 12)}
    fov = float(rng.uniform(30.0, 55.0))
    target = [0.0, float(rng.uniform(0.1, 0.4)), 0.0]
    dist = 1.8 / np.tan(np.radians(fov / 2)) * float(rng.uniform(0.8, 1.2))
    scene["sensor"] = camera.perspective(
        orbit_point(target, dist, float(rng.uniform(-60, 60)), float(rng.uniform(15, 60))), target, fov)

    if rng.random() < 0.3:
        floor_bsdf = materials.diffuse(textures.checkerboard(rng, float(rng.uniform(4, 16))))
    else:
        floor_bsdf = materials.diffuse(random_albedo(rng, 0.3, 0.85, max_saturation=0.4))
    walls = {"floor": floor_bsdf}
    if rng.random() < 0.5:
        walls["back"] = materials.diffuse(random_albedo(rng, 0.3, 0.8, max_saturation=0.4))
    scene.update(room(12.0, 6.0, 12.0, walls))
    scene["light"] = _light(rng)
    if rng.random() < 0.5:
        scene["ambient"] = lights.constant(scaled([1.0, 1.0, 1.0], log_uniform(rng, 0.005, 0.1)))

    count = int(rng.integers(1, 5))
    for i, (x, z) in enumerate(scatter_positions(rng, count, 1.0, 1.0, min_gap=1.0)):
        if rng.random() < 0.2:
            scene.update(_ring(rng, f"object_{i}", x, z))
        else:
            bsdf = materials.random_bsdf(rng, OBJECT_BSDFS)
            scene.update(random_object(rng, f"object_{i}", bsdf, (x, z), float(rng.uniform(0.4, 0.9)),
                                       kinds=("sphere", "sphere", "cube", "cylinder")))
    return GeneratedScene(FAMILY, seed, scene, {})
