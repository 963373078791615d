"""Dark scenes lit by small, very bright emitters: point lights, spot lights, tiny spheres.

Walls have low albedo (0.03..0.35) and there is at most a faint ambient (0..0.02), so most of
the frame is dim and the lights (visible tiny spheres of radius 0.005..0.05 and radiance
1e2..1e4, their glossy reflections, lights half-hidden behind objects) produce the fireflies
and large dynamic range a denoiser must survive. Varies per seed: room size and which side
walls and ceiling exist (floor and back wall always do), 1-4 lights of the three kinds (point
intensity 0.3..100 W/sr, spot 1..300 W/sr with cutoff 10..45 deg), 1-5 objects of all material
kinds, camera, path depth 3..7 (the scene is mostly closed: depth is what costs).
"""
from __future__ import annotations

import numpy as np

from scenes import camera, integrator, lights, materials
from scenes.colors import light_tint, random_albedo, scaled
from scenes.rooms import room
from scenes.sampling import log_uniform
from scenes.shapes import random_object, scatter_positions, sphere
from scenes.spec import GeneratedScene

FAMILY = "small_emitters"
OBJECT_BSDFS = {"diffuse": 1.0, "plastic": 1.0, "roughplastic": 1.0, "conductor": 1.0,
                "roughconductor": 1.5, "dielectric": 0.7, "roughdielectric": 0.3}


def _light(rng: np.random.Generator, w: float, h: float, d: float) -> tuple[str, dict]:
    pos = (float(rng.uniform(-0.45, 0.45)) * w, float(rng.uniform(0.05, 0.95)) * h,
           float(rng.uniform(-0.45, 0.3)) * d)
    tint = light_tint(rng, 1.0)
    kind = str(rng.choice(["point", "spot", "sphere", "sphere"]))
    if kind == "point":
        return kind, lights.point(pos, scaled(tint, log_uniform(rng, 0.3, 100.0)))
    if kind == "spot":
        target = (float(rng.uniform(-0.4, 0.4)) * w, 0.0, float(rng.uniform(-0.4, 0.2)) * d)
        cutoff = float(rng.uniform(10.0, 45.0))
        return kind, lights.spot(pos, target, scaled(tint, log_uniform(rng, 1.0, 300.0)),
                                 cutoff, cutoff * float(rng.uniform(0.3, 0.9)))
    radius = log_uniform(rng, 0.005, 0.05)
    return kind, sphere(pos, radius, None, lights.area(scaled(tint, log_uniform(rng, 1e2, 1e4))))


def generate(seed: int) -> GeneratedScene:
    """A dark scene with small bright emitters for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    scene: dict = {"type": "scene", "integrator": integrator.path(rng, 3, 7)}
    w, h, d = float(rng.uniform(3.0, 7.0)), float(rng.uniform(2.0, 4.0)), float(rng.uniform(3.0, 7.0))
    fov = float(rng.uniform(35.0, 70.0))
    eye = (float(rng.uniform(-0.2, 0.2)) * w, float(rng.uniform(0.3, 0.8)) * h,
           d / 2 + float(rng.uniform(0.2, 2.0)))
    look = (float(rng.uniform(-0.2, 0.2)) * w, float(rng.uniform(0.0, 0.35)) * h, -d / 2)
    scene["sensor"] = camera.perspective(eye, look, fov)

    walls = {"floor": materials.diffuse(random_albedo(rng, 0.03, 0.35)),
             "back": materials.diffuse(random_albedo(rng, 0.03, 0.35))}
    for name, p in (("left", 0.6), ("right", 0.6), ("ceiling", 0.4)):
        if rng.random() < p:
            walls[name] = materials.diffuse(random_albedo(rng, 0.03, 0.35))
    scene.update(room(w, h, d, walls))
    if rng.random() < 0.3:
        scene["ambient"] = lights.constant(scaled([1.0, 1.0, 1.0], log_uniform(rng, 1e-4, 0.02)))

    # Objects first, so lights can be hidden behind them.
    spots = scatter_positions(rng, int(rng.integers(1, 6)), 0.35 * w, 0.3 * d, 0.8, (0.0, -0.1 * d))
    for i, (x, z) in enumerate(spots):
        bsdf = materials.random_bsdf(rng, OBJECT_BSDFS)
        scene.update(random_object(rng, f"object_{i}", bsdf, (x, z), float(rng.uniform(0.3, 0.8))))
    for i in range(int(rng.integers(1, 5))):
        kind, light = _light(rng, w, h, d)
        scene[f"{kind}_light_{i}"] = light
    return GeneratedScene(FAMILY, seed, scene, {})
