"""Image-quality metrics against a reference, on HxWx3 float32 linear radiance.

PSNR follows ../shared/eval-scenes/README.md: tonemap x/(1+x) per channel (negatives clamped to
0), gamma 1/2.2, peak 1. relMSE is mean((x-r)^2 / (r^2 + eps)), eps = 0.01. Identical images give
PSNR = +inf (kept as inf in Python, written as null in JSON by the callers).

PSNR, SSIM, relMSE and SMAPE are computed a block of rows at a time (their float64 temporaries
within ``max_bytes``), each pixel's value as over the whole image, the means summed in float64
block by block: they agree with a whole-image computation to rounding (~1e-15 relative). FLIP
runs on whole images (NVIDIA's evaluator takes nothing smaller). :func:`percentile` of one image
is exact and blocked too.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from imaging.blocks import DEFAULT_BLOCK_BYTES, block_rows, row_blocks

RELMSE_EPS = 0.01
PIXEL_BYTES_PER_VALUE = 48  # psnr, relmse, smape: float64 temporaries per value (32 measured)
SSIM_BYTES_PER_VALUE = 128  # ssim: five blurred maps and their temporaries per value (~100 measured)
SSIM_RADIUS = 5
KEY_DIGIT = 11  # percentile: bits of the sort key counted per pass (2**11 counters)


def tonemap(x: np.ndarray) -> np.ndarray:
    """Linear radiance (>=0) -> display values in [0, 1): x/(1+x), then gamma 1/2.2."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, None)
    return (x / (1.0 + x)) ** (1.0 / 2.2)


def _check(x: np.ndarray, ref: np.ndarray) -> None:
    if np.shape(x) != np.shape(ref):
        raise ValueError(f"image shape {np.shape(x)} differs from reference shape {np.shape(ref)}")


def _blocked_mean(per_value: Callable[[np.ndarray, np.ndarray], np.ndarray], x: np.ndarray,
                  ref: np.ndarray, bytes_per_value: float, max_bytes: float) -> float:
    """The mean of ``per_value(x_rows, ref_rows)`` over the whole image, a block of rows at a time
    (block sums added in float64); NaN for an empty image."""
    x, ref = np.asarray(x), np.asarray(ref)
    if x.ndim == 0:
        return float(np.mean(per_value(x, ref)))
    total, count = 0.0, 0
    for rows in row_blocks(len(x), int(np.prod(x.shape[1:], dtype=np.int64)), bytes_per_value, max_bytes):
        values = per_value(x[rows], ref[rows])
        total += float(values.sum(dtype=np.float64))
        count += values.size
    return total / count if count else float("nan")


def _tonemapped_se(x: np.ndarray, r: np.ndarray) -> np.ndarray:
    return (tonemap(x) - tonemap(r)) ** 2


def _relative_se(x: np.ndarray, r: np.ndarray, eps: float = RELMSE_EPS) -> np.ndarray:
    x, r = np.asarray(x, dtype=np.float64), np.asarray(r, dtype=np.float64)
    return (x - r) ** 2 / (r * r + eps)


def _symmetric_ape(x: np.ndarray, r: np.ndarray, eps: float = RELMSE_EPS) -> np.ndarray:
    x, r = np.asarray(x, dtype=np.float64), np.asarray(r, dtype=np.float64)
    return np.abs(x - r) / (np.abs(x) + np.abs(r) + eps)


def psnr(x: np.ndarray, ref: np.ndarray, max_bytes: float = DEFAULT_BLOCK_BYTES) -> float:
    """Tonemapped PSNR in dB (peak 1); +inf for identical images."""
    _check(x, ref)
    mse = _blocked_mean(_tonemapped_se, x, ref, PIXEL_BYTES_PER_VALUE, max_bytes)
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(1.0 / mse))


def relmse(x: np.ndarray, ref: np.ndarray, eps: float = RELMSE_EPS,
           max_bytes: float = DEFAULT_BLOCK_BYTES) -> float:
    """Relative MSE on linear radiance: mean((x-r)^2 / (r^2 + eps))."""
    _check(x, ref)
    return _blocked_mean(lambda a, b: _relative_se(a, b, eps), x, ref, PIXEL_BYTES_PER_VALUE, max_bytes)


