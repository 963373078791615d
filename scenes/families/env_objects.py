"""Objects under procedural HDR skies with a bright sun spot (image-based lighting).

The env map (256x128 or 512x256 EXR) is the only light: sun disc radiance 1e2..3e4, sky
0.1..2 (times a scale of 0.5..2). Varies per seed: sky colours, cloud cover, sun position and
size, map rotation, 2-7 objects (spheres, cubes, cylinders) of all material kinds, either
floating above nothing or resting on a plain ground disc (diffuse or rough plastic), camera
orbit (elevation -5..50 deg) and fov 30..60, path depth 3..12.
"""
from __future__ import annotations

import numpy as np

from scenes import camera, envmaps, integrator, lights, materials
from scenes.colors import random_albedo
from scenes.sampling import log_uniform, orbit_point
from scenes.shapes import random_object, scatter_positions, transformed
from scenes.spec import Asset, GeneratedScene
from scenes.transforms import compose, rotate, scale

FAMILY = "env_objects"
ENV = "textures/sky.exr"


def generate(seed: int) -> GeneratedScene:
    """An env-map-lit object cluster for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    assets: dict[str, Asset] = {}
    scene: dict = {"type": "scene", "integrator": integrator.path(rng, 3, 12)}
    count = int(rng.integers(2, 8))
    radius = 0.5 + 0.25 * count
    ground = rng.random() < 0.7
    floor_y = 0.0 if ground else float(rng.uniform(0.0, 1.0))
    fov = float(rng.uniform(30.0, 60.0))
    dist = radius / np.tan(np.radians(fov / 2)) * float(rng.uniform(0.75, 1.1))
    target = [0.0, floor_y + float(rng.uniform(0.2, 0.6)), 0.0]
    elevation = float(rng.uniform(5.0, 50.0)) if ground else float(rng.uniform(-5.0, 50.0))
    scene["sensor"] = camera.perspective(orbit_point(target, dist, float(rng.uniform(0, 360)), elevation),
                                         target, fov)

    img, _ = envmaps.sky(rng, int(rng.choice([128, 256])))
    assets[ENV] = img
    scene["environment"] = lights.envmap(ENV, log_uniform(rng, 0.5, 2.0), float(rng.uniform(0, 360)))
    if ground:
        finish = random_albedo(rng, 0.1, 0.7, max_saturation=0.5)
        bsdf = materials.diffuse(finish) if rng.random() < 0.6 else materials.roughplastic(rng, finish)
        m = compose(rotate((1, 0, 0), -90.0), scale(float(rng.uniform(2.0, 4.0)) * radius))
        scene["ground"] = transformed("disk", m, bsdf)

    spots = scatter_positions(rng, count, radius * 0.7, radius * 0.7, min_gap=0.9)
    for i, (x, z) in enumerate(spots):
        size = float(rng.uniform(0.4, 0.9))
        y0 = floor_y + (0.0 if ground else float(rng.uniform(-0.5, 0.5)))
        scene.update(random_object(rng, f"object_{i}", materials.random_bsdf(rng), (x, z), size,
                                   floor_y=y0))
    return GeneratedScene(FAMILY, seed, scene, assets)
