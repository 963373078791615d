"""Give a denoised image back the local mean radiance of the render where the render proves it.

A network trained with L1 in a compressive transfer space (PU, log) predicts something close to the
median of the radiance it cannot resolve, not its mean: at a few spp, where a pixel's estimate is
a few bright samples among dark ones, it comes out darker than the truth. Measured on the eval
scenes at 4 spp the default model kept 95% of the reference's mean radiance (80-99% per scene,
OIDN 98-113%). The render itself is an unbiased estimate of that mean: averaged over a wide
window its noise is small, so the output's window mean can be matched to it.

Per channel, with ``a`` the render's and ``b`` the output's mean over a window of about 40 px
(``block`` x ``block`` pixel blocks, a (2r+1)^2 window of blocks), the output is multiplied by
``1 + w * (clip(a / b, 1/max_ratio, max_ratio) - 1)``, the ratio map interpolated bilinearly
between block centres. ``w = d^2 / (d^2 + k * se^2)`` with ``d = a - b`` and ``se^2`` the
variance of ``a``: the window's pixel variance over its pixel count, the pixel variance taken from
the render itself, each block's sample variance. That is the noise plus the signal's own variation
within 8 px, an over-estimate of the noise, so the test errs towards leaving the output alone; it
needs no second render (a 1-spp render, a file from elsewhere), and measured as good as the
variance of the render's two halves where those exist (docs/design.md). Where the difference
is within the render's own spread the output is left alone; where it is several standard errors
off, matched. Values are clamped at ``clamp`` (radiance after the network's exposure scale,
:func:`denoise.chain.exposure_scale`) before anything is summed: one firefly of 1000 would otherwise
make a whole window's mean.

``benchmarks/energy.py`` measured the settings on our held-out scenes (1-16 spp) and scores them
on ../shared/eval-scenes (docs/evaluate.md, benchmarks/energy.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imaging.blocks import block_rows, parallel_map, row_blocks
from denoise.box_filter import box_sum_2d
from model.transfer import HDR_MAX

# Peak scratch bytes per pixel of a row block: a clamped float32 copy summed by :func:`block_sums`,
# then squared in place and summed again (12 + 1.5), or :func:`_apply_rows`' interpolated factors
# and their lower half (24): a bound with headroom of what tests/test_energy.py measures.
ENERGY_BYTES_PER_PIXEL = 32


@dataclass(frozen=True)
class EnergySettings:
    """``clamp``: radiance (after exposure) at which values are clamped before averaging;
    ``block``: pixels per block side; ``radius``: the window's radius in blocks; ``max_ratio``:
    the largest factor either way; ``significance``: ``k``, standard errors squared that a
    difference must exceed to be half matched."""

    clamp: float = 16.0
    block: int = 8
    radius: int = 2
    max_ratio: float = 1.5
    significance: float = 4.0

    def __post_init__(self) -> None:
        if not (self.clamp > 0 and np.isfinite(self.clamp)):
            raise ValueError(f"clamp must be positive and finite, got {self.clamp}")
        if self.block < 1 or self.radius < 0:
            raise ValueError(f"block must be >= 1 and radius >= 0, got {self.block}, {self.radius}")
        if not (self.max_ratio >= 1 and np.isfinite(self.max_ratio)):
            raise ValueError(f"max_ratio must be >= 1 and finite, got {self.max_ratio}")
        if not (self.significance >= 0 and np.isfinite(self.significance)):
            raise ValueError(f"significance must be >= 0 and finite, got {self.significance}")


def settings_if(on: bool) -> EnergySettings | None:
    """The default :class:`EnergySettings` where the correction is on, None (off) where not: what a
    ``--no-energy`` flag or an ``energy`` config field turns into."""
    return EnergySettings() if on else None


def scaled(x: np.ndarray, exposure: float, clamp: float) -> np.ndarray:
    """float32 copy of radiance ``x`` times ``exposure``, clamped to [0, clamp] (NaN -> 0; clamped
    before scaling, so nothing overflows)."""
    out = np.array(x, dtype=np.float32)
    np.putmask(out, np.isnan(out), 0.0)
    np.clip(out, 0.0, clamp / exposure, out=out)
    out *= np.float32(exposure)
    return np.clip(out, 0.0, clamp, out=out)


def block_sums(x: np.ndarray, block: int) -> np.ndarray:
    """(ceil(H/block) x ceil(W/block) x C) float64 sums of an HxWxC float32 array's blocks (the
    last row and column of blocks may be partial): down the rows in float32 (``block`` values, a
    1/block-size result), then across in float64; no copy of the input."""
    rows = np.add.reduceat(x, np.arange(0, x.shape[0], block), axis=0)
    return np.add.reduceat(rows.astype(np.float64), np.arange(0, x.shape[1], block), axis=1)


def block_statistics(noisy: np.ndarray, denoised: np.ndarray, exposure: float, clamp: float, block: int,
                     max_bytes: float, workers: int = 1) -> tuple[np.ndarray, ...]:
    """Per block of ``block`` x ``block`` pixels, at the network's ``exposure`` (:func:`scaled`):
    sums of the render and of the output, the render's sample variance (unbiased) times the block's
    pixel count (the sum of its pixels' variances, were they equal), each hxwx3 float64, and the
    pixel counts (hxwx1). Row blocks of whole pixel blocks within ``max_bytes``."""
    height, width = denoised.shape[:2]
    workers = max(1, workers)
    rows = max(block, block_rows(width, ENERGY_BYTES_PER_PIXEL, max_bytes / workers, -(-height // workers))
               // block * block)  # whole pixel blocks

    def sums(y: int) -> tuple[np.ndarray, ...]:
        part = slice(y, min(height, y + rows))
        x = scaled(noisy[part], exposure, clamp)
        plain = block_sums(x, block)
        x *= x
        return plain, block_sums(x, block), block_sums(scaled(denoised[part], exposure, clamp), block)

    parts = parallel_map(sums, range(0, height, rows), workers)
    noisy_sums, square_sums, out_sums = (np.concatenate([p[i] for p in parts], axis=0) for i in range(3))
    counts = _block_counts(height, width, block)[..., None]
    var_sums = np.maximum(square_sums - noisy_sums * noisy_sums / counts, 0.0) * counts / np.maximum(counts - 1, 1)
    return noisy_sums, out_sums, var_sums, counts


def _block_counts(height: int, width: int, block: int) -> np.ndarray:
    """hxw float64: the pixels in each block (the last row and column of blocks may be partial)."""
    return np.outer(np.minimum(block, height - np.arange(0, height, block)),
                    np.minimum(block, width - np.arange(0, width, block))).astype(np.float64)


def _window_sums(x: np.ndarray, radius: int) -> np.ndarray:
    """Per-channel (2r+1)^2 window sums of an hxwxC array of block values, float64."""
    return np.stack([box_sum_2d(x[:, :, c], radius) for c in range(x.shape[2])], axis=2).astype(np.float64)


def ratio_map(noisy_sums: np.ndarray, out_sums: np.ndarray, var_sums: np.ndarray, counts: np.ndarray,
              settings: EnergySettings) -> np.ndarray:
    """hxwx3 float32 factor per block (the module's formula) from :func:`block_statistics`."""
    n = _window_sums(counts, settings.radius)  # float32 sums: clamped values keep them far from its limits
    a = _window_sums(noisy_sums, settings.radius) / n
    b = _window_sums(out_sums, settings.radius) / n
    se2 = _window_sums(var_sums, settings.radius) / (n * n)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.clip(a / b, 1.0 / settings.max_ratio, settings.max_ratio)
        d2 = (a - b) ** 2
        w = d2 / (d2 + settings.significance * se2)
    ratio = 1.0 + np.nan_to_num(w, nan=0.0) * (ratio - 1.0)
    return np.where(b > 0, ratio, 1.0).astype(np.float32)


def _interpolation(n: int, cells: int, block: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For pixels 0..n-1: the two block indices around each pixel centre and the second's weight."""
    pos = (np.arange(n) + 0.5) / block - 0.5
    lo = np.clip(np.floor(pos).astype(np.int64), 0, cells - 1)
    hi = np.minimum(lo + 1, cells - 1)
    return lo, hi, np.clip(pos - lo, 0.0, 1.0).astype(np.float32)


def _across(ratio: np.ndarray, width: int, block: int) -> np.ndarray:
    """hxWx3 float32: each row of the block map interpolated linearly to the pixel columns."""
    x0, x1, fx = _interpolation(width, ratio.shape[1], block)
    out = ratio[:, x0] * (1.0 - fx)[None, :, None]
    out += ratio[:, x1] * fx[None, :, None]
    return out


def _apply_rows(denoised: np.ndarray, across: np.ndarray, rows: slice, block: int, upper: float) -> None:
    """Multiply ``denoised[rows]`` in place by :func:`_across`'s map interpolated down to its rows,
    capped at ``upper``."""
    y0, y1, fy = (a[rows] for a in _interpolation(denoised.shape[0], across.shape[0], block))
    factor = across[y0]
    factor *= (1.0 - fy)[:, None, None]
    lower = across[y1]
    lower *= fy[:, None, None]
    factor += lower
    del lower
    part = denoised[rows]
    with np.errstate(over="ignore"):  # a product past float32's range is inf, capped on the next line
        part *= factor
    np.minimum(part, np.float32(upper), out=part)


def correct_in_place(noisy: np.ndarray, denoised: np.ndarray, max_bytes: float, exposure: float = 1.0,
                     settings: EnergySettings = EnergySettings(), workers: int = 1) -> float:
    """Match ``denoised``'s local means to ``noisy``'s as the module describes, in place.

    ``noisy``: HxWx3 render (any float dtype); ``denoised``: HxWx3 float32 >= 0, changed in place
    (stays >= 0, finite and at most ``HDR_MAX / exposure``, the chain's own bound); ``exposure``: the
    factor the network scaled the radiance by (``clamp`` applies after it).
    Scratch memory: row blocks within ``max_bytes`` (``workers`` of them at a time on threads)
    plus the block maps (about 1/block^2 of the image each). Returns the mean factor applied
    (pixel-weighted over the three channels; 1: nothing changed).
    """
    if noisy.shape != denoised.shape or denoised.ndim != 3 or denoised.shape[2] != 3:
        raise ValueError(f"shapes differ or are not HxWx3: noisy {noisy.shape}, denoised {denoised.shape}")
    if not (exposure > 0 and np.isfinite(exposure)):
        raise ValueError(f"exposure must be positive and finite, got {exposure}")
    if denoised.size == 0:
        return 1.0
    ratio = ratio_map(*block_statistics(noisy, denoised, exposure, settings.clamp, settings.block, max_bytes, workers),
                      settings)
    return apply_ratio(denoised, ratio, settings.block, max_bytes, HDR_MAX / exposure, workers)


def apply_ratio(denoised: np.ndarray, ratio: np.ndarray, block: int, max_bytes: float, upper: float = HDR_MAX,
                workers: int = 1) -> float:
    """Multiply ``denoised`` in place by the block map ``ratio`` interpolated bilinearly between block
    centres, capped at ``upper`` (the chain's bound, ``HDR_MAX`` over the exposure: float16 files keep
    every value), in row blocks within ``max_bytes``; returns the mean factor (pixel-weighted, over
    the channels)."""
    height, width = denoised.shape[:2]
    across = _across(ratio, width, block)
    parallel_map(lambda rows: _apply_rows(denoised, across, rows, block, upper),
                 row_blocks(height, width, ENERGY_BYTES_PER_PIXEL, max_bytes / max(1, workers), workers), workers)
    return float(ratio.mean(axis=2).ravel() @ _block_counts(height, width, block).ravel() / (height * width))
