"""Meshes: a generated height-field terrain (binary PLY, <= ~18k triangles) with built-in shapes.

The terrain is fractal value noise on a 64..96 vertex grid (smooth normals, UVs), scaled to
4..10 units wide with relief 5..25% of its width; spheres, cubes, cylinders and disks rest
on it. Varies per seed: terrain shape and material (diffuse, rough plastic, or a bitmap/
checkerboard texture), 1-5 objects of all material kinds, light (sun 1..30 W/m^2 plus
constant sky, or a procedural sky env map with sun), camera height/orbit/fov, path depth 3..12.
"""
from __future__ import annotations

import numpy as np

from scenes import camera, envmaps, integrator, lights, materials, meshes, textures
from scenes.colors import light_tint, random_albedo, scaled
from scenes.sampling import direction, log_uniform, orbit_point
from scenes.shapes import ply, random_object, scatter_positions, transformed
from scenes.spec import Asset, GeneratedScene
from scenes.transforms import compose, rotate, scale, translate

FAMILY = "terrain"
MESH = "meshes/terrain.ply"
ENV = "textures/sky.exr"
TEX = "textures/terrain.exr"


def _height_at(heights: np.ndarray, size: float, x: float, z: float) -> float:
    """Terrain height (world units, before scaling by ``size``) under world point (x, z)."""
    rows, cols = heights.shape
    c = float(np.clip((x / size + 1) / 2 * (cols - 1), 0, cols - 1))
    r = float(np.clip((z / size + 1) / 2 * (rows - 1), 0, rows - 1))
    r0, c0 = min(int(r), rows - 2), min(int(c), cols - 2)
    fr, fc = r - r0, c - c0
    top = heights[r0, c0] * (1 - fc) + heights[r0, c0 + 1] * fc
    bottom = heights[r0 + 1, c0] * (1 - fc) + heights[r0 + 1, c0 + 1] * fc
    return float(top * (1 - fr) + bottom * fr)


def _terrain_bsdf(rng: np.random.Generator, assets: dict[str, Asset]) -> dict:
    choice = rng.random()
    if choice < 0.3:
        assets[TEX] = textures.random_image(rng, 128)
        return materials.diffuse(textures.bitmap(TEX, float(rng.uniform(1.0, 6.0))))
    if choice < 0.4:
        return materials.diffuse(textures.checkerboard(rng, float(rng.uniform(4.0, 20.0))))
    color = random_albedo(rng, 0.1, 0.7, max_saturation=0.6)
    return materials.diffuse(color) if choice < 0.8 else materials.roughplastic(rng, color)


def generate(seed: int) -> GeneratedScene:
    """A terrain-and-objects scene for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    assets: dict[str, Asset] = {}
    scene: dict = {"type": "scene", "integrator": integrator.path(rng, 3, 12)}
    half = float(rng.uniform(2.0, 5.0))  # half width of the terrain
    relief = float(rng.uniform(0.1, 0.5)) * half
    assets[MESH], heights = meshes.random_terrain(rng, int(rng.integers(64, 97)), 1.0)
    heights = heights * relief

    fov = float(rng.uniform(30.0, 65.0))
    target = [float(rng.uniform(-0.2, 0.2)) * half, 0.0, float(rng.uniform(-0.2, 0.2)) * half]
    target[1] = _height_at(heights, half, target[0], target[2])
    eye = orbit_point(target, half * float(rng.uniform(0.8, 1.6)), float(rng.uniform(0, 360)),
                      float(rng.uniform(10, 50)))
    eye[1] = max(eye[1], _height_at(heights, half, eye[0], eye[2]) + 0.3 * half)
    scene["sensor"] = camera.perspective(eye, target, fov)

    if rng.random() < 0.5:
        img, _ = envmaps.sky(rng, 128)
        assets[ENV] = img
        scene["sky"] = lights.envmap(ENV, log_uniform(rng, 0.5, 2.0), float(rng.uniform(0, 360)))
    else:
        travel = [-v for v in direction(float(rng.uniform(0, 360)), float(rng.uniform(10, 70)))]
        scene["sun"] = lights.directional(travel, scaled(light_tint(rng, 0.5), log_uniform(rng, 1.0, 30.0)))
        scene["sky"] = lights.constant(scaled([0.6, 0.75, 1.0], log_uniform(rng, 0.05, 1.5)))

    scene["terrain"] = ply(MESH, scale((half, relief, half)), _terrain_bsdf(rng, assets))

    spots = scatter_positions(rng, int(rng.integers(1, 6)), 0.5 * half, 0.5 * half, 0.25 * half,
                              (target[0], target[2]))
    for i, (x, z) in enumerate(spots):
        size = float(rng.uniform(0.1, 0.25)) * half
        y = _height_at(heights, half, x, z) - 0.05 * size
        if rng.random() < 0.15:  # a flat disk lying on the ground, e.g. a pond
            disk = compose(translate((x, y + 0.1 * size, z)), rotate((1, 0, 0), -90.0), scale(size))
            scene[f"object_{i}"] = transformed("disk", disk, materials.random_bsdf(rng))
            continue
        scene.update(random_object(rng, f"object_{i}", materials.random_bsdf(rng), (x, z), size, y))
    return GeneratedScene(FAMILY, seed, scene, assets)
