"""Indoor rooms lit only through a window: sun (directional) plus sky (constant or env map).

The room is closed except for one rectangular opening in a side or back wall; all light comes
in through it, so most of the image is lit indirectly (the hard case for denoisers). Varies per
seed: room size, wall/floor colours (floor sometimes textured), window wall/size/position, sun
direction (always shining in through the window) and irradiance (3..60), sky radiance
(0.3..5, constant or a procedural sky map), 0-3 pieces of furniture, camera position in the
room's front half, fov 50..75, path depth 4..7.
"""
from __future__ import annotations

import numpy as np

from scenes import camera, envmaps, integrator, lights, materials, textures
from scenes.colors import light_tint, random_albedo, scaled
from scenes.rooms import room, wall
from scenes.sampling import log_uniform
from scenes.shapes import random_object, scatter_positions
from scenes.spec import Asset, GeneratedScene

FAMILY = "indoor_room"
ENV = "textures/sky.exr"
FLOOR_TEX = "textures/floor.exr"
FURNITURE_BSDFS = {"diffuse": 3.0, "roughplastic": 1.0, "plastic": 0.5, "roughconductor": 0.5}


def _window(rng: np.random.Generator, w: float, h: float, d: float) -> tuple[str, tuple[float, ...]]:
    side = str(rng.choice(["left", "right", "back"]))
    g = wall(side, w, h, d)
    half_w = float(rng.uniform(0.25, 0.6)) * g.half_u
    half_h = float(rng.uniform(0.25, 0.55)) * g.half_v
    cu = float(rng.uniform(-1, 1)) * (g.half_u - half_w) * 0.8
    cv = float(rng.uniform(-0.2, 0.5)) * (g.half_v - half_h)
    return side, (cu - half_w, cu + half_w, cv - half_h, cv + half_h)


def _sun_direction(rng: np.random.Generator, w: float, h: float, d: float,
                   side: str, hole: tuple[float, ...]) -> list[float]:
    """Direction of travel of sunlight entering through the window and hitting the floor."""
    g = wall(side, w, h, d)
    u0, u1, v0, v1 = hole
    window = g.center + 0.5 * (u0 + u1) * g.u + 0.5 * (v0 + v1) * g.v
    spot = np.array([rng.uniform(-0.3, 0.3) * w, 0.0, rng.uniform(-0.3, 0.3) * d])
    travel = spot - window
    travel[1] = min(travel[1], -0.3 * np.linalg.norm(travel))  # the sun is above the horizon
    return [float(v) for v in travel / np.linalg.norm(travel)]


def generate(seed: int) -> GeneratedScene:
    """An indoor room lit through a window for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    assets: dict[str, Asset] = {}
    w, h, d = float(rng.uniform(3.0, 6.0)), float(rng.uniform(2.4, 3.2)), float(rng.uniform(3.0, 6.0))
    scene: dict = {"type": "scene", "integrator": integrator.path(rng, 4, 7)}
    eye = (float(rng.uniform(-0.3, 0.3)) * w, float(rng.uniform(1.0, 1.8)), 0.4 * d)
    look = (float(rng.uniform(-0.3, 0.3)) * w, float(rng.uniform(0.4, 1.4)), -0.5 * d)
    scene["sensor"] = camera.perspective(eye, look, float(rng.uniform(50.0, 75.0)))

    wall_color = random_albedo(rng, 0.4, 0.8, max_saturation=0.35)
    if rng.random() < 0.5:
        assets[FLOOR_TEX] = textures.random_image(rng, 128)
        floor = materials.diffuse(textures.bitmap(FLOOR_TEX, float(rng.uniform(1.0, 4.0))))
    else:
        floor = materials.diffuse(random_albedo(rng, 0.1, 0.6))
    bsdfs = {name: materials.diffuse(wall_color) for name in ("ceiling", "back", "front", "left", "right")}
    bsdfs["floor"] = floor
    side, hole = _window(rng, w, h, d)
    scene.update(room(w, h, d, bsdfs, opening=(side, hole)))

    sun = _sun_direction(rng, w, h, d, side, hole)
    scene["sun"] = lights.directional(sun, scaled(light_tint(rng, 0.5), log_uniform(rng, 3.0, 60.0)))
    sky_level = log_uniform(rng, 0.3, 5.0)
    if rng.random() < 0.5:
        img, _ = envmaps.sky(rng, 128, sun=False)
        assets[ENV] = img
        scene["sky"] = lights.envmap(ENV, sky_level, float(rng.uniform(0, 360)))
    else:
        scene["sky"] = lights.constant(scaled([0.6, 0.75, 1.0], sky_level))

    count = int(rng.integers(0, 4))
    spots = scatter_positions(rng, count, 0.3 * w, 0.2 * d, 0.9, (0.0, -0.2 * d)) if count else []
    for i, (x, z) in enumerate(spots):
        bsdf = materials.random_bsdf(rng, FURNITURE_BSDFS)
        scene.update(random_object(rng, f"furniture_{i}", bsdf, (x, z), float(rng.uniform(0.5, 1.2)),
                                   kinds=("cube", "cube", "cylinder", "sphere")))
    return GeneratedScene(FAMILY, seed, scene, assets)
