"""Film crops that keep a render within a memory budget: layout, seeds, Mitsuba's crop window.

The budget is OIDN's ``maxMemoryMB`` applied to the render: scratch memory beyond the output
images (RenderResult's rgb, AOVs and variance). Mitsuba 3.9.1's llvm variant traces the whole path
tracer into one kernel and keeps no per-sample state: a 512x512 film peaks at the same resident
memory at 1 and at 256 spp in one pass (67M samples in flight; benchmarks/render_memory.py
measures it). A render's scratch is therefore per *pixel* of the film being rendered: Mitsuba's
film storage and developed image, and our float64 accumulators. So the budget bounds the pixels
rendered at once, not the samples per pass: a film whose pixels do not fit is rendered as crops
(Mitsuba's film crop window), one after the other, each written into the output images.

With the box filter every render uses (:mod:`rendering.scene_io`), a sample only ever lands in
the pixel it was drawn in, so crops stitch exactly: a pixel's estimate has the same distribution
whichever crop rendered it (no seams). Each crop has its own seed (:func:`crop_seed`; crop 0 keeps
the render's seed, so a render that fits in one crop is the render made without crops): Mitsuba's
independent sampler derives a sample's random numbers from (seed, index of the sample within the
rendered window), so two crops with one seed would repeat each other's noise.

Each crop's window is compiled into its own kernel by Dr.Jit (offset and size are constants of
the kernel): the first render of a layout compiles one kernel per crop, about 1 s each on a 2-core
machine, cached on disk (~/.drjit) for later runs. Bands the width of the film keep the count low.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from imaging.errors import RenderError

Crop = tuple[int, int, int, int]  # x, y, width, height in pixels of the film's own crop window

MB = 2**20
MIN_CROP_PIXELS = 4096
# Measured with benchmarks/render_memory.py --parts calibrate (mitsuba 3.9.1 llvm_ad_rgb, demo
# scene, 2-core x86; results/render_memory.json): scratch of a render of P pixels and C channels is
# FIXED + P * bytes_per_pixel(C, halves). Measured 52, 106, 191 and 275 bytes per pixel for 3, 3 +
# halves, 9 and 9 + halves channels, 15-20 MB fixed (kernel compilation: more for scenes whose
# kernel is larger), 0.03 bytes per sample in flight (noise). The constants bound these by 5-35%.
FIXED_BYTES = 32 * MB
BYTES_PER_CHANNEL = 24.0  # film storage, developed image, float64 accumulator, float64 pass image
HALVES_BYTES_PER_CHANNEL = 8.0  # the second half's float64 accumulator
HALVES_BYTES_PER_PIXEL = 32.0  # the variance's float64 temporaries (3 channels)


def bytes_per_pixel(channels: int, halves: bool) -> float:
    """Peak scratch bytes per rendered pixel for ``channels`` output channels (3 + 3 per AOV)."""
    if halves:
        return channels * (BYTES_PER_CHANNEL + HALVES_BYTES_PER_CHANNEL) + HALVES_BYTES_PER_PIXEL
    return channels * BYTES_PER_CHANNEL


def max_crop_pixels(channels: int, halves: bool, max_memory_mb: float | None) -> int | None:
    """Most pixels one crop may have under ``max_memory_mb`` (None: no budget, no limit)."""
    if max_memory_mb is None:
        return None
    if not 0 < max_memory_mb < math.inf:  # also refuses NaN
        raise RenderError(f"memory budget must be positive and finite, got {max_memory_mb!r} MB")
    usable = max_memory_mb * MB - FIXED_BYTES
    return max(MIN_CROP_PIXELS, int(usable // bytes_per_pixel(channels, halves)))


IMAGE_BYTES_PER_PIXEL = 12  # one HxWx3 float32 output image (rgb, an AOV, the variance)


def render_bytes(width: int, height: int, channels: int, halves: bool, max_memory_mb: float | None) -> int:
    """Peak memory of a ``width`` x ``height`` render of ``channels`` output channels (3 + 3 per
    AOV): its float32 output images (and the variance's with ``halves``), which are whole-film
    whatever the budget, and the scratch of its largest crop under ``max_memory_mb``."""
    pixels = width * height
    crop = pixels if max_memory_mb is None else min(pixels, max_crop_pixels(channels, halves, max_memory_mb))
    images = channels // 3 + int(halves)
    return images * pixels * IMAGE_BYTES_PER_PIXEL + FIXED_BYTES + math.ceil(crop * bytes_per_pixel(channels, halves))


def _split(total: int, parts: int) -> list[tuple[int, int]]:
    """``total`` cut into ``parts`` (start, length) runs whose lengths differ by at most one."""
    bounds = [total * i // parts for i in range(parts + 1)]
    return [(a, b - a) for a, b in zip(bounds, bounds[1:])]


def crop_layout(width: int, height: int, max_pixels: int | None) -> list[Crop]:
    """Crops covering a ``width`` x ``height`` film, row-major, each at most ``max_pixels``.

    One crop when the film fits; else bands the width of the film (fewest crops), or, when one
    row does not fit, a grid. Crop sizes differ by at most one pixel per axis.
    """
    if max_pixels is None or width * height <= max_pixels:
        return [(0, 0, width, height)]
    columns = math.ceil(width / max_pixels)
    widest = math.ceil(width / columns)
    rows = math.ceil(height / max(1, max_pixels // widest))
    return [(x, y, w, h) for y, h in _split(height, rows) for x, w in _split(width, columns)]


def crop_seed(seed: int, index: int) -> int:
    """Seed of crop ``index`` of a render with ``seed``: crop 0 keeps it, the others a 32-bit mix."""
    if index == 0:
        return seed
    x = (seed ^ (index * 0x9E3779B9)) & 0xFFFFFFFF
    x = (x + 0x632BE5AB * index) & 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x85EBCA6B) & 0xFFFFFFFF
    x ^= x >> 13
    x = (x * 0xC2B2AE35) & 0xFFFFFFFF
    x ^= x >> 16
    return x


def film_window(scene: Any) -> Crop:
    """(x, y, width, height) of the first sensor's film crop window (the whole film unless the
    scene set one)."""
    film = scene.sensors()[0].film()
    (x, y), (w, h) = (int(v) for v in film.crop_offset()), (int(v) for v in film.crop_size())
    return x, y, w, h


@contextmanager
def cropped(scene: Any) -> Iterator[Any]:
    """``with cropped(scene) as set_crop: set_crop((x, y, w, h))`` renders that part of the
    film's window; the film's own window is restored on exit."""
    import mitsuba as mi

    sensor = scene.sensors()[0]
    params = mi.traverse(sensor)
    if "film.crop_offset" not in params or "film.crop_size" not in params:
        raise RenderError(f"cannot crop the film of a {type(sensor).__name__} sensor "
                          "(render at a lower resolution or raise the memory budget)")
    x0, y0, w0, h0 = film_window(scene)

    def set_crop(crop: Crop) -> None:
        x, y, w, h = crop
        params["film.crop_offset"] = mi.ScalarPoint2u(x0 + x, y0 + y)
        params["film.crop_size"] = mi.ScalarVector2u(w, h)
        params.update()

    try:
        yield set_crop
    finally:
        set_crop((0, 0, w0, h0))
