"""Shape dicts: Mitsuba's built-in primitives and PLY meshes, plus random objects on a floor.

Sizes and positions are world units in Mitsuba's Y-up world; the floor is the plane y = ``floor_y``.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from scenes.transforms import compose, rotate, scale, to_mitsuba, translate

Shape = dict[str, Any]
OBJECT_KINDS = ("sphere", "cube", "cylinder")


def sphere(center: Sequence[float], radius: float, bsdf: dict[str, Any] | None = None,
           emitter: dict[str, Any] | None = None) -> Shape:
    """A sphere; an emitter makes it an area light."""
    shape: Shape = {"type": "sphere", "center": [float(v) for v in center], "radius": float(radius)}
    return _attach(shape, bsdf, emitter)


def transformed(kind: str, to_world: np.ndarray, bsdf: dict[str, Any] | None = None,
                emitter: dict[str, Any] | None = None) -> Shape:
    """A built-in shape (``cube``, ``cylinder``, ``disk``, ``rectangle``) placed by ``to_world``."""
    return _attach({"type": kind, "to_world": to_mitsuba(to_world)}, bsdf, emitter)


def ply(filename: str, to_world: np.ndarray, bsdf: dict[str, Any] | None = None) -> Shape:
    """A PLY mesh asset (relative file name) placed by ``to_world``."""
    return _attach({"type": "ply", "filename": filename, "to_world": to_mitsuba(to_world),
                    "face_normals": False}, bsdf, None)


def _attach(shape: Shape, bsdf: dict[str, Any] | None, emitter: dict[str, Any] | None) -> Shape:
    if bsdf is not None:
        shape["bsdf"] = bsdf
    if emitter is not None:
        shape["emitter"] = emitter
    return shape


def random_object(rng: np.random.Generator, name: str, bsdf: dict[str, Any],
                  position: Sequence[float], size: float, floor_y: float = 0.0,
                  kinds: Sequence[str] = OBJECT_KINDS) -> dict[str, Shape]:
    """One object of a random kind resting on the floor at ``position`` = (x, z).

    ``size`` is its rough diameter. Returns ``{key: shape}`` (a cylinder comes with its top cap).
    """
    kind = str(rng.choice(list(kinds)))
    x, z = float(position[0]), float(position[1])
    if kind == "sphere":
        r = size / 2
        return {name: sphere((x, floor_y + r, z), r, bsdf)}
    yaw = float(rng.uniform(0.0, 360.0))
    if kind == "cube":
        half = np.array([size / 2, size / 2 * rng.uniform(0.5, 1.6), size / 2 * rng.uniform(0.6, 1.0)])
        m = compose(translate((x, floor_y + half[1], z)), rotate((0, 1, 0), yaw), scale(half))
        return {name: transformed("cube", m, bsdf)}
    if kind == "cylinder":
        r, h = size / 2, size * float(rng.uniform(0.6, 1.8))
        m = compose(translate((x, floor_y, z)), rotate((1, 0, 0), -90.0), scale((r, r, h)))
        cap = compose(translate((x, floor_y + h, z)), rotate((1, 0, 0), -90.0), scale((r, r, 1.0)))
        return {name: transformed("cylinder", m, bsdf),
                f"{name}_cap": transformed("disk", cap, bsdf)}
    raise ValueError(f"unknown object kind {kind!r} (known: {', '.join(OBJECT_KINDS)})")


def scatter_positions(rng: np.random.Generator, count: int, half_x: float, half_z: float,
                      min_gap: float, center: Sequence[float] = (0.0, 0.0),
                      tries: int = 200) -> list[tuple[float, float]]:
    """Up to ``count`` (x, z) positions in the rectangle center ± (half_x, half_z), pairwise at
    least ``min_gap`` apart (fewer if they do not fit in ``tries`` draws; always at least one)."""
    points: list[tuple[float, float]] = []
    for _ in range(tries):
        if len(points) == count:
            break
        p = (float(center[0] + rng.uniform(-half_x, half_x)),
             float(center[1] + rng.uniform(-half_z, half_z)))
        if all((p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2 >= min_gap**2 for q in points):
            points.append(p)
    return points or [(float(center[0]), float(center[1]))]
