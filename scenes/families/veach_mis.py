"""Veach-style multiple-importance-sampling tests: glossy plates reflecting lights of many sizes.

2-5 sphere lights in a row share one power, so their radiance grows as 1/radius^2 (radii
0.01..0.5, radiance ~1..1e4); 3-5 plates, tilted so every light is mirrored towards the camera,
range from near-mirror to rough (alpha 0.005..0.4, metal or plastic). Varies per seed: light
count/radii/power/tints, plate count/roughness progression/materials, backdrop albedo and
whether a dim fill light exists, camera jitter and fov, path depth 3..10.
"""
from __future__ import annotations

import numpy as np

from scenes import camera, integrator, lights, materials
from scenes.colors import light_tint, random_albedo, rgb
from scenes.rooms import room
from scenes.sampling import log_uniform
from scenes.shapes import sphere, transformed
from scenes.spec import GeneratedScene
from scenes.transforms import compose, scale, translate

FAMILY = "veach_mis"


def _plate_bsdf(rng: np.random.Generator, alpha: float, metal: bool) -> dict:
    if metal:
        return {"type": "roughconductor", "material": str(rng.choice(materials.CONDUCTORS)),
                "distribution": "beckmann", "alpha": alpha}
    return {"type": "roughplastic", "distribution": "beckmann", "alpha": alpha,
            "diffuse_reflectance": rgb(random_albedo(rng, 0.02, 0.3)), "int_ior": 1.5}


def _plate(center: np.ndarray, normal: np.ndarray, width: float, depth: float) -> np.ndarray:
    """to_world of a width x depth rectangle at ``center`` whose normal is ``normal``."""
    u = np.array([1.0, 0.0, 0.0])
    v = np.cross(normal, u)
    v /= np.linalg.norm(v)
    u = np.cross(v, normal)
    basis = np.eye(4)
    basis[:3, 0], basis[:3, 1], basis[:3, 2] = u, v, normal
    return compose(translate(center), basis, scale((width / 2, depth / 2, 1.0)))


def generate(seed: int) -> GeneratedScene:
    """A Veach MIS scene for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    scene: dict = {"type": "scene", "integrator": integrator.path(rng, 3, 10)}
    eye = np.array([float(rng.uniform(-0.5, 0.5)), float(rng.uniform(1.8, 3.0)),
                    float(rng.uniform(4.5, 6.0))])
    look = np.array([0.0, float(rng.uniform(0.4, 1.0)), 0.0])
    scene["sensor"] = camera.perspective(eye, look, float(rng.uniform(40.0, 55.0)))
    scene.update(room(20.0, 10.0, 20.0, {"floor": materials.diffuse(random_albedo(rng, 0.05, 0.4)),
                                           "back": materials.diffuse(random_albedo(rng, 0.05, 0.4))},
                      prefix="backdrop_"))

    n_lights = int(rng.integers(2, 6))
    radii = np.geomspace(log_uniform(rng, 0.01, 0.05), log_uniform(rng, 0.2, 0.5), n_lights)
    rng.shuffle(radii)
    power = log_uniform(rng, 20.0, 200.0)
    xs = np.linspace(-2.2, 2.2, n_lights) + rng.uniform(-0.1, 0.1, n_lights)
    light_y, light_z = float(rng.uniform(2.5, 4.0)), float(rng.uniform(-3.0, -1.5))
    for i, (x, r) in enumerate(zip(xs, radii)):
        radiance = lights.radiance_for_power(light_tint(rng, 0.8), power, 4 * np.pi * r * r)
        scene[f"light_{i}"] = sphere((float(x), light_y, light_z), float(r), None, lights.area(radiance))
    if rng.random() < 0.5:
        scene["fill"] = lights.constant([log_uniform(rng, 0.002, 0.05)] * 3)

    n_plates = int(rng.integers(3, 6))
    alphas = np.geomspace(log_uniform(rng, 0.005, 0.02), log_uniform(rng, 0.1, 0.4), n_plates)
    metal = rng.random() < 0.6
    lights_center = np.array([0.0, light_y, light_z])
    for i, z in enumerate(np.linspace(-0.8, 1.6, n_plates)):
        center = np.array([0.0, 0.15 + 0.35 * (n_plates - 1 - i) / max(n_plates - 1, 1), z])
        to_eye = (eye - center) / np.linalg.norm(eye - center)
        to_light = (lights_center - center) / np.linalg.norm(lights_center - center)
        normal = (to_eye + to_light) / np.linalg.norm(to_eye + to_light)
        m = _plate(center, normal, 5.0, 2.4 / n_plates * 0.9)
        scene[f"plate_{i}"] = transformed("rectangle", m, _plate_bsdf(rng, float(alphas[i]), metal))
    return GeneratedScene(FAMILY, seed, scene, {})
