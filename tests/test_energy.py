"""The energy correction: analytic cases, its test against the render's own spread, clamps, exposure, memory."""
from __future__ import annotations

import numpy as np
import pytest

from denoise.energy import ENERGY_BYTES_PER_PIXEL, EnergySettings, correct_in_place
from tests.test_noise_guard import _traced_peak

BIG = 2**30  # a memory bound that never splits an image of these tests


def _corrected(noisy: np.ndarray, denoised: np.ndarray, **kw) -> tuple[np.ndarray, float]:
    out = np.array(denoised, np.float32)
    factor = correct_in_place(noisy, out, kw.pop("max_bytes", BIG), **kw)
    return out, factor


def _checkerboard(h: int, w: int, mean: float, spread: float) -> np.ndarray:
    """HxWx3 float32: ``mean +- spread`` alternating per pixel (each 8x8 block's sample variance
    ``spread^2 * 64/63``)."""
    y, x = np.mgrid[0:h, 0:w]
    sign = np.where((y + x) % 2 == 0, 1.0, -1.0)[..., None]
    return np.repeat(mean + spread * sign, 3, axis=2).astype(np.float32)


def test_a_noiseless_render_s_means_are_restored_exactly() -> None:
    """A uniform render has no spread: any difference is significant; a uniform 20% deficit is made
    up everywhere."""
    denoised = np.full((40, 48, 3), 0.5, np.float32)
    out, factor = _corrected(np.full_like(denoised, 0.6), denoised)
    np.testing.assert_allclose(out, 0.6, rtol=1e-6)
    assert factor == pytest.approx(1.2, rel=1e-6)


def test_a_difference_within_the_render_s_noise_is_left_alone() -> None:
    """A render of mean 1.01 spread +-1 (pixel variance 64/63 in every block; every window the whole
    40x40 image): d = 0.01 against se^2 = (64/63) / 1600, so w = 1e-4 / (1e-4 + 4 se^2) = 0.038 and
    the factor is 1 + 0.038 * 0.01."""
    denoised = np.full((40, 40, 3), 1.0, np.float32)
    out, _ = _corrected(_checkerboard(40, 40, 1.01, 1.0), denoised, settings=EnergySettings(radius=5))
    w = 1e-4 / (1e-4 + 4 * (64 / 63) / 1600)
    np.testing.assert_allclose(out, 1 + w * 0.01, rtol=1e-5)


def test_the_factor_is_bounded_both_ways() -> None:
    denoised = np.full((24, 24, 3), 0.1, np.float32)
    np.testing.assert_allclose(_corrected(denoised * 10, denoised)[0], 0.15, rtol=1e-6)
    np.testing.assert_allclose(_corrected(denoised * 0.1, denoised)[0], 0.1 / 1.5, rtol=1e-6)


def test_a_black_output_stays_black_and_a_firefly_counts_as_the_clamp() -> None:
    """Where the output is 0 there is no factor to apply. One sample of 1e6 among 0.5s counts as
    16 (every window the whole 24x24 image): the render's mean a = (0.5 * 575 + 16) / 576, its
    block's spread gives se^2 = 64 * var(block) / 576^2, and the factor is 1 + w (a / 0.5 - 1)."""
    denoised = np.full((24, 24, 3), 0.5, np.float32)
    denoised[:, :, 2] = 0.0
    noisy = denoised.copy()
    noisy[12, 12] = 1e6
    out, _ = _corrected(noisy, denoised, settings=EnergySettings(radius=5))
    assert np.all(out[:, :, 2] == 0)
    block = np.full(64, 0.5)
    block[0] = 16.0
    a, se2 = (0.5 * 575 + 16) / 576, 64 * block.var(ddof=1) / 576**2
    w = (a - 0.5) ** 2 / ((a - 0.5) ** 2 + 4 * se2)
    np.testing.assert_allclose(out[:, :, :2], 0.5 * (1 + w * (a / 0.5 - 1)), rtol=1e-5)


def test_non_finite_inputs_give_a_finite_non_negative_output() -> None:
    rng = np.random.default_rng(0)
    denoised = rng.random((33, 41, 3), dtype=np.float32)
    noisy = denoised * 1.3
    noisy[3, 4] = [np.nan, np.inf, -np.inf]
    noisy[20, 30] = [np.finfo(np.float32).max, -1.0, 1e-30]
    out, factor = _corrected(noisy, denoised)
    assert np.all(np.isfinite(out)) and out.min() >= 0 and np.isfinite(factor)