def smape(x: np.ndarray, ref: np.ndarray, eps: float = RELMSE_EPS,
          max_bytes: float = DEFAULT_BLOCK_BYTES) -> float:
    """Symmetric mean absolute percentage error: mean(|x-r| / (|x| + |r| + eps))."""
    _check(x, ref)
    return _blocked_mean(lambda a, b: _symmetric_ape(a, b, eps), x, ref, PIXEL_BYTES_PER_VALUE, max_bytes)


def _kernel(sigma: float, radius: int) -> np.ndarray:
    t = np.arange(-radius, radius + 1)
    k = np.exp(-0.5 * (t / sigma) ** 2)
    return k / k.sum()


def _blur_axis(padded: np.ndarray, k: np.ndarray, axis: int, size: int) -> np.ndarray:
    """Weighted sum of ``len(k)`` shifted windows of ``size`` along ``axis`` of an array padded
    by the radius on both sides of that axis."""
    return sum(k[i] * np.take(padded, range(i, i + size), axis=axis) for i in range(len(k)))


def _gaussian_blur(img: np.ndarray, sigma: float = 1.5, radius: int = SSIM_RADIUS) -> np.ndarray:
    """Separable gaussian blur of an HxWxC array, reflect-padded so any size works."""
    k = _kernel(sigma, radius)
    out = img
    for axis in (0, 1):
        pad = [(0, 0)] * img.ndim
        pad[axis] = (radius, radius)
        out = _blur_axis(np.pad(out, pad, mode="symmetric"), k, axis, img.shape[axis])
    return out


def _blur_rows(extended: np.ndarray, size: int, sigma: float = 1.5, radius: int = SSIM_RADIUS) -> np.ndarray:
    """:func:`_gaussian_blur`'s ``size`` rows from the rows around them (``extended``: ``size`` +
    2 ``radius`` rows, padded as the whole image is padded): each value as in the whole blur."""
    k = _kernel(sigma, radius)
    out = _blur_axis(extended, k, 0, size)
    pad = [(0, 0)] * out.ndim
    pad[1] = (radius, radius)
    return _blur_axis(np.pad(out, pad, mode="symmetric"), k, 1, out.shape[1])


def _ssim_rows(x: np.ndarray, ref: np.ndarray, rows: slice) -> np.ndarray:
    """The SSIM map's ``rows`` (each value as over the whole image): the blur's rows around them
    gathered with the whole image's symmetric padding."""
    around = np.pad(np.arange(len(x)), SSIM_RADIUS, mode="symmetric")[rows.start:rows.stop + 2 * SSIM_RADIUS]
    a, b = tonemap(x[around]), tonemap(ref[around])
    size = rows.stop - rows.start
    c1, c2 = 0.01**2, 0.03**2
    mu_a, mu_b = _blur_rows(a, size), _blur_rows(b, size)
    var_a = _blur_rows(a * a, size) - mu_a**2
    var_b = _blur_rows(b * b, size) - mu_b**2
    cov = _blur_rows(a * b, size) - mu_a * mu_b
    num = (2 * mu_a * mu_b + c1) * (2 * cov + c2)
    den = (mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2)
    return num / den


def ssim(x: np.ndarray, ref: np.ndarray, max_bytes: float = DEFAULT_BLOCK_BYTES) -> float:
    """SSIM (Wang et al. 2004: 11x11 gaussian window, sigma 1.5, K1 0.01, K2 0.03) of the
    tonemapped images with peak 1, averaged over pixels and channels; 1.0 for identical images.
    Blocks of rows, each with the ``SSIM_RADIUS`` rows above and below it that its blur needs."""
    _check(x, ref)
    x, ref = np.asarray(x), np.asarray(ref)
    height, halo = len(x), 2 * SSIM_RADIUS
    width = int(np.prod(x.shape[1:], dtype=np.int64))
    rows = max(1, block_rows(width, SSIM_BYTES_PER_VALUE, max_bytes, height + halo) - halo)
    total, count = 0.0, 0
    for y in range(0, height, rows):
        values = _ssim_rows(x, ref, slice(y, min(height, y + rows)))
        total += float(values.sum(dtype=np.float64))
        count += values.size
    return total / count


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


