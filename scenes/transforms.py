"""Affine 4x4 transforms for scene dicts, computed in numpy and handed to Mitsuba as matrices.

Matrices act on column vectors (``p' = M @ p``) in Mitsuba's right-handed, Y-up world; angles are
in degrees. :func:`to_mitsuba` turns the final float64 matrix into a ``drjit.scalar.Matrix4f64``,
the form every ``to_world`` / ``to_uv`` in our scene dicts takes: unlike ``mi.ScalarTransform4f``
it can be deep-copied (``rendering.scene_io`` copies dicts), and Mitsuba inverts it in double
precision exactly as it does an XML ``<matrix>`` (a float32 ``Matrix4f`` is inverted in float32,
which differs in the last bits), so a dict and its XML export render identically.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from rendering.backend import select_variant

Vec3 = Sequence[float]


def translate(v: Vec3) -> np.ndarray:
    """Translation by ``v`` (world units)."""
    m = np.eye(4)
    m[:3, 3] = np.asarray(v, dtype=np.float64)
    return m


def scale(v: Vec3 | float) -> np.ndarray:
    """Axis-aligned scale by ``v`` (a scalar or one factor per axis)."""
    s = np.broadcast_to(np.asarray(v, dtype=np.float64), (3,))
    return np.diag([s[0], s[1], s[2], 1.0])


def rotate(axis: Vec3, angle_deg: float) -> np.ndarray:
    """Right-handed rotation of ``angle_deg`` degrees about ``axis`` (need not be normalised)."""
    a = np.asarray(axis, dtype=np.float64)
    norm = np.linalg.norm(a)
    if norm == 0.0:
        raise ValueError("rotation axis must be non-zero")
    x, y, z = a / norm
    t = np.radians(angle_deg)
    c, s = np.cos(t), np.sin(t)
    m = np.eye(4)
    m[:3, :3] = [
        [c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
        [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
        [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)],
    ]
    return m


def look_at(origin: Vec3, target: Vec3, up: Vec3) -> np.ndarray:
    """Camera-to-world matrix like Mitsuba's ``look_at``: local +Z looks from origin to target."""
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(target, dtype=np.float64) - o
    if np.linalg.norm(d) == 0.0:
        raise ValueError("look_at: origin and target coincide")
    d /= np.linalg.norm(d)
    left = np.cross(np.asarray(up, dtype=np.float64), d)
    if np.linalg.norm(left) < 1e-9:
        raise ValueError("look_at: up vector is parallel to the viewing direction")
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return m


def compose(*matrices: np.ndarray) -> np.ndarray:
    """Product ``matrices[0] @ matrices[1] @ ...``: the last one applies first."""
    out = np.eye(4)
    for m in matrices:
        out = out @ m
    return out


def to_mitsuba(m: np.ndarray) -> Any:
    """A 4x4 matrix as the float64 ``drjit.scalar.Matrix4f64`` Mitsuba dicts accept.

    Dr.Jit loads libLLVM on import, so it is imported only after the variant is selected.
    """
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise ValueError(f"expected a finite 4x4 matrix, got shape {m.shape}")
    select_variant()
    import drjit as dr

    return dr.scalar.Matrix4f64(m)
