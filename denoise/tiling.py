"""Tiled inference that equals untiled inference exactly.

The image is cut into non-overlapping *core* tiles; each is processed with a margin of context
on every side (clamped at the image border) and only its core is kept. A fully convolutional
network with receptive-field radius r (and no normalisation across pixels) gives bit-for-bit the
untiled result in the core whenever ``margin >= r``: every core pixel sees the same input pixels,
and at the image border the same zero padding. So no blending is needed and no seam can show.
A network that works on a grid of ``align``-pixel cells (pooling, pixel-unshuffle) is also
exact when every window starts on that grid: with ``align`` the cores start on multiples of it
and the windows are widened outwards to it (a window that reaches the image's end keeps the
end, so it is padded to the alignment as the whole image is).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from imaging.blocks import parallel_map


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


def _cuts(size: int, core: int, align: int) -> list[int]:
    """Core boundaries along one axis: balanced, on multiples of ``align``, first 0, last ``size``."""
    parts = math.ceil(size / core)
    cuts = sorted({min(size, align * round(i * size / parts / align)) for i in range(parts)} | {size})
    return cuts if cuts[0] == 0 else [0, *cuts]


Core = int | tuple[int, int]  # a square core's side, or (rows, columns)


def plan_tiles(height: int, width: int, core: Core, margin: int, align: int = 1) -> Iterator[Tile]:
    """Cover an image with cores of at most ``core`` px (a side, or (rows, columns); sizes
    balanced), windows + ``margin``; with ``align`` > 1 cores start and windows start/end on
    multiples of it (see module docstring)."""
    core_h, core_w = (core, core) if isinstance(core, int) else core
    if min(core_h, core_w) < 1 or margin < 0 or align < 1:
        raise ValueError(f"tile core and align must be >= 1 and margin >= 0, got {core}, {align}, {margin}")
    ys = _cuts(height, max(align, core_h - core_h % align), align)
    xs = _cuts(width, max(align, core_w - core_w % align), align)
    for y0, y1 in zip(ys[:-1], ys[1:]):
        for x0, x1 in zip(xs[:-1], xs[1:]):
            yield Tile(y0, y1, x0, x1, *window_span(y0, y1, height, margin, align),
                       *window_span(x0, x1, width, margin, align))


def window_span(lo: int, hi: int, size: int, margin: int, align: int) -> tuple[int, int]:
    """Window [start, end) of the core [lo, hi) along an axis of ``size`` pixels: ``margin`` more
    on each side, widened to multiples of ``align`` (the end stays ``size`` where it reaches it)."""
    start = max(0, lo - margin) // align * align
    end = hi + margin
    return start, (size if end >= size else min(size, -(-end // align) * align))


def core_for_budget(bytes_per_pixel: float, max_bytes: float, margin: int, minimum: int = 16) -> int:
    """Largest square core whose window ``(core + 2*margin)^2`` fits ``max_bytes``."""
    side = math.isqrt(max(0, int(max_bytes / max(bytes_per_pixel, 1e-9))))
    return max(minimum, side - 2 * margin)


def _round_up(n: int, multiple: int) -> int:
    """The least multiple of ``multiple`` that is at least ``n``."""
    return -(-n // multiple) * multiple


def _axis_plans(size: int, margin: int, align: int, minimum: int) -> list[tuple[int, int, int]]:
    """Per number of cores along an axis of ``size`` px: (core, largest window, sum of windows)."""
    plans: dict[int, tuple[int, int, int]] = {}
    for parts in range(1, max(1, -(-size // max(minimum, align))) + 1):
        core = max(align, _round_up(_round_up(size, parts) // parts, align))
        if core in plans:
            continue
        cuts = _cuts(size, core, align)
        windows = [b - a for a, b in (window_span(lo, hi, size, margin, align) for lo, hi in zip(cuts[:-1], cuts[1:]))]
        plans[core] = (core, max(windows), sum(windows))
    return sorted(plans.values(), key=lambda p: -p[0])


def cores_for_budget(height: int, width: int, bytes_per_pixel: float, max_bytes: float, margin: int,
                     align: int = 1, minimum: int = 16) -> tuple[int, int]:
    """The (rows, columns) core of :func:`plan_tiles` that processes the fewest window pixels
    in all while every window fits ``max_bytes`` at ``bytes_per_pixel``. With a margin as wide as
    a multi-scale network's (~250 px) the windows' overlap dominates: a full-height strip of a
    1080p image beats square tiles under the same bound. Where no plan fits, the smallest cores
    (``minimum``, aligned)."""
    pixels = max_bytes / max(bytes_per_pixel, 1e-9)
    rows, cols = _axis_plans(height, margin, align, minimum), _axis_plans(width, margin, align, minimum)
    best: tuple[float, int, int] | None = None
    for core_h, window_h, sum_h in rows:
        fitting = [(sum_w, core_w) for core_w, window_w, sum_w in cols if window_h * window_w <= pixels]
        if fitting:
            sum_w, core_w = min(fitting, key=lambda c: (c[0], -c[1]))
            if best is None or sum_h * sum_w < best[0]:
                best = (sum_h * sum_w, core_h, core_w)
    if best is None:
        return rows[-1][0], cols[-1][0]
    return best[1], best[2]


def _band_row_plans(rows: int, height: int, margin: int, align: int, minimum: int) -> list[tuple[int, int, int]]:
    """:func:`_axis_plans` for cores cut across a band of ``rows`` rows that starts on a multiple of
    ``align`` anywhere in an image of ``height`` rows (its windows take their margins from the image):
    per core, its largest window and a bound of the sum of its windows. The band that is the whole
    image: the exact plans."""
    if rows >= height:
        return _axis_plans(height, margin, align, minimum)
    reach = _round_up(margin, align)  # an aligned core's window reaches this far on each side
    plans: dict[int, tuple[int, int, int]] = {}
    for parts in range(1, max(1, -(-rows // max(minimum, align))) + 1):
        core = max(align, _round_up(-(-rows // parts), align))
        if core in plans:
            continue
        window = min(height, core + 2 * reach)
        plans[core] = (core, window, -(-rows // core) * window)
    return sorted(plans.values(), key=lambda p: -p[0])


def band_cores(rows: int, height: int, width: int, bytes_per_pixel: float, max_bytes: float, margin: int,
               align: int = 1, minimum: int = 16) -> tuple[tuple[int, int], int] | None:
    """:func:`cores_for_budget` for a full-width band of ``rows`` rows of an HxW image, starting on a
    multiple of ``align`` (the whole image where ``rows`` >= H): the (rows, columns) core whose
    windows fit ``max_bytes`` with the fewest window pixels, and that bound of its window pixels;
    None where no plan fits."""
    pixels = max_bytes / max(bytes_per_pixel, 1e-9)
    best: tuple[int, int, int] | None = None
    cols = _axis_plans(width, margin, align, minimum)
    for core_h, window_h, sum_h in _band_row_plans(rows, height, margin, align, minimum):
        fitting = [(sum_w, core_w) for core_w, window_w, sum_w in cols if window_h * window_w <= pixels]
        if fitting:
            sum_w, core_w = min(fitting, key=lambda c: (c[0], -c[1]))
            if best is None or sum_h * sum_w < best[0]:
                best = (sum_h * sum_w, core_h, core_w)
    return None if best is None else ((best[1], best[2]), best[0])


def run_tiled(
    fn: Callable[[np.ndarray], np.ndarray], image: np.ndarray, core: Core, margin: int,
    progress: Callable[[int, int], None] | None = None, align: int = 1,
) -> np.ndarray:
    """Apply ``fn`` (HxWxC -> HxWxC', same H, W) tile by tile; returns the stitched HxWxC'."""
    height, width = image.shape[:2]
    return run_windows(lambda t: fn(image[t.wy0:t.wy1, t.wx0:t.wx1]), height, width, core, margin,
                       progress, align)


def region_tiles(height: int, width: int, core: Core, margin: int, align: int = 1,
                 region: tuple[int, int, int, int] | None = None) -> list[Tile]:
    """The tiles of ``region`` (y0, y1, x0, x1; the whole HxW image where None): its cores cut as
    :func:`plan_tiles` cuts them, each window taking its ``margin`` from the whole image."""
    y0, y1, x0, x1 = region if region is not None else (0, height, 0, width)
    return [Tile(t.y0 + y0, t.y1 + y0, t.x0 + x0, t.x1 + x0,
                 *window_span(t.y0 + y0, t.y1 + y0, height, margin, align),
                 *window_span(t.x0 + x0, t.x1 + x0, width, margin, align))
            for t in plan_tiles(y1 - y0, x1 - x0, core, 0, align)]


def run_windows(
    fn: Callable[[Tile], np.ndarray], height: int, width: int, core: Core, margin: int,
    progress: Callable[[int, int], None] | None = None, align: int = 1,
    out: np.ndarray | None = None, region: tuple[int, int, int, int] | None = None, workers: int = 1,
) -> np.ndarray:
    """Call ``fn(tile)`` for each tile of an HxW image (it returns the HxWxC' result over the
    tile's window) and stitch the cores into ``out`` (allocated on the first result if None).
    ``workers`` > 1: that many tiles at a time on threads (:func:`imaging.blocks.parallel_map`;
    worth it for numpy work), stitched in order; at most ``workers`` results are held at once.

    ``region`` (y0, y1, x0, x1): tile only that part of the image (its corners on multiples of
    ``align``, or at the image's end); the windows still take their margins from the whole image,
    and ``out`` outside the region is left as it is.
    """
    tiles = region_tiles(height, width, core, margin, align, region)
    step = max(1, workers)
    for start in range(0, len(tiles), step):
        batch = tiles[start:start + step]
        for n, (t, result) in enumerate(zip(batch, parallel_map(fn, batch, workers)), start):
            if out is None:
                out = np.empty((height, width, result.shape[2]), dtype=result.dtype)
            out[t.y0:t.y1, t.x0:t.x1] = result[t.y0 - t.wy0:t.y1 - t.wy0, t.x0 - t.wx0:t.x1 - t.wx0]
            if progress:
                progress(n + 1, len(tiles))
    assert out is not None
    return out
