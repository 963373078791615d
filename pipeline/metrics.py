"""Image-quality metrics against a reference, on HxWx3 float32 linear radiance.

PSNR follows ../shared/eval-scenes/README.md: tonemap x/(1+x) per channel (negatives clamped to
0), gamma 1/2.2, peak 1. relMSE is mean((x-r)^2 / (r^2 + eps)), eps = 0.01. Identical images give
PSNR = +inf (kept as inf in Python, written as null in JSON by the callers).
"""
from __future__ import annotations

import numpy as np

RELMSE_EPS = 0.01


def tonemap(x: np.ndarray) -> np.ndarray:
    """Linear radiance (>=0) -> display values in [0, 1): x/(1+x), then gamma 1/2.2."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, None)
    return (x / (1.0 + x)) ** (1.0 / 2.2)


def _check(x: np.ndarray, ref: np.ndarray) -> None:
    if np.shape(x) != np.shape(ref):
        raise ValueError(f"image shape {np.shape(x)} differs from reference shape {np.shape(ref)}")


def psnr(x: np.ndarray, ref: np.ndarray) -> float:
    """Tonemapped PSNR in dB (peak 1); +inf for identical images."""
    _check(x, ref)
    mse = float(np.mean((tonemap(x) - tonemap(ref)) ** 2))
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(1.0 / mse))


def relmse(x: np.ndarray, ref: np.ndarray, eps: float = RELMSE_EPS) -> float:
    """Relative MSE on linear radiance: mean((x-r)^2 / (r^2 + eps))."""
    _check(x, ref)
    x = np.asarray(x, dtype=np.float64)
    r = np.asarray(ref, dtype=np.float64)
    return float(np.mean((x - r) ** 2 / (r * r + eps)))
