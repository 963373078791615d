"""Blend a denoiser's output with the render by how much of its change the render's noise explains.

An RGB-only denoiser cannot tell a converged few-pixel light source from a firefly, nor a
4096-spp image from a 64-spp one, and may "denoise" detail that is not noise. The renderer knows
better: a render made of two halves of independent samples, A (``n_a`` spp) and B (``n_b``), gives
the image ``(n_a*A + n_b*B)/n`` and, per pixel and channel, an unbiased estimate of that mean's
variance, ``(A - B)^2 * n_a*n_b / n^2`` (for equal halves ``(A - B)^2 / 4``). One pixel's estimate
has a single degree of freedom, so it is pooled over a ``(2r+1)^2`` box window.

The guard blends the render and the denoiser's output by how much of the denoiser's change the
render's noise explains. Model the render as truth + noise of variance V and the denoiser's output
as truth + an error of variance T independent of it: the change ``c = denoised - noisy`` then has
mean square ``D = V + T`` and the blend ``noisy + w*c`` with ``w = V / (V + T) = min(1, V/D)`` has
error variance ``V*T/(V+T)``, never above either input's (with V and D exact; their window
estimates scatter, so where the denoiser is good a little noise comes back). V and D are window
means (the same window for both), summed over the channels, so one weight applies to a pixel's
RGB. Where a render is noisy, a good denoiser's change is the noise (``D ~ V``, w = 1: its
output passes unchanged); where a render has converged (V -> 0) whatever the denoiser changed is
its own error and the render is kept. ``strength`` s scales V (``w = min(1, s*V/D)``);
``benchmarks/noise_guard.py`` measures the window and s used by default.

Window sums add each window's own values (not a running sum), so :func:`guard_in_place`, which
computes the weights tile by tile and blends in row blocks within a memory budget, gives the
whole-image result bit for bit.
"""
from __future__ import annotations

import numpy as np

from imaging.blocks import parallel_map, row_blocks
from denoise.box_filter import box_mean_2d
from denoise.tiling import Tile, core_for_budget, run_windows

DEFAULT_RADIUS = 2      # window 5x5 (benchmarks/noise_guard.py)
DEFAULT_STRENGTH = 1.0  # 1: the Wiener weight; larger trusts the denoiser more
DEFAULT_PIVOT_SPP = 256  # below this many spp the strength grows as pivot/spp (benchmarks/noise_guard.py)
# Peak scratch bytes per pixel (numpy allocations, traced) of blend_weight with clean_render's copy
# of its window, and of blend with its copy, both float32 HxWx3 in: a bound with headroom of what
# tests/test_noise_guard.py measures with tracemalloc.
GUARD_BYTES_PER_PIXEL = 48
BLEND_BYTES_PER_PIXEL = 48
# Per-value bounds of the variance and of the squared change before the channel and window sums, so
# that the sums (3 channels x a window's pixels, times the strength, at most DEFAULT_PIVOT_SPP) stay
# far inside float32 (3.4e38) for any window up to ~1e5 pixels; real values are many orders below
# (a variance of 1e30 means nothing is known there, and min(1, V / D) is 1 either way).
VALUE_MAX = 1e30
CHANGE_MAX = 1e15  # |denoised - noisy|, squared: VALUE_MAX


def strength_for(spp: int, pivot_spp: float = DEFAULT_PIVOT_SPP) -> float:
    """Strength for a render of ``spp`` samples: ``max(1, pivot/spp)``.

    At a few samples per pixel the halves' variance misses what no sample found (a dim pixel
    whose samples are all 0 has variance 0, though the denoiser rightly fills it in), so the
    estimate V is trusted less there and the denoiser more; from ``pivot_spp`` on, the plain
    Wiener weight. ``pivot_spp = 0``: strength 1 at every spp.
    """
    return max(1.0, pivot_spp / spp)


def channel_sum(a: np.ndarray) -> np.ndarray:
    """HxW sum of an HxWx3 float32 array's channels, (c0 + c1) + c2 as whole planes: numpy reduces
    a short last axis slowly, and works on a strided channel plane slowly."""
    total = np.add(a[:, :, 0], a[:, :, 1])
    total += a[:, :, 2]
    return total


