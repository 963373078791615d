"""Material previews: 1-3 primitives of random materials on a textured floor under an env map.

Varies per seed: object count/kinds/sizes, materials (all seven kinds, metals and plastics
favoured), floor texture (checkerboard or a generated bitmap, tiling 2..12) and finish (diffuse
or rough plastic), environment (procedural sky with sun or studio soft boxes, rotated, scaled
0.3..3), an optional area key light, camera orbit (azimuth, elevation 5..45 deg, distance,
fov 25..50), path depth 3..12.
"""
from __future__ import annotations

import numpy as np

from scenes import camera, envmaps, integrator, lights, materials, textures
from scenes.colors import light_tint
from scenes.sampling import log_uniform, orbit_point
from scenes.shapes import random_object, scatter_positions, sphere, transformed
from scenes.spec import Asset, GeneratedScene
from scenes.transforms import compose, rotate, scale

FAMILY = "material_preview"
OBJECT_BSDFS = {"diffuse": 1.0, "plastic": 1.0, "roughplastic": 1.5, "conductor": 1.0,
                "roughconductor": 1.5, "dielectric": 1.0, "roughdielectric": 1.0}
ENV = "textures/env.exr"
FLOOR_TEX = "textures/floor.exr"


def _floor(rng: np.random.Generator, assets: dict[str, Asset], size: float) -> dict:
    tiles = float(rng.uniform(2.0, 12.0))
    if rng.random() < 0.5:
        tex = textures.checkerboard(rng, tiles)
    else:
        assets[FLOOR_TEX] = textures.random_image(rng, int(rng.choice([64, 128, 256])))
        tex = textures.bitmap(FLOOR_TEX, tiles / 2)
    bsdf = materials.diffuse(tex) if rng.random() < 0.6 else materials.roughplastic(rng, tex)
    m = compose(rotate((1, 0, 0), -90.0), scale((size, size, 1.0)))
    return transformed("rectangle", m, bsdf)


def _key_light(rng: np.random.Generator, eye: list[float]) -> dict:
    """A spherical area light high above the objects, kept well away from the camera."""
    radius = float(rng.uniform(0.1, 0.4))
    center = eye
    while np.linalg.norm(np.subtract(center, eye)) < radius + 0.5:
        center = orbit_point([0, 0, 0], float(rng.uniform(3.0, 6.0)), float(rng.uniform(0, 360)),
                             float(rng.uniform(30, 70)))
    area_m2 = 4 * np.pi * radius**2
    radiance = lights.radiance_for_power(light_tint(rng), log_uniform(rng, 10.0, 200.0), area_m2)
    return sphere(center, radius, None, lights.area(radiance))


def generate(seed: int) -> GeneratedScene:
    """A material-preview scene for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    assets: dict[str, Asset] = {}
    scene: dict = {"type": "scene", "integrator": integrator.path(rng, 3, 12)}
    count = int(rng.integers(1, 4))
    spread = 0.0 if count == 1 else float(rng.uniform(0.6, 1.2))
    fov = float(rng.uniform(25.0, 50.0))
    dist = (1.2 + spread) / np.tan(np.radians(fov / 2)) * float(rng.uniform(0.8, 1.1))
    target = [0.0, float(rng.uniform(0.3, 0.6)), 0.0]
    origin = orbit_point(target, dist, float(rng.uniform(0, 360)), float(rng.uniform(5, 45)))
    scene["sensor"] = camera.perspective(origin, target, fov)

    assets[ENV] = envmaps.random_envmap(rng)
    scene["environment"] = lights.envmap(ENV, log_uniform(rng, 0.3, 3.0), float(rng.uniform(0, 360)))
    if rng.random() < 0.3:
        scene["key_light"] = _key_light(rng, origin)
    scene["floor"] = _floor(rng, assets, float(rng.uniform(4.0, 12.0)))
    spots = scatter_positions(rng, count, spread, spread, min_gap=1.05)
    for i, (x, z) in enumerate(spots):
        bsdf = materials.random_bsdf(rng, OBJECT_BSDFS)
        scene.update(random_object(rng, f"object_{i}", bsdf, (x, z), float(rng.uniform(0.6, 1.0)),
                                   kinds=("sphere", "sphere", "cube", "cylinder")))
    return GeneratedScene(FAMILY, seed, scene, assets)
