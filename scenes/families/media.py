"""Participating media: subsurface-like objects, tinted glass, smoke boxes and foggy rooms.

Every scene is rendered with ``volpath`` and holds at least one ``homogeneous`` medium. Each seed
draws one sub-kind (``kind_of(seed)`` names it):

- ``subsurface`` (40%): a main object 0.6..1.2 across (a lumpy, bunny-like blob mesh 60%, a
  sphere or a box) with a smooth (70%) or rough dielectric boundary (IOR 1.3..1.6) around a
  medium of high, tinted albedo (each channel 0.7..0.999), mean free path 0.5%..20% of the
  object's size (extinction sometimes slightly chromatic) and an isotropic or forward
  Henyey-Greenstein phase (g 0.2..0.9); beside it 0-2 small diffuse or plastic objects;
- ``absorbing`` (20%): 1-3 glass objects (smooth 75%) 0.4..0.9 across, filled with a low-albedo
  (0..0.3) medium whose transmittance across the object is a random colour at 0.3..3 optical
  depths;
- ``smoke_box`` (20%): an invisible (``null``) box 1.2..2.5 across on the floor, filled with
  smoke (optical depth 0.2..2 across, albedo 0.5..0.9, g -0.2..0.8) around 0-2 opaque objects,
  lit from outside by a spot light (cutoff 10..35 deg) or a small sphere light, half the time
  with a dim constant ambient (0.01..0.2);
- ``fog_room`` (20%): a room (4..8 x 2.5..4.5 x 4..8) open at the front (and at the top 70%)
  with dim walls (albedo 0.1..0.5), filled with thin fog that also holds the camera (optical
  depth 0.05..0.8 across the room, albedo 0.5..0.95, g 0..0.8), lit by 1-3 spot lights near the
  top and/or a window-shaped area light in a wall (light shafts), with 1-4 opaque objects
  casting volumetric shadows.

The first two kinds stand on a diffuse floor (sometimes a checkerboard) with an optional back
wall, lit by an env map (sky or studio, 60%) and 0-2 large area lights, or by 1-2 large area
lights and a dim constant fill (0.03..0.3); the second light, and a quarter of the first ones,
stand behind the objects (light through the medium). Camera orbit and fov vary. ``max_depth``
(16..64) and the depth where Russian roulette starts (2..8) are drawn from ranges per kind
(``DEPTHS``) that keep a 256x256, 1024-spp render within about a minute on two cores.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from scenes import camera, envmaps, lights, materials, textures
from scenes.colors import hsv_to_rgb, light_tint, random_albedo, rgb, scaled
from scenes.meshes import ply_bytes
from scenes.rooms import room, wall
from scenes.sampling import log_uniform, orbit_point
from scenes.shapes import Shape, ply, random_object, scatter_positions, sphere, transformed
from scenes.spec import Asset, GeneratedScene
from scenes.transforms import compose, look_at, rotate, scale, translate

FAMILY = "media"
KINDS = {"subsurface": 0.4, "absorbing": 0.2, "smoke_box": 0.2, "fog_room": 0.2}
# (max_depth range, rr_depth range) per kind, inclusive: dense scattering needs long paths;
# volpath costs about twice what path does per bounce, so Russian roulette starts early where
# paths bounce a lot (fog rooms, smoke, glass), keeping 1024 spp at 256x256 near a minute.
DEPTHS = {"subsurface": ((16, 64), (4, 8)), "absorbing": ((16, 32), (3, 6)),
          "smoke_box": ((16, 24), (3, 5)), "fog_room": ((16, 32), (2, 3))}
ENV = "textures/env.exr"
OPAQUE_BSDFS = {"diffuse": 2.0, "roughplastic": 1.0, "plastic": 0.5, "roughconductor": 1.0}
BLOB_SUBDIVISIONS = 4  # 5120 triangles
Medium = dict[str, Any]


def kind_of(seed: int) -> str:
    """The sub-kind ``generate(seed)`` builds (one of ``KINDS``)."""
    return _draw_kind(np.random.default_rng(seed))


def _draw_kind(rng: np.random.Generator) -> str:
    names = list(KINDS)
    p = np.array([KINDS[k] for k in names])
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def volpath(rng: np.random.Generator, depth: tuple[int, int],
            rr_depth: tuple[int, int]) -> dict[str, Any]:
    """A ``volpath`` integrator: ``max_depth`` and ``rr_depth`` (the depth where Russian roulette
    starts) uniform in the given inclusive ranges."""
    return {"type": "volpath", "max_depth": int(rng.integers(depth[0], depth[1] + 1)),
            "rr_depth": int(rng.integers(rr_depth[0], rr_depth[1] + 1))}


def homogeneous(albedo: list[float], sigma_t: list[float] | float, density: float,
                g: float | None = None, sample_emitters: bool = True) -> Medium:
    """A ``homogeneous`` medium: extinction ``sigma_t`` (RGB in [0, 1] or a float) times
    ``density`` (1/world units), single-scattering ``albedo`` (RGB in [0, 1]); HG phase of
    asymmetry ``g`` or isotropic. ``sample_emitters=False`` for media behind a dielectric,
    where shadow rays are always blocked."""
    medium: Medium = {"type": "homogeneous", "albedo": rgb(albedo),
                      "sigma_t": rgb(sigma_t) if isinstance(sigma_t, list) else float(sigma_t),
                      "scale": float(density), "sample_emitters": bool(sample_emitters)}
    if g is not None:
        medium["phase"] = {"type": "hg", "g": float(g)}
    return medium


def _icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit-sphere vertices (Vx3) and outward, counter-clockwise triangles (Fx3)."""
    t = (1.0 + 5.0**0.5) / 2.0
    v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t],
                  [0, -1, -t], [0, 1, -t], [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    for _ in range(subdivisions):
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        unique, inverse = np.unique(edges, axis=0, return_inverse=True)
        mid = (len(v) + inverse.reshape(-1)).reshape(3, -1)  # midpoints of ab, bc, ca per face
        middle = v[unique[:, 0]] + v[unique[:, 1]]
        v = np.concatenate([v, middle / np.linalg.norm(middle, axis=1, keepdims=True)])
        a, b, c = f.T
        f = np.concatenate([np.stack(s, axis=1) for s in
                            ((a, mid[0], mid[2]), (b, mid[1], mid[0]), (c, mid[2], mid[1]), mid)])
    return v, f


def blob_mesh(rng: np.random.Generator) -> bytes:
    """PLY of a closed, star-shaped lumpy blob: a rounded box-to-sphere (superellipsoid exponent
    2..5) with 2-6 smooth bumps, stretched per axis. It spans [-0.5, 0.5] along its longest
    axis, stands on y = 0, is centred on the Y axis and has outward smooth normals."""
    dirs, faces = _icosphere(BLOB_SUBDIVISIONS)
    p = float(rng.uniform(2.0, 5.0))
    radius = np.sum(np.abs(dirs) ** p, axis=1) ** (-1.0 / p)
    bumps = np.ones(len(dirs))
    for _ in range(int(rng.integers(2, 7))):
        center = rng.normal(size=3)
        center /= np.linalg.norm(center)
        width = log_uniform(rng, 0.05, 0.4)
        bumps += float(rng.uniform(0.1, 0.6)) * np.exp((dirs @ center - 1.0) / width)
    points = dirs * (radius * bumps)[:, None] * rng.uniform(0.6, 1.0, size=3)
    lo, hi = points.min(axis=0), points.max(axis=0)
    points = (points - [(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2]) / float((hi - lo).max())
    tri = points[faces]
    face_n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 x area
    normals = np.zeros_like(points)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_n)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    uvs = np.stack([0.5 + np.arctan2(dirs[:, 0], -dirs[:, 2]) / (2 * np.pi),
                    np.arccos(np.clip(dirs[:, 1], -1.0, 1.0)) / np.pi], axis=1)
    return ply_bytes(points, normals, uvs, faces)


def _filled_object(rng: np.random.Generator, name: str, assets: dict[str, Asset],
                   xz: tuple[float, float], size: float, bsdf: dict[str, Any],
                   medium: Callable[[np.random.Generator, float], Medium],
                   blob_weight: float) -> dict[str, Shape]:
    """A blob (probability ``blob_weight``), sphere or box ``size`` across standing on y = 0 at
    ``xz``, filled with ``medium(rng, size)`` (a medium whose density suits that extent)."""
    x, z = xz
    yaw = float(rng.uniform(0.0, 360.0))
    kind = str(rng.choice(["blob", "sphere", "box"], p=[blob_weight, *[(1 - blob_weight) / 2] * 2]))
    if kind == "blob":
        filename = f"meshes/{name}.ply"
        assets[filename] = blob_mesh(rng)
        m = compose(translate((x, 0.0, z)), rotate((0, 1, 0), yaw), scale(size))
        shape = ply(filename, m, bsdf)
    elif kind == "sphere":
        shape = sphere((x, size / 2, z), size / 2, bsdf)
    else:
        half = np.array([0.5, rng.uniform(0.3, 0.5), rng.uniform(0.25, 0.5)]) * size
        m = compose(translate((x, half[1], z)), rotate((0, 1, 0), yaw), scale(half))
        shape = transformed("cube", m, bsdf)
    shape["interior"] = medium(rng, size)
    return {name: shape}


def _subsurface_medium(rng: np.random.Generator, size: float) -> Medium:
    """High tinted albedo (0.7..0.999), mean free path 0.5%..20% of ``size``."""
    base = 1.0 - log_uniform(rng, 0.001, 0.3)
    albedo = np.clip(1.0 - (1.0 - base) * rng.uniform(1.0, 8.0, size=3), 0.7, 0.999)
    mfp = log_uniform(rng, 0.005, 0.2) * size
    ratio = np.ones(3) if rng.random() < 0.7 else rng.uniform(max(0.6, mfp / (0.2 * size)), 1.0, 3)
    ratio /= ratio.max()  # per-channel mean free path mfp / ratio stays within 0.5%..20%
    g = None if rng.random() < 0.5 else float(rng.uniform(0.2, 0.9))
    return homogeneous([float(a) for a in albedo], [float(r) for r in ratio], 1.0 / mfp, g,
                       sample_emitters=False)


def _absorbing_medium(rng: np.random.Generator, size: float) -> Medium:
    """Low albedo (0..0.3); transmittance across ``size`` is a colour at 0.3..3 optical depths."""
    color = hsv_to_rgb(rng.random(), rng.uniform(0.3, 1.0), 1.0)
    optical = -np.log(np.clip(color, 0.05, 1.0)) + 0.05
    depth = log_uniform(rng, 0.3, 3.0)
    albedo = scaled([1.0, 1.0, 1.0] if rng.random() < 0.5 else list(color), rng.uniform(0.0, 0.3))
    return homogeneous(albedo, [float(o) for o in optical / optical.max()], depth / size,
                       sample_emitters=False)


def _scattering_medium(rng: np.random.Generator, optical_depth: float, extent: float,
                       albedo_range: tuple[float, float], g_range: tuple[float, float]) -> Medium:
    """Smoke/fog: greyish albedo in ``albedo_range``, ``optical_depth`` across ``extent``."""
    albedo = hsv_to_rgb(rng.random(), rng.uniform(0.0, 0.15), rng.uniform(*albedo_range))
    g = None if rng.random() < 0.3 else float(rng.uniform(*g_range))
    return homogeneous([float(a) for a in albedo], 1.0, optical_depth / extent, g)


def _area_light(rng: np.random.Generator, azimuth: float, target: list[float]) -> Shape:
    """A sphere (radius 0.2..0.6) or rectangle (0.6..2 wide) area light of 20..300 W, 2.5..5
    away from ``target``: large, since light reaches a dielectric-bounded medium only through
    paths that leave it and hit the light by chance (shadow rays cannot cross the boundary)."""
    position = orbit_point(target, float(rng.uniform(2.5, 5.0)), azimuth, float(rng.uniform(15, 70)))
    power, tint = log_uniform(rng, 20.0, 300.0), light_tint(rng, 0.7)
    if rng.random() < 0.5:
        radius = float(rng.uniform(0.2, 0.6))
        return sphere(position, radius, None,
                      lights.area(lights.radiance_for_power(tint, power, 4 * np.pi * radius**2)))
    half = float(rng.uniform(0.3, 1.0))
    m = compose(look_at(position, target, (0, 1, 0)), scale((half, half, 1.0)))
    return transformed("rectangle", m, None,
                       lights.area(lights.radiance_for_power(tint, power, 4 * half * half)))


def _stage(rng: np.random.Generator, scene: dict, assets: dict[str, Asset], extent: float,
           target: list[float]) -> None:
    """Camera, floor (+ back wall), env map and/or area lights around objects ``extent`` wide
    at the origin."""
    fov = float(rng.uniform(25.0, 50.0))
    dist = extent / np.tan(np.radians(fov / 2)) * float(rng.uniform(0.9, 1.3))
    azimuth = float(rng.uniform(-60.0, 60.0))
    origin = orbit_point(target, dist, azimuth, float(rng.uniform(8.0, 45.0)))
    scene["sensor"] = camera.perspective(origin, target, fov)
    if rng.random() < 0.3:
        floor = materials.diffuse(textures.checkerboard(rng, float(rng.uniform(4, 16))))
    else:
        floor = materials.diffuse(random_albedo(rng, 0.2, 0.8, max_saturation=0.4))
    walls = {"floor": floor}
    if rng.random() < 0.5:
        walls["back"] = materials.diffuse(random_albedo(rng, 0.2, 0.8, max_saturation=0.4))
    scene.update(room(12.0, 6.0, 12.0, walls))
    has_env = rng.random() < 0.6
    if has_env:
        assets[ENV] = envmaps.random_envmap(rng)
        scene["environment"] = lights.envmap(ENV, log_uniform(rng, 0.3, 2.0),
                                             float(rng.uniform(0, 360)))
    else:  # soft fill light: paths leaving a dielectric-bounded medium rarely hit a small light
        scene["ambient"] = lights.constant(scaled(light_tint(rng, 0.5), log_uniform(rng, 0.03, 0.3)))
    for i in range(int(rng.integers(0 if has_env else 1, 3))):
        behind = i == 1 or rng.random() < 0.25  # a back light shines through the medium
        # A front light keeps 50..130 deg of azimuth from the camera, so it cannot hide the view.
        offset = float(rng.uniform(-50, 50)) + 180.0 if behind \
            else float(rng.uniform(50, 130)) * float(rng.choice([-1.0, 1.0]))
        light_az = azimuth + offset
        scene[f"light_{i}"] = _area_light(rng, light_az, target)


def _objects_scene(rng: np.random.Generator, kind: str, scene: dict,
                   assets: dict[str, Asset]) -> None:
    """``subsurface`` or ``absorbing``: filled dielectric objects on a lit floor."""
    count = 1 if kind == "subsurface" else int(rng.integers(1, 4))
    extras = int(rng.integers(0, 3)) if kind == "subsurface" else 0
    spread = 0.0 if count + extras == 1 else float(rng.uniform(0.6, 1.1))
    spots = scatter_positions(rng, count + extras, spread, spread, min_gap=1.0)
    _stage(rng, scene, assets, 1.0 + spread, [0.0, float(rng.uniform(0.25, 0.5)), 0.0])
    for i, xz in enumerate(spots):
        if i >= count:
            bsdf = materials.random_bsdf(rng, {"diffuse": 1.0, "plastic": 1.0, "roughplastic": 1.0})
            scene.update(random_object(rng, f"object_{i}", bsdf, xz, float(rng.uniform(0.25, 0.5)),
                                       kinds=("sphere", "cube")))
            continue
        rough = rng.random() < (0.3 if kind == "subsurface" else 0.25)
        bsdf = materials.roughdielectric(rng) if rough else materials.dielectric(rng)
        if kind == "subsurface":
            bsdf["int_ior"] = float(rng.uniform(1.3, 1.6))
            size, medium, blob_weight = float(rng.uniform(0.6, 1.2)), _subsurface_medium, 0.6
        else:
            size, medium, blob_weight = float(rng.uniform(0.4, 0.9)), _absorbing_medium, 0.3
        scene.update(_filled_object(rng, f"object_{i}", assets, xz, size, bsdf, medium, blob_weight))


def _smoke_box_scene(rng: np.random.Generator, scene: dict, assets: dict[str, Asset]) -> None:
    """A null-bounded smoke box (its bottom below the floor) around 0-2 objects, lit from outside."""
    half = rng.uniform(0.6, 1.25, size=3)
    target = [0.0, float(half[1]) * 0.7, 0.0]
    fov = float(rng.uniform(30.0, 55.0))
    dist = float(np.linalg.norm(half)) / np.tan(np.radians(fov / 2)) * float(rng.uniform(1.4, 2.0))
    azimuth = float(rng.uniform(-60.0, 60.0))
    scene["sensor"] = camera.perspective(orbit_point(target, dist, azimuth, float(rng.uniform(5, 40))),
                                         target, fov)
    walls = {"floor": materials.diffuse(random_albedo(rng, 0.2, 0.8, max_saturation=0.4))}
    if rng.random() < 0.5:
        walls["back"] = materials.diffuse(random_albedo(rng, 0.2, 0.8, max_saturation=0.4))
    scene.update(room(12.0, 6.0, 12.0, walls))
    box = compose(translate((0.0, half[1] - 0.1, 0.0)), scale(half))
    medium = _scattering_medium(rng, log_uniform(rng, 0.2, 2.0), 2 * float(half.min()),
                                (0.5, 0.9), (-0.2, 0.8))
    scene["smoke"] = transformed("cube", box, materials.null())
    scene["smoke"]["interior"] = medium
    count = int(rng.integers(0, 3))
    spots = scatter_positions(rng, count, float(half[0]) - 0.35, float(half[2]) - 0.35, min_gap=0.6)
    for i, xz in enumerate(spots[:count]):
        bsdf = materials.random_bsdf(rng, OPAQUE_BSDFS)
        scene.update(random_object(rng, f"object_{i}", bsdf, xz, float(rng.uniform(0.25, 0.5))))
    light_az = azimuth + float(rng.uniform(40, 180)) * float(rng.choice([-1.0, 1.0]))
    center = [0.0, float(half[1]) - 0.1, 0.0]  # the light stays outside the box's bounding sphere
    reach = float(np.linalg.norm(half)) + float(rng.uniform(1.0, 2.5))
    position = orbit_point(center, reach, light_az, float(rng.uniform(25, 75)))
    tint = light_tint(rng, 0.7)
    if rng.random() < 0.6:
        aim = [float(rng.uniform(-0.3, 0.3)) * half[0], 0.0, float(rng.uniform(-0.3, 0.3)) * half[2]]
        cutoff = float(rng.uniform(10.0, 35.0))
        scene["spot"] = lights.spot(position, aim, scaled(tint, log_uniform(rng, 20.0, 400.0)),
                                    cutoff, cutoff * float(rng.uniform(0.3, 0.9)))
    else:
        radius = float(rng.uniform(0.05, 0.3))
        power = log_uniform(rng, 20.0, 300.0)
        radiance = lights.radiance_for_power(tint, power, 4 * np.pi * radius**2)
        scene["lamp"] = sphere(position, radius, None, lights.area(radiance))
    if rng.random() < 0.5:
        scene["ambient"] = lights.constant(scaled([1.0, 1.0, 1.0], log_uniform(rng, 0.01, 0.2)))


def _window_light(rng: np.random.Generator, w: float, h: float,
                  d: float) -> tuple[str, tuple[float, ...], Shape]:
    """An opening in a side or back wall, covered from outside by an area light facing in."""
    side = str(rng.choice(["left", "right", "back"]))
    g = wall(side, w, h, d)
    half_u, half_v = float(rng.uniform(0.15, 0.4)) * g.half_u, float(rng.uniform(0.2, 0.45)) * g.half_v
    cu = float(rng.uniform(-0.6, 0.6)) * (g.half_u - half_u)
    cv = float(rng.uniform(0.0, 0.6)) * (g.half_v - half_v)
    hole = (cu - half_u, cu + half_u, cv - half_v, cv + half_v)
    m = 0.1  # the light overlaps the opening so that no path slips out past its edges
    panel = g.panel(hole[0] - m, hole[1] + m, hole[2] - m, hole[3] + m, offset=-0.02)
    radiance = scaled(light_tint(rng, 0.8), log_uniform(rng, 3.0, 40.0))
    return side, hole, transformed("rectangle", panel, None, lights.area(radiance))


def _fog_room_scene(rng: np.random.Generator, scene: dict) -> None:
    """A room open at the front (and maybe the top) filled with thin fog, the camera inside it.

    The fog is the interior of a ``null`` box reaching past the floor, walls and ceiling, so
    every surface of the room lies in it while paths leaving through the openings escape (in a
    closed room every path bounces until Russian roulette ends it: 1.5-2x the render time).
    """
    w, h, d = float(rng.uniform(4.0, 8.0)), float(rng.uniform(2.5, 4.5)), float(rng.uniform(4.0, 8.0))
    ceiling = rng.random() < 0.3
    top = h + 0.1 if ceiling else h
    scene["fog"] = _scattering_medium(rng, log_uniform(rng, 0.05, 0.8), d, (0.5, 0.95), (0.0, 0.8))
    eye = (float(rng.uniform(-0.25, 0.25)) * w, float(rng.uniform(0.3, 0.6)) * h, 0.42 * d)
    look = (float(rng.uniform(-0.2, 0.2)) * w, float(rng.uniform(0.1, 0.5)) * h, -d / 2)
    scene["sensor"] = camera.perspective(eye, look, float(rng.uniform(45.0, 75.0)))
    scene["sensor"]["medium"] = {"type": "ref", "id": "fog"}
    box = compose(translate((0.0, (top - 0.1) / 2, -0.05)),
                  scale((w / 2 + 0.1, (top + 0.1) / 2, d / 2 + 0.05)))
    scene["fog_volume"] = transformed("cube", box, materials.null())
    scene["fog_volume"]["interior"] = {"type": "ref", "id": "fog"}
    has_window = rng.random() < 0.5
    opening = None
    if has_window:
        side, hole, scene["window_light"] = _window_light(rng, w, h, d)
        opening = (side, hole)
    names = ("floor", "back", "left", "right") + (("ceiling",) if ceiling else ())
    bsdfs = {name: materials.diffuse(random_albedo(rng, 0.1, 0.5, max_saturation=0.4))
             for name in names}
    scene.update(room(w, h, d, bsdfs, opening))
    spots = scatter_positions(rng, int(rng.integers(1, 5)), 0.35 * w, 0.3 * d, 0.8, (0.0, -0.1 * d))
    for i, xz in enumerate(spots):
        bsdf = materials.random_bsdf(rng, OPAQUE_BSDFS)
        scene.update(random_object(rng, f"object_{i}", bsdf, xz, float(rng.uniform(0.3, 0.9))))
    for i in range(int(rng.integers(0 if has_window else 1, 4))):
        pos = (float(rng.uniform(-0.4, 0.4)) * w, h - float(rng.uniform(0.05, 0.3)),
               float(rng.uniform(-0.4, 0.2)) * d)
        aim = (float(rng.uniform(-0.35, 0.35)) * w, 0.0, float(rng.uniform(-0.4, 0.2)) * d)
        cutoff = float(rng.uniform(8.0, 30.0))
        intensity = scaled(light_tint(rng, 0.8), log_uniform(rng, 10.0, 200.0))
        scene[f"spot_{i}"] = lights.spot(pos, aim, intensity, cutoff,
                                         cutoff * float(rng.uniform(0.3, 0.9)))


def generate(seed: int) -> GeneratedScene:
    """A participating-media scene for ``seed`` (see the module docstring)."""
    rng = np.random.default_rng(seed)
    kind = _draw_kind(rng)
    assets: dict[str, Asset] = {}
    scene: dict = {"type": "scene", "integrator": volpath(rng, *DEPTHS[kind])}
    if kind in ("subsurface", "absorbing"):
        _objects_scene(rng, kind, scene, assets)
    elif kind == "smoke_box":
        _smoke_box_scene(rng, scene, assets)
    else:
        _fog_room_scene(rng, scene)
    return GeneratedScene(FAMILY, seed, scene, assets)
