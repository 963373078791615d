"""Cornell-style boxes: coloured side walls, a ceiling light, 1-4 random objects.

Varies per seed: box proportions, wall colours (classic red/green or random), light size
(5-60% of the ceiling width) and power (log-uniform over 1.5 decades), object count, kinds
(sphere/cube/cylinder), sizes and materials (all seven kinds, glass and metal often),
camera distance/offset/fov, path depth 3..8 (closed box: every bounce is paid for).
"""
from __future__ import annotations

import numpy as np

from scenes import camera, integrator, lights, materials
from scenes.colors import light_tint, random_albedo
from scenes.rooms import room, wall
from scenes.sampling import log_uniform
from scenes.shapes import random_object, scatter_positions, transformed
from scenes.spec import GeneratedScene

FAMILY = "cornell_box"
OBJECT_BSDFS = {"diffuse": 2.0, "plastic": 1.0, "roughplastic": 1.0, "conductor": 1.0,
                "roughconductor": 1.0, "dielectric": 1.5, "roughdielectric": 0.5}


def _wall_colors(rng: np.random.Generator) -> dict[str, list[float]]:
    white = random_albedo(rng, 0.55, 0.8, max_saturation=0.15)
    if rng.random() < 0.5:
        left, right = [0.63, 0.065, 0.05], [0.14, 0.45, 0.091]
    else:
        left, right = random_albedo(rng, 0.2, 0.7), random_albedo(rng, 0.2, 0.7)
    if rng.random() < 0.5:
        left, right = right, left
    return {"floor": white, "ceiling": white, "back": white, "left": left, "right": right}


def generate(seed: int) -> GeneratedScene:
    """A Cornell-style box scene for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    w, h, d = float(rng.uniform(1.6, 2.6)), float(rng.uniform(1.6, 2.4)), float(rng.uniform(1.6, 2.6))
    colors = _wall_colors(rng)
    scene: dict = {"type": "scene", "integrator": integrator.path(rng, 3, 8)}
    fov = float(rng.uniform(30.0, 50.0))
    dist = (max(w, h) / 2) / np.tan(np.radians(fov / 2)) * float(rng.uniform(0.9, 1.15))
    origin = (float(rng.uniform(-0.1, 0.1) * w), h / 2 + float(rng.uniform(-0.15, 0.15)) * h,
              d / 2 + dist)
    target = (0.0, h / 2 + float(rng.uniform(-0.1, 0.05)) * h, 0.0)
    scene["sensor"] = camera.perspective(origin, target, fov)
    scene.update(room(w, h, d, {k: materials.diffuse(c) for k, c in colors.items()}))

    # Ceiling light: a rectangle just below the ceiling, facing down.
    lw = w * float(rng.uniform(0.05, 0.6))
    ld = lw * float(rng.uniform(0.6, 1.5))
    power = log_uniform(rng, 3.0, 100.0)
    ceiling = wall("ceiling", w, h, d)
    lx, lz = float(rng.uniform(-0.2, 0.2)) * w, float(rng.uniform(-0.2, 0.2)) * d
    panel = ceiling.panel(lx - lw / 2, lx + lw / 2, lz - ld / 2, lz + ld / 2, offset=1e-3)
    radiance = lights.radiance_for_power(light_tint(rng, 0.5), power, lw * ld)
    scene["light"] = transformed("rectangle", panel, materials.diffuse([0.7, 0.7, 0.7]),
                                 lights.area(radiance))

    count = int(rng.integers(1, 5))
    spots = scatter_positions(rng, count, 0.3 * w, 0.3 * d, min_gap=0.35 * min(w, d))
    for i, (x, z) in enumerate(spots):
        size = float(rng.uniform(0.2, 0.4)) * min(w, d, h)  # cylinders stay below the ceiling
        bsdf = materials.random_bsdf(rng, OBJECT_BSDFS)
        scene.update(random_object(rng, f"object_{i}", bsdf, (x, z), size))
    return GeneratedScene(FAMILY, seed, scene, {})
