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
"""
from __future__ import annotations

import numpy as np

DEFAULT_RADIUS = 2      # window 5x5 (benchmarks/noise_guard.py)
DEFAULT_STRENGTH = 1.0  # 1: the Wiener weight; larger trusts the denoiser more
DEFAULT_PIVOT_SPP = 256  # below this many spp the strength grows as pivot/spp (benchmarks/noise_guard.py)


def strength_for(spp: int, pivot_spp: float = DEFAULT_PIVOT_SPP) -> float:
    """Strength for a render of ``spp`` samples: ``max(1, pivot/spp)``.

    At a few samples per pixel the halves' variance misses what no sample found (a dim pixel
    whose samples are all 0 has variance 0, though the denoiser rightly fills it in), so the
    estimate V is trusted less there and the denoiser more; from ``pivot_spp`` on, the plain
    Wiener weight. ``pivot_spp = 0``: strength 1 at every spp.
    """
    return max(1.0, pivot_spp / spp)


def box_mean(img: np.ndarray, radius: int) -> np.ndarray:
    """Mean over a (2r+1)^2 window per channel of an HxWxC image, the window cut at the borders."""
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    count = np.ones(img.shape[:2])
    for axis in (0, 1):
        count = _box_sum_1d(count, radius, axis)
    out = np.empty(img.shape, np.float32)
    for c in range(img.shape[2]):
        plane = np.asarray(img[:, :, c], np.float64)
        for axis in (0, 1):
            plane = _box_sum_1d(plane, radius, axis)
        out[:, :, c] = plane / count
    return out


def _box_sum_1d(a: np.ndarray, radius: int, axis: int) -> np.ndarray:
    """Sum over ``[i-r, i+r]`` along ``axis`` (indices outside the array contribute nothing)."""
    n = a.shape[axis]
    c = np.cumsum(a, axis=axis)
    c = np.concatenate([np.zeros_like(np.take(c, [0], axis=axis)), c], axis=axis)
    idx = np.arange(n)
    hi = np.minimum(idx + radius + 1, n)
    lo = np.maximum(idx - radius, 0)
    return np.take(c, hi, axis=axis) - np.take(c, lo, axis=axis)


def blend_weight(noisy: np.ndarray, denoised: np.ndarray, variance: np.ndarray,
                 radius: int = DEFAULT_RADIUS, strength: float = DEFAULT_STRENGTH) -> np.ndarray:
    """HxWx1 weight of the denoiser's output: ``min(1, strength * V / D)`` with V the window mean
    of the render's variance and D that of the squared change ``(denoised - noisy)^2`` (summed
    over channels). Non-finite variance in a window: weight 1 there."""
    if not (strength > 0 and np.isfinite(strength)):
        raise ValueError(f"strength must be positive and finite, got {strength}")
    if not noisy.shape == denoised.shape == variance.shape:
        raise ValueError(f"shapes differ: noisy {noisy.shape}, denoised {denoised.shape}, "
                         f"variance {variance.shape}")
    var = np.asarray(variance, np.float64)
    unbounded = ~np.isfinite(var).all(axis=2, keepdims=True)
    v = box_mean(np.where(unbounded, 0.0, np.maximum(var, 0)).sum(axis=2, keepdims=True), radius)
    change = np.asarray(denoised, np.float64) - np.asarray(noisy, np.float64)
    d = box_mean((change * change).sum(axis=2, keepdims=True), radius)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(d > strength * v, strength * v / d, 1.0)
    w[box_mean(unbounded.astype(np.float32), radius) > 0] = 1.0
    return w.astype(np.float32)


def blend(noisy: np.ndarray, denoised: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``noisy + w * (denoised - noisy)`` for an HxWx1 weight ``w``: float32, >= 0 where both inputs are."""
    noisy, denoised = np.asarray(noisy, np.float32), np.asarray(denoised, np.float32)
    out = np.where(w >= 1, denoised, noisy + w * (denoised - noisy))  # w = 1: exactly the output
    return out.astype(np.float32)


def guard(noisy: np.ndarray, denoised: np.ndarray, variance: np.ndarray,
          radius: int = DEFAULT_RADIUS, strength: float = DEFAULT_STRENGTH) -> tuple[np.ndarray, float]:
    """:func:`blend` with ``w`` = :func:`blend_weight`. Returns the image and the mean weight (1:
    the denoiser's output unchanged)."""
    w = blend_weight(noisy, denoised, variance, radius, strength)
    return blend(noisy, denoised, w), float(w.mean())
