"""Axis-aligned rooms of inward-facing rectangles, optionally with an opening in one wall.

The room spans x in [-w/2, w/2], y in [0, h], z in [-d/2, d/2] (world units, Y up). Walls are
named ``floor``, ``ceiling``, ``back`` (z = -d/2), ``front`` (z = +d/2), ``left`` (x = -w/2) and
``right`` (x = +w/2); each faces the room's inside.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from scenes.shapes import Shape, transformed
from scenes.transforms import compose, scale, translate

WALLS = ("floor", "ceiling", "back", "front", "left", "right")


@dataclass(frozen=True)
class Wall:
    """A wall's centre, inward normal ``n``, in-plane axes ``u``, ``v`` and half extents."""

    center: np.ndarray
    n: np.ndarray
    u: np.ndarray
    v: np.ndarray
    half_u: float
    half_v: float

    def panel(self, u0: float, u1: float, v0: float, v1: float, offset: float = 0.0) -> np.ndarray:
        """to_world of the rectangle [u0, u1] x [v0, v1] (wall coordinates), moved ``offset``
        along the normal."""
        c = self.center + 0.5 * (u0 + u1) * self.u + 0.5 * (v0 + v1) * self.v + offset * self.n
        basis = np.eye(4)
        basis[:3, 0], basis[:3, 1], basis[:3, 2] = self.u, self.v, self.n
        return compose(translate(c), basis, scale((0.5 * (u1 - u0), 0.5 * (v1 - v0), 1.0)))


def wall(name: str, w: float, h: float, d: float) -> Wall:
    """Geometry of one wall of a w x h x d room."""
    e = np.eye(3)
    table = {
        "floor": ((0, 0, 0), e[1], e[0], w, d),
        "ceiling": ((0, h, 0), -e[1], e[0], w, d),
        "back": ((0, h / 2, -d / 2), e[2], e[0], w, h),
        "front": ((0, h / 2, d / 2), -e[2], -e[0], w, h),
        "left": ((-w / 2, h / 2, 0), e[0], -e[2], d, h),
        "right": ((w / 2, h / 2, 0), -e[0], e[2], d, h),
    }
    if name not in table:
        raise ValueError(f"unknown wall {name!r} (known: {', '.join(WALLS)})")
    center, n, u, size_u, size_v = table[name]
    return Wall(np.asarray(center, dtype=np.float64), n, u, np.cross(n, u), size_u / 2, size_v / 2)


def room(w: float, h: float, d: float, bsdfs: Mapping[str, dict[str, Any]],
         opening: tuple[str, Sequence[float]] | None = None, prefix: str = "") -> dict[str, Shape]:
    """Shapes of the walls named in ``bsdfs`` (wall -> BSDF); walls not named are left open.

    ``opening = (wall, (u0, u1, v0, v1))`` cuts a rectangular hole (wall coordinates, centred on
    the wall) into that wall, which is then made of up to four panels around it.
    """
    shapes: dict[str, Shape] = {}
    for name, bsdf in bsdfs.items():
        g = wall(name, w, h, d)
        if opening is not None and opening[0] == name:
            u0, u1, v0, v1 = opening[1]
            pieces = [(-g.half_u, g.half_u, -g.half_v, v0), (-g.half_u, g.half_u, v1, g.half_v),
                      (-g.half_u, u0, v0, v1), (u1, g.half_u, v0, v1)]
            for i, (a, b, c, e) in enumerate(pieces):
                if b - a > 1e-6 and e - c > 1e-6:
                    shapes[f"{prefix}{name}_{i}"] = transformed("rectangle", g.panel(a, b, c, e), bsdf)
        else:
            shapes[f"{prefix}{name}"] = transformed(
                "rectangle", g.panel(-g.half_u, g.half_u, -g.half_v, g.half_v), bsdf)
    return shapes