def all_metrics(x: np.ndarray, ref: np.ndarray, max_bytes: float = DEFAULT_BLOCK_BYTES) -> dict[str, float]:
    """Every metric of ``x`` against ``ref`` (both HxWx3 linear radiance); the blocked ones
    within ``max_bytes`` of temporaries."""
    return {"psnr": psnr(x, ref, max_bytes), "ssim": ssim(x, ref, max_bytes),
            "relmse": relmse(x, ref, max_bytes=max_bytes), "smape": smape(x, ref, max_bytes=max_bytes),
            "flip": flip(x, ref), "hdr_flip": flip(x, ref, hdr=True)}


# ----------------------------------------------------------------- statistics of one image
def _sort_keys(values: np.ndarray) -> np.ndarray:
    """Unsigned integers in the order of the floating-point ``values`` (NaN aside)."""
    bits = values.dtype.itemsize * 8
    raw = values.view(np.dtype(f"u{values.dtype.itemsize}"))
    sign = raw >> np.array(bits - 1, raw.dtype)
    return raw ^ (sign * np.array(2**bits - 1, raw.dtype) | np.array(1 << (bits - 1), raw.dtype))


def _kth_smallest(values: np.ndarray, k: int, max_bytes: float) -> np.ndarray:
    """The ``k``-th smallest (0-based) of the float ``values`` (no NaN), found ``KEY_DIGIT`` bits
    of its sort key at a time by counting over blocks of rows."""
    flat_width = int(np.prod(values.shape[1:], dtype=np.int64)) if values.ndim > 1 else 1
    bits = values.dtype.itemsize * 8
    prefix, rank = 0, k
    for high in range(bits, 0, -KEY_DIGIT):
        low = max(0, high - KEY_DIGIT)
        counts = np.zeros(2 ** (high - low), np.int64)
        for rows in row_blocks(len(values), flat_width, 6 * values.dtype.itemsize, max_bytes):
            keys = _sort_keys(np.ascontiguousarray(values[rows]).reshape(-1))
            if high < bits:
                keys = keys[(keys >> np.array(high, keys.dtype)) == prefix]
            digits = (keys >> np.array(low, keys.dtype)) & np.array(2 ** (high - low) - 1, keys.dtype)
            counts += np.bincount(digits.astype(np.int64), minlength=len(counts))
        digit = int(np.searchsorted(np.cumsum(counts), rank, side="right"))
        rank -= int(counts[:digit].sum())
        prefix = (prefix << (high - low)) | digit
    key = np.array([prefix], np.dtype(f"u{values.dtype.itemsize}"))
    top = np.array(1 << (bits - 1), key.dtype)
    raw = np.where(key & top, key ^ top, ~key)  # _sort_keys undone
    return raw.view(values.dtype)[0]


def percentile(img: np.ndarray, q: float, max_bytes: float = DEFAULT_BLOCK_BYTES) -> float:
    """``np.percentile(img, q)`` (its default, linear method), with the same value, without its
    copy of the image: the two order statistics it interpolates are found by counting over blocks
    of rows (:func:`_kth_smallest`). NaN when the image holds a NaN."""
    img = np.asarray(img)
    if img.dtype.kind != "f" or img.ndim == 0 or img.size == 0 or img.dtype.itemsize not in (2, 4, 8):
        return float(np.percentile(img, q))
    if any(np.isnan(img[rows]).any() for rows in row_blocks(len(img), img.size // len(img), 1, max_bytes)):
        return float("nan")
    virtual = (img.size - 1) * np.true_divide(q, 100)
    below = img.size - 1 if virtual >= img.size - 1 else int(np.floor(virtual))
    a = _kth_smallest(img, below, max_bytes)
    b = a if below == img.size - 1 else _kth_smallest(img, below + 1, max_bytes)
    gamma = float(virtual - np.floor(virtual))  # numpy's _lerp with a Python-float weight
    with np.errstate(invalid="ignore"):  # inf - inf: NaN, as numpy gives
        diff = b - a
        return float(b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma)
