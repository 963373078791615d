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


def smape(x: np.ndarray, ref: np.ndarray, eps: float = RELMSE_EPS) -> float:
    """Symmetric mean absolute percentage error: mean(|x-r| / (|x| + |r| + eps))."""
    _check(x, ref)
    x = np.asarray(x, dtype=np.float64)
    r = np.asarray(ref, dtype=np.float64)
    return float(np.mean(np.abs(x - r) / (np.abs(x) + np.abs(r) + eps)))


def _gaussian_blur(img: np.ndarray, sigma: float = 1.5, radius: int = 5) -> np.ndarray:
    """Separable gaussian blur of an HxWxC array, reflect-padded so any size works."""
    t = np.arange(-radius, radius + 1)
    k = np.exp(-0.5 * (t / sigma) ** 2)
    k /= k.sum()
    out = img
    for axis in (0, 1):
        pad = [(0, 0)] * img.ndim
        pad[axis] = (radius, radius)
        padded = np.pad(out, pad, mode="symmetric")
        out = sum(k[i] * np.take(padded, range(i, i + img.shape[axis]), axis=axis)
                  for i in range(len(k)))
    return out


def ssim(x: np.ndarray, ref: np.ndarray) -> float:
    """SSIM (Wang et al. 2004: 11x11 gaussian window, sigma 1.5, K1 0.01, K2 0.03) of the
    tonemapped images with peak 1, averaged over pixels and channels; 1.0 for identical images."""
    _check(x, ref)
    a, b = tonemap(x), tonemap(ref)
    c1, c2 = 0.01**2, 0.03**2
    mu_a, mu_b = _gaussian_blur(a), _gaussian_blur(b)
    var_a = _gaussian_blur(a * a) - mu_a**2
    var_b = _gaussian_blur(b * b) - mu_b**2
    cov = _gaussian_blur(a * b) - mu_a * mu_b
    num = (2 * mu_a * mu_b + c1) * (2 * cov + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)
    return float(np.mean(num / den))


def flip(x: np.ndarray, ref: np.ndarray, hdr: bool = False) -> float:
    """Mean NVIDIA FLIP error (0 = identical). LDR: on the tonemapped images (display values);
    HDR: HDR-FLIP on the linear radiance (negatives clamped to 0)."""
    _check(x, ref)
    import flip_evaluator

    if hdr:
        a = np.clip(np.asarray(x, np.float32), 0, None)
        b = np.clip(np.asarray(ref, np.float32), 0, None)
    else:
        a, b = tonemap(x).astype(np.float32), tonemap(ref).astype(np.float32)
    _, mean_error, _ = flip_evaluator.evaluate(np.ascontiguousarray(b), np.ascontiguousarray(a),
                                               "HDR" if hdr else "LDR", applyMagma=False)
    return float(mean_error)


def all_metrics(x: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """Every metric of ``x`` against ``ref`` (both HxWx3 linear radiance)."""
    return {"psnr": psnr(x, ref), "ssim": ssim(x, ref), "relmse": relmse(x, ref),
            "smape": smape(x, ref), "flip": flip(x, ref), "hdr_flip": flip(x, ref, hdr=True)}
