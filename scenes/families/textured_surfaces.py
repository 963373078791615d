"""Textured surfaces: floor, walls and objects carrying checkerboards and generated bitmaps.

Detail the denoiser must keep rather than blur: bricks, tiles, stripes, dots and noise
patterns (64..256 px EXR bitmaps, tiled 1..8 times) and procedural checkerboards, on diffuse or
rough-plastic finishes, at grazing and frontal views. Varies per seed: which of floor/back/side
wall exist and their textures, 1-4 textured or plain objects, lighting (a rectangular or
spherical area light of 10..300 W, a sun of 1..20 W/m^2, or both, plus constant sky
0.02..1), camera (close-ups to wide, fov 25..70), path depth 3..10.
"""
from __future__ import annotations

import numpy as np

from scenes import camera, integrator, lights, materials, textures
from scenes.colors import light_tint, scaled
from scenes.rooms import room
from scenes.sampling import direction, log_uniform, orbit_point
from scenes.shapes import random_object, scatter_positions, sphere, transformed
from scenes.spec import Asset, GeneratedScene
from scenes.transforms import compose, look_at, scale

FAMILY = "textured_surfaces"


def _texture(rng: np.random.Generator, assets: dict[str, Asset], name: str) -> dict:
    """A checkerboard (30%) or a new bitmap asset ``textures/<name>.exr`` (70%)."""
    if rng.random() < 0.3:
        return textures.checkerboard(rng, float(rng.uniform(2.0, 16.0)))
    filename = f"textures/{name}.exr"
    assets[filename] = textures.random_image(rng, int(rng.choice([64, 128, 256])))
    return textures.bitmap(filename, float(rng.uniform(1.0, 8.0)), nearest=rng.random() < 0.2)


def _finish(rng: np.random.Generator, tex: dict) -> dict:
    return materials.diffuse(tex) if rng.random() < 0.65 else materials.roughplastic(rng, tex)


def _lights(rng: np.random.Generator, scene: dict) -> None:
    kind = str(rng.choice(["area", "sun", "both"]))
    if kind in ("area", "both"):
        pos = orbit_point([0, 0, 0], float(rng.uniform(2.0, 4.0)), float(rng.uniform(-70, 70)),
                          float(rng.uniform(30, 75)))
        power = log_uniform(rng, 10.0, 300.0)
        if rng.random() < 0.5:
            r = float(rng.uniform(0.1, 0.4))
            radiance = lights.radiance_for_power(light_tint(rng), power, 4 * np.pi * r * r)
            scene["area_light"] = sphere(pos, r, None, lights.area(radiance))
        else:
            half = float(rng.uniform(0.2, 0.6))
            m = compose(look_at(pos, [0, 0, 0], (0, 1, 0)), scale((half, half, 1.0)))
            radiance = lights.radiance_for_power(light_tint(rng), power, 4 * half * half)
            scene["area_light"] = transformed("rectangle", m, None, lights.area(radiance))
    if kind in ("sun", "both"):
        travel = [-v for v in direction(float(rng.uniform(-80, 80)), float(rng.uniform(20, 70)))]
        scene["sun"] = lights.directional(travel, scaled(light_tint(rng, 0.5), log_uniform(rng, 1.0, 20.0)))
    scene["sky"] = lights.constant(scaled([0.7, 0.8, 1.0], log_uniform(rng, 0.02, 1.0)))


def generate(seed: int) -> GeneratedScene:
    """A textured-surfaces scene for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    assets: dict[str, Asset] = {}
    scene: dict = {"type": "scene", "integrator": integrator.path(rng, 3, 10)}
    fov = float(rng.uniform(25.0, 70.0))
    target = [float(rng.uniform(-0.5, 0.5)), float(rng.uniform(0.2, 1.0)), float(rng.uniform(-1.0, 0.5))]
    dist = float(rng.uniform(1.5, 5.0))
    scene["sensor"] = camera.perspective(
        orbit_point(target, dist, float(rng.uniform(-50, 50)), float(rng.uniform(5, 60))), target, fov)

    walls = {"floor": _finish(rng, _texture(rng, assets, "floor"))}
    if rng.random() < 0.8:
        walls["back"] = _finish(rng, _texture(rng, assets, "back"))
    if rng.random() < 0.4:
        walls[str(rng.choice(["left", "right"]))] = _finish(rng, _texture(rng, assets, "side"))
    scene.update(room(8.0, 4.0, 6.0, walls))
    _lights(rng, scene)

    spots = scatter_positions(rng, int(rng.integers(1, 5)), 1.5, 1.2, 0.9, (0.0, -0.8))
    for i, (x, z) in enumerate(spots):
        if rng.random() < 0.7:
            bsdf = _finish(rng, _texture(rng, assets, f"object_{i}"))
        else:
            bsdf = materials.random_bsdf(rng, {"diffuse": 1.0, "roughplastic": 1.0, "roughconductor": 1.0})
        scene.update(random_object(rng, f"object_{i}", bsdf, (x, z), float(rng.uniform(0.5, 1.0))))
    return GeneratedScene(FAMILY, seed, scene, assets)