def test_the_clamp_applies_after_the_exposure() -> None:
    """Scaling both images by 2^-20 with exposure 2^20 scales the result."""
    rng = np.random.default_rng(1)
    denoised = (rng.random((32, 40, 3)) * 30).astype(np.float32)
    noisy = (denoised * rng.gamma(2.0, 0.6, denoised.shape)).astype(np.float32)
    ref, f = _corrected(noisy, denoised)
    s = np.float32(2.0**-20)
    out, g = _corrected(noisy * s, denoised * s, exposure=2.0**20)
    np.testing.assert_allclose(out / s, ref, rtol=1e-5)
    assert g == pytest.approx(f, rel=1e-6)


@pytest.mark.parametrize("max_bytes, workers", [(1, 1), (5e4, 1), (5e4, 2), (BIG, 2)])
def test_row_blocks_and_threads_do_not_change_the_result(max_bytes: float, workers: int) -> None:
    rng = np.random.default_rng(2)
    denoised = rng.random((70, 53, 3), dtype=np.float32)
    noisy = (denoised * rng.gamma(1.0, 1.1, denoised.shape)).astype(np.float32)
    whole, f = _corrected(noisy, denoised)
    part, g = _corrected(noisy, denoised, max_bytes=max_bytes, workers=workers)
    assert np.array_equal(part, whole) and f == g


def test_a_biased_estimate_moves_toward_the_truth() -> None:
    """A smooth truth, an unbiased render of it (gamma-distributed around it, never negative), and
    an output 15% too dark everywhere: the corrected output's error is a fraction of the output's."""
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:96, 0:128]
    truth = np.stack([0.3 + 0.2 * np.sin(x / 20.0), 0.5 + 0.1 * np.cos(y / 15.0), np.full(x.shape, 0.2)], axis=2)
    noisy = (truth * rng.gamma(2.0, 0.5, truth.shape)).astype(np.float32)
    denoised = (truth * 0.85).astype(np.float32)
    out, factor = _corrected(noisy, denoised)
    before, after = np.abs(denoised - truth).mean(), np.abs(out - truth).mean()
    assert after < 0.3 * before
    assert 1.1 < factor < 1.25  # 1 / 0.85 = 1.18


@pytest.mark.parametrize("shape", [(64, 64), (300, 300), (100, 37), (1, 500), (500, 3)])
def test_scratch_per_pixel_stays_under_its_stated_bound(shape: tuple[int, int]) -> None:
    """One row block holding the whole image: within ENERGY_BYTES_PER_PIXEL per pixel, plus the
    block maps (about ten float64 maps of 3 channels, 240 bytes a block, and the hxWx3 float32
    interpolation across) and 16 KiB of Python objects."""
    rng = np.random.default_rng(5)
    denoised = rng.random((*shape, 3), dtype=np.float32)
    noisy = denoised * 1.2
    pixels = shape[0] * shape[1]
    h, w = shape[0] // 8 + 1, shape[1] // 8 + 1
    maps = 300 * h * w + 12 * h * shape[1]
    peak = _traced_peak(lambda: correct_in_place(noisy, denoised, BIG))
    assert peak <= ENERGY_BYTES_PER_PIXEL * pixels + maps + 16384


@pytest.mark.parametrize("workers", [1, 2])
def test_the_correction_stays_within_its_budget(workers: int) -> None:
    """A 600x500 image within 2 MB of row blocks plus the block maps (as in the test above), also
    with two threads at once (tracemalloc counts every thread's allocations); the whole image in
    one block takes several times that."""
    rng = np.random.default_rng(4)
    denoised = rng.random((600, 500, 3), dtype=np.float32)
    noisy = denoised * 1.1
    maps = 300 * 76 * 63 + 12 * 76 * 500
    peak = _traced_peak(lambda: correct_in_place(noisy, denoised, 2e6, workers=workers))
    assert peak <= 2e6 * 1.1 + maps
    whole = denoised.copy()
    assert _traced_peak(lambda: correct_in_place(noisy, whole, BIG)) > 2 * peak


def test_bad_arguments_are_refused() -> None:
    img = np.zeros((8, 8, 3), np.float32)
    with pytest.raises(ValueError, match="shapes differ"):
        correct_in_place(img, img[:4], BIG)
    with pytest.raises(ValueError, match="exposure"):
        correct_in_place(img, img, BIG, exposure=0.0)
    for bad in ({"clamp": 0.0}, {"block": 0}, {"radius": -1}, {"max_ratio": 0.5}, {"significance": -1.0},
                {"clamp": float("nan")}):
        with pytest.raises(ValueError):
            EnergySettings(**bad)
