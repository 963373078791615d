"""The sensor's frame, and normals turned into it (``ModelConfig.aux_normals="camera"``).

Mitsuba's ``sh_normal`` AOV holds world-space shading normals. In the sensor's frame (its
``to_world`` transform's axes, Mitsuba's ``look_at`` convention) +X points to the image's left,
+Y up and +Z along the viewing direction: a surface facing the camera has normal (0, 0, -1)
wherever the camera stands. A rotation R (3x3, float64) takes world directions into that frame:
``n_camera = R @ n_world``; it is the transpose of the orthonormal (polar) factor of
``to_world``'s linear part, so a scale in the transform changes nothing.
"""
from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np

from imaging.errors import SceneError


def world_to_camera(to_world: np.ndarray) -> np.ndarray:
    """The rotation (3x3 float64) of a sensor whose ``to_world`` is the 4x4 (or 3x3) matrix given:
    the transpose of the orthonormal factor of its linear part. Raises :class:`SceneError` for a
    singular or non-finite matrix."""
    m = np.asarray(to_world, np.float64).reshape(np.shape(to_world)[0], -1)[:3, :3]
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise SceneError(f"a sensor's to_world must be a finite 4x4 or 3x3 matrix, got {np.shape(to_world)}")
    u, s, vt = np.linalg.svd(m)
    if s[-1] <= 1e-9 * s[0]:
        raise SceneError("the sensor's to_world transform is singular")
    return (u @ vt).T


def sensor_rotation(scene: Any) -> np.ndarray:
    """:func:`world_to_camera` of a loaded ``mi.Scene``'s first sensor."""
    sensors = scene.sensors()
    if not sensors:
        raise SceneError("the scene has no sensor")
    return world_to_camera(np.array(sensors[0].world_transform().matrix).reshape(4, 4))


@functools.lru_cache(maxsize=1024)
def _file_rotation(path: str) -> np.ndarray:
    from rendering.render import load_scene, prepare

    return sensor_rotation(load_scene(prepare(path, (8, 8))))


def scene_file_rotation(path: str | Path) -> np.ndarray:
    """:func:`sensor_rotation` of the scene file ``path`` (loaded with Mitsuba once per file and
    process; a copy each call). Raises :class:`SceneError` if it cannot be loaded."""
    return _file_rotation(str(Path(path).resolve())).copy()


def rotate_normals(normals: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """HxWx3 normals (any float; NaN/Inf -> 0 first) times ``rotation`` (3x3): float32 ``R @ n``
    per pixel. Lengths are kept (averaged normals of a pixel stay shorter than 1)."""
    n = np.nan_to_num(np.asarray(normals, np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    return n @ np.asarray(rotation, np.float32).T