def blend_weight(noisy: np.ndarray, denoised: np.ndarray, variance: np.ndarray,
                 radius: int = DEFAULT_RADIUS, strength: float = DEFAULT_STRENGTH) -> np.ndarray:
    """HxWx1 weight of the denoiser's output: ``min(1, strength * V / D)`` with V the window mean
    of the render's variance and D that of the squared change ``(denoised - noisy)^2`` (summed
    over channels). Non-finite variance in a window: weight 1 there. Scratch memory: at most
    :data:`GUARD_BYTES_PER_PIXEL` per pixel, with :func:`clean_render`'s copy."""
    if not (strength > 0 and np.isfinite(strength)):
        raise ValueError(f"strength must be positive and finite, got {strength}")
    if not noisy.shape == denoised.shape == variance.shape:
        raise ValueError(f"shapes differ: noisy {noisy.shape}, denoised {denoised.shape}, "
                         f"variance {variance.shape}")
    var = np.asarray(variance, np.float32)
    finite = np.isfinite(var)
    anywhere_unbounded = not finite.all()
    with np.errstate(invalid="ignore", over="ignore"):
        # within [0, VALUE_MAX] so that the window sums stay finite; NaN where unbounded: zeroed below
        positive = np.clip(var, np.float32(0.0), np.float32(VALUE_MAX))
    total = channel_sum(positive)
    change = np.subtract(denoised, noisy, dtype=np.float32)
    np.clip(change, np.float32(-CHANGE_MAX), np.float32(CHANGE_MAX), out=change)
    change *= change
    d_total = channel_sum(change)
    del positive, change
    unbounded = ~finite.all(axis=2) if anywhere_unbounded else None
    del finite
    if unbounded is not None:
        np.putmask(total, unbounded, 0.0)
    v = box_mean_2d(total, radius)
    d = box_mean_2d(d_total, radius)
    del total, d_total
    v *= np.float32(strength)
    # min(1, v/d) in place: d <= v gives v/d >= 1 (also v/0 = inf), and 0/0 = NaN, which fmin drops
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        w = np.fmin(np.divide(v, d, out=v), np.float32(1.0), out=v)
    if unbounded is not None:
        w[box_mean_2d(unbounded.astype(np.float32), radius) > 0] = 1.0
    return w[..., None]


def blend(noisy: np.ndarray, denoised: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``noisy + w * (denoised - noisy)`` for an HxWx1 weight ``w``: float32, >= 0 where both inputs are."""
    noisy, denoised = np.asarray(noisy, np.float32), np.asarray(denoised, np.float32)
    out = np.subtract(denoised, noisy)  # noisy + w * (denoised - noisy), one temporary
    out *= w
    out += noisy
    np.copyto(out, denoised, where=np.broadcast_to(w >= 1, out.shape))  # w = 1: exactly the output
    return out


def guard(noisy: np.ndarray, denoised: np.ndarray, variance: np.ndarray,
          radius: int = DEFAULT_RADIUS, strength: float = DEFAULT_STRENGTH) -> tuple[np.ndarray, float]:
    """:func:`blend` with ``w`` = :func:`blend_weight`. Returns the image and the mean weight (1:
    the denoiser's output unchanged)."""
    w = blend_weight(noisy, denoised, variance, radius, strength)
    return blend(noisy, denoised, w), float(w.mean())


def clean_render(noisy: np.ndarray) -> np.ndarray:
    """The render the guard blends with: float32 HxWx3, NaN and infinities -> 0, negatives -> 0."""
    out = np.array(noisy, dtype=np.float32)
    bad = ~np.isfinite(out)
    np.maximum(out, 0.0, out=out)
    np.putmask(out, bad, 0.0)
    return out


def guard_in_place(noisy: np.ndarray, denoised: np.ndarray, variance: np.ndarray, weights: np.ndarray,
                   max_bytes: float, radius: int = DEFAULT_RADIUS, strength: float = DEFAULT_STRENGTH,
                   workers: int = 1) -> None:
    """:func:`guard` of a whole image within ``max_bytes`` of scratch memory, bit for bit.

    ``noisy``: HxWx3 render (any float dtype; :func:`clean_render` is applied), ``variance`` its
    HxWx3 variance (read as float32); ``denoised``: HxWx3 float32, replaced by the blend; ``weights``: HxWx1
    float32, filled with :func:`blend_weight`. The weights are computed on tiles with ``radius``
    pixels of context (:func:`box_mean_2d` makes them exact), then blended in row blocks: the
    weights need the unblended output around each tile, so it is changed only once they are
    all known. A tile or a block is at least 16 px or one row wide, whatever ``max_bytes`` says.
    ``workers``: tiles and blocks processed at a time on threads (:func:`imaging.blocks.parallel_map`),
    each within ``max_bytes / workers``; there are at least that many of each where the image
    has the rows. The result does not depend on it.
    """
    height, width = denoised.shape[:2]
    if weights.shape != (height, width, 1) or weights.dtype != np.float32:
        raise ValueError(f"weights must be HxWx1 float32 like the image, got {weights.shape} {weights.dtype}")
    workers = max(1, workers)
    budget = max_bytes / workers
    side = core_for_budget(GUARD_BYTES_PER_PIXEL, budget, radius)
    core = (min(side, -(-height // workers)), side)

    def weight(t: Tile) -> np.ndarray:
        window = slice(t.wy0, t.wy1), slice(t.wx0, t.wx1)
        return blend_weight(clean_render(noisy[window]), denoised[window],
                            np.asarray(variance[window], np.float32), radius, strength)

    def blend_rows(rows: slice) -> None:
        denoised[rows] = blend(clean_render(noisy[rows]), denoised[rows], weights[rows])

    run_windows(weight, height, width, core, radius, out=weights, workers=workers)
    parallel_map(blend_rows, row_blocks(height, width, BLEND_BYTES_PER_PIXEL, budget, workers), workers)
