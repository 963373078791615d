"""Box-window sums and means of an image plane, exact per tile.

Each sum adds its window's own values in one fixed order (rows, then columns), not a running sum:
a tile computed with ``radius`` pixels of context beside its core equals the whole image's result
there bit for bit, and a dim pixel's sum beside a firefly keeps float32's relative precision.
Used by the noise guard, the ensemble's weights and the energy correction.
"""
from __future__ import annotations

import numpy as np


def box_sum_2d(plane: np.ndarray, radius: int) -> np.ndarray:
    """Sum over the (2r+1)^2 window of an HxW plane, the window cut at the borders; float32."""
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    plane = np.asarray(plane, np.float32)
    return _box_sum_1d(_box_sum_1d(plane, radius, 0), radius, 1)


def box_mean_2d(plane: np.ndarray, radius: int) -> np.ndarray:
    """Mean over a (2r+1)^2 window of an HxW plane, the window cut at the borders; float32."""
    height, width = np.shape(plane)
    out = box_sum_2d(plane, radius)
    out /= _window_counts(height, radius)[:, None]
    out /= _window_counts(width, radius)[None, :]
    return out


def _window_counts(n: int, radius: int) -> np.ndarray:
    """Pixels inside the window ``[i-r, i+r]`` cut to ``[0, n)``, for each i (float32)."""
    idx = np.arange(n)
    return (np.minimum(idx + radius, n - 1) - np.maximum(idx - radius, 0) + 1).astype(np.float32)


def _box_sum_1d(a: np.ndarray, radius: int, axis: int) -> np.ndarray:
    """Sum over ``[i-r, i+r]`` along ``axis`` of a 2-D float32 array (indices outside it contribute
    nothing), added from the window's first index to its last."""
    n = a.shape[axis]
    out = np.zeros(a.shape, np.float32)
    for k in range(-radius, radius + 1):
        lo, hi = max(0, -k), min(n, n - k)  # the i whose neighbour i+k lies inside
        if lo < hi:
            dst = (slice(lo, hi),) if axis == 0 else (slice(None), slice(lo, hi))
            src = (slice(lo + k, hi + k),) if axis == 0 else (slice(None), slice(lo + k, hi + k))
            out[dst] += a[src]
    return out
