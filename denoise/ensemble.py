"""Combine several denoisers' outputs of one render, each pixel weighted by its estimated error.

Two networks of different shapes make different errors: measured on our held-out scenes and on
../shared/eval-scenes, the flat ``flat-s-allspp`` is the better one from 32 spp up (pixel-scale detail),
the multi-scale ``unet-l-allspp`` from 1 to 16 spp (context), and each is better in some places of every
image. Their plain mean gains at a few spp and loses from 64 spp up, where one of them is clearly
better locally. The render's two halves tell which: with ``y_k`` a denoiser's output, ``x`` the
render and ``V`` the window mean of the halves' variance estimate (:mod:`denoise.noise_guard`),
the window mean ``D_k`` of ``(y_k - x)^2`` (summed over channels) estimates ``V + T_k`` where
``T_k`` is that output's own squared error, so ``T_k ~ max(0, D_k - V)``. Each output is weighted
by ``(1 / (T_k + lam * V))^power``: close to choosing the smaller error where the render has
converged, the plain mean where the noise is so large that the estimates of ``T_k`` cannot tell
the outputs apart (``lam`` regularises the estimate by its own scatter, which grows with V).
Without a variance (a single EXR) the outputs are averaged.

``benchmarks/ensemble.py`` measured the window radius, ``lam`` and ``power`` on our held-out scenes
(flat in all three: radius 2-5, lam 0.1-1, power 1-2 within 0.05 dB) and scores the result on the
eval scenes; power 2 rather than 1 because where renders have converged (``benchmarks/noise_guard.py``'s
converged regime) inverse errors still let the worse output in across a sharp edge (the teapot on
black: 0.8-1.0 dB lower after the guard), where their squares keep it out. Window sums are exact per tile (:func:`denoise.box_filter.box_mean_2d`), so
:func:`combine_in_place` gives the whole-image result bit for bit within any memory bound, and
:func:`denoise_combined` runs the networks and combines their outputs tile by tile: no member's
output is ever held whole.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import ExitStack
from typing import TYPE_CHECKING

import numpy as np

from imaging.blocks import row_blocks
from denoise.box_filter import box_mean_2d
from denoise.tiling import Core, Tile, core_for_budget, run_windows
from denoise.noise_guard import channel_sum, clean_render

if TYPE_CHECKING:
    from denoise.chain import ChainRun

DEFAULT_RADIUS = 3  # window 7x7 (benchmarks/ensemble.py)
DEFAULT_LAMBDA = 0.3  # T_k + lam * V (benchmarks/ensemble.py)
DEFAULT_POWER = 2.0  # weights (1 / (T_k + lam * V))^power (benchmarks/ensemble.py, the converged regime)


def combine_weights(noisy: np.ndarray, outputs: Sequence[np.ndarray], variance: np.ndarray,
                    radius: int = DEFAULT_RADIUS, lam: float = DEFAULT_LAMBDA,
                    power: float = DEFAULT_POWER) -> np.ndarray:
    """HxWxK weights (summing to 1 per pixel) of K outputs of one render: ``(1 / (T_k + lam * V))^power``
    normalised, with V and ``T_k = max(0, D_k - V)`` window means over ``(2r+1)^2`` pixels (see
    the module's docstring). Where V is not finite in a window the outputs get equal weights;
    where some ``T_k + lam * V`` are 0 (a converged window: V = 0 and those outputs equal the
    render there) those outputs share the weight."""
    if not outputs:
        raise ValueError("no outputs to combine")
    if not (lam >= 0 and np.isfinite(lam)):
        raise ValueError(f"lam must be >= 0 and finite, got {lam}")
    if not (power > 0 and np.isfinite(power)):
        raise ValueError(f"power must be positive and finite, got {power}")
    for out in outputs:
        if out.shape != noisy.shape or variance.shape != noisy.shape:
            raise ValueError(f"shapes differ: noisy {noisy.shape}, output {out.shape}, variance {variance.shape}")
    var = np.asarray(variance, np.float32)
    with np.errstate(invalid="ignore", over="ignore"):
        positive = np.maximum(var, np.float32(0.0))
    total = channel_sum(positive)  # NaN or inf where a channel is
    del positive
    unbounded = ~np.isfinite(total)
    anywhere_unbounded = bool(unbounded.any())
    if anywhere_unbounded:
        total[unbounded] = 0.0
    v = box_mean_2d(total, radius)
    del total
    floor = np.float32(lam) * v
    errors = []
    for out in outputs:
        change = np.subtract(out, noisy, dtype=np.float32)
        change *= change
        t = box_mean_2d(channel_sum(change), radius)
        del change
        t -= v
        np.maximum(t, np.float32(0.0), out=t)
        t += floor
        errors.append(t)
    del v, floor
    smallest = errors[0].copy()
    for t in errors[1:]:
        np.minimum(smallest, t, out=smallest)
    w = np.empty((*smallest.shape, len(errors)), np.float32)
    norm = np.zeros_like(smallest)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        for t in errors:  # 1 / err scaled by the smallest: no overflow for tiny errors
            np.divide(smallest, t, out=t)
            np.nan_to_num(t, copy=False, nan=1.0)  # 0/0: the outputs whose error is 0 share the weight
            if power != 1:
                np.power(t, np.float32(power), out=t)
            norm += t
    if anywhere_unbounded:
        equal = box_mean_2d(unbounded.astype(np.float32), radius) > 0
        for t in errors:
            t[equal] = 1.0
        norm[equal] = len(errors)
    for k, t in enumerate(errors):
        t /= norm
        w[:, :, k] = t
    return w


def combine(noisy: np.ndarray, outputs: Sequence[np.ndarray], variance: np.ndarray | None,
            radius: int = DEFAULT_RADIUS, lam: float = DEFAULT_LAMBDA, power: float = DEFAULT_POWER) -> np.ndarray:
    """The weighted sum of ``outputs`` (:func:`combine_weights`), or their mean without a variance;
    float32 HxWx3."""
    if variance is None:
        out = np.array(outputs[0], np.float32)
        for other in outputs[1:]:
            out += other
        out /= np.float32(len(outputs))
        return out
    w = combine_weights(clean_render(noisy), outputs, np.asarray(variance, np.float32), radius, lam, power)
    return weighted_sum(outputs, w)


def weighted_sum(outputs: Sequence[np.ndarray], w: np.ndarray) -> np.ndarray:
    """``sum_k w[..., k] * outputs[k]`` for an HxWxK weight map; float32 HxWx3."""
    out = np.multiply(outputs[0], w[:, :, 0:1], dtype=np.float32)
    for k in range(1, len(outputs)):
        out += outputs[k] * w[:, :, k:k + 1]
    return out


# Peak scratch bytes per pixel (numpy allocations, traced) of combine_weights for K outputs with
# clean_render's copy of its window, and of one row block's combination (its result included),
# float32 HxWx3 in: bounds with headroom of what tests/test_ensemble.py measures with tracemalloc
# (67-77 + 10-13 K and 12-27 at 1x500 to 300x300).
def weight_bytes_per_pixel(k: int) -> int:
    return 64 + 16 * k


COMBINE_BYTES_PER_PIXEL = 40


def combine_in_place(noisy: np.ndarray, outputs: Sequence[np.ndarray], variance: np.ndarray | None,
                     max_bytes: float, radius: int = DEFAULT_RADIUS, lam: float = DEFAULT_LAMBDA,
                     power: float = DEFAULT_POWER) -> None:
    """:func:`combine` written into ``outputs[0]`` within ``max_bytes`` of scratch beyond an HxWxK
    weight map (tiles with ``radius`` pixels of context, then row blocks); bit for bit the
    whole-image result. ``outputs``: float32 HxWx3 arrays; the others are left unchanged."""
    first = outputs[0]
    height, width = first.shape[:2]
    k = len(outputs)
    if variance is None:
        for rows in row_blocks(height, width, COMBINE_BYTES_PER_PIXEL, max_bytes):
            first[rows] = combine(noisy[rows], [o[rows] for o in outputs], None)
        return

    def weight(t: Tile) -> np.ndarray:
        window = slice(t.wy0, t.wy1), slice(t.wx0, t.wx1)
        return combine_weights(clean_render(noisy[window]), [o[window] for o in outputs],
                               np.asarray(variance[window], np.float32), radius, lam, power)

    weights = run_windows(weight, height, width, core_for_budget(weight_bytes_per_pixel(k), max_bytes, radius),
                          radius, out=np.empty((height, width, k), np.float32))
    for rows in row_blocks(height, width, COMBINE_BYTES_PER_PIXEL, max_bytes):
        first[rows] = weighted_sum([o[rows] for o in outputs], weights[rows])


def context_rows(weighted: bool, align: int, radius: int = DEFAULT_RADIUS) -> int:
    """Rows of the members' outputs that :func:`denoise_combined` computes beyond each band: the
    weights' window radius where the outputs are weighted (a variance is given), none where they
    are averaged; rounded up to a multiple of ``align``, so that every band's rows start on the
    networks' grid."""
    return -(-radius // align) * align if weighted else 0


def denoise_combined(runs: Sequence[ChainRun], noisy: np.ndarray, variance: np.ndarray | None, rows: int,
                     cores: Sequence[Core], combine_bytes: float, radius: int = DEFAULT_RADIUS,
                     lam: float = DEFAULT_LAMBDA, power: float = DEFAULT_POWER) -> np.ndarray:
    """:func:`combine` of the chains' outputs (:class:`denoise.chain.ChainRun`, one per network, of
    the HxWx3 render ``noisy``), a band of ``rows`` rows at a time (a multiple of every chain's
    alignment): each chain's output over the band and :func:`context_rows` rows beyond it
    (:meth:`ChainRun.rect` on its own tiles, ``cores``, one per chain), combined there by
    :func:`combine_in_place` within ``combine_bytes`` of scratch, of which the band is kept. The
    same as combining the whole-image outputs; only one band's outputs are held at a time
    (:meth:`denoise.denoiser.Denoiser.ensemble_plan` sizes the bands; one band of the whole image
    holds every output whole, the first of which is returned). Returns a new HxWx3 float32 image."""
    height, width = noisy.shape[:2]
    context = context_rows(variance is not None, max(run.align for run in runs), radius)
    with ExitStack() as stack:
        for run in runs:
            stack.enter_context(run)
        if rows >= height:  # one band: the first output becomes the result
            outputs = [run.rect(0, height, 0, width, core) for run, core in zip(runs, cores)]
            combine_in_place(noisy, outputs, variance, combine_bytes, radius, lam, power)
            return outputs[0]
        out = np.empty((height, width, 3), np.float32)
        for y0 in range(0, height, rows):
            y1 = min(height, y0 + rows)
            r0, r1 = max(0, y0 - context), min(height, y1 + context)
            outputs = [run.rect(r0, r1, 0, width, core) for run, core in zip(runs, cores)]
            combine_in_place(noisy[r0:r1], outputs, None if variance is None else variance[r0:r1], combine_bytes,
                             radius, lam, power)
            out[y0:y1] = outputs[0][y0 - r0:y1 - r0]
            del outputs
    return out
