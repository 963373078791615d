"""Tiled inference that equals untiled inference exactly.

The image is cut into non-overlapping *core* tiles; each is processed with a margin of context
on every side (clamped at the image border) and only its core is kept. A fully convolutional
network with receptive-field radius r (and no normalisation across pixels) gives bit-for-bit the
untiled result in the core whenever ``margin >= r``: every core pixel sees the same input pixels,
and at the image border the same zero padding. So no blending is needed and no seam can show.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Tile:
    """A core region [y0:y1, x0:x1] and its input window [wy0:wy1, wx0:wx1] (with margin)."""

    y0: int
    y1: int
    x0: int
    x1: int
    wy0: int
    wy1: int
    wx0: int
    wx1: int


def plan_tiles(height: int, width: int, core: int, margin: int) -> Iterator[Tile]:
    """Cover an image with cores of at most ``core`` px (sizes balanced), windows + ``margin``."""
    if core < 1 or margin < 0:
        raise ValueError(f"tile core must be >= 1 and margin >= 0, got {core}, {margin}")
    ny, nx = math.ceil(height / core), math.ceil(width / core)
    ys = [round(i * height / ny) for i in range(ny + 1)]
    xs = [round(i * width / nx) for i in range(nx + 1)]
    for y0, y1 in zip(ys[:-1], ys[1:]):
        for x0, x1 in zip(xs[:-1], xs[1:]):
            yield Tile(y0, y1, x0, x1, max(0, y0 - margin), min(height, y1 + margin),
                       max(0, x0 - margin), min(width, x1 + margin))


def core_for_budget(bytes_per_pixel: float, max_bytes: float, margin: int, minimum: int = 16) -> int:
    """Largest square core whose window ``(core + 2*margin)^2`` fits ``max_bytes``."""
    side = math.isqrt(max(0, int(max_bytes / max(bytes_per_pixel, 1e-9))))
    return max(minimum, side - 2 * margin)


def run_tiled(
    fn: Callable[[np.ndarray], np.ndarray], image: np.ndarray, core: int, margin: int,
    progress: Callable[[int, int], None] | None = None,
) -> np.ndarray:
    """Apply ``fn`` (HxWxC -> HxWxC', same H, W) tile by tile; returns the stitched HxWxC'."""
    height, width = image.shape[:2]
    tiles = list(plan_tiles(height, width, core, margin))
    out: np.ndarray | None = None
    for n, t in enumerate(tiles):
        result = fn(image[t.wy0:t.wy1, t.wx0:t.wx1])
        if out is None:
            out = np.empty((height, width, result.shape[2]), dtype=result.dtype)
        out[t.y0:t.y1, t.x0:t.x1] = result[t.y0 - t.wy0:t.y1 - t.wy0, t.x0 - t.wx0:t.x1 - t.wx0]
        if progress:
            progress(n + 1, len(tiles))
    assert out is not None
    return out
