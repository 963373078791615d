"""The noise guard: the Wiener blend of render and denoiser, within its memory bounds."""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from rendering.render import render
from denoise.noise_guard import (BLEND_BYTES_PER_PIXEL, DEFAULT_PIVOT_SPP, GUARD_BYTES_PER_PIXEL, blend,
                                  blend_weight, clean_render, guard, guard_in_place, strength_for)


def _guard_case(h: int, w: int, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    noisy = rng.random((h, w, 3), dtype=np.float32) * 3
    noisy.flat[::97] = np.nan
    noisy.flat[5::89] = -np.inf
    noisy.flat[7::83] = np.inf
    noisy.flat[11::79] = -2.0
    denoised = rng.random((h, w, 3), dtype=np.float32)
    variance = rng.random((h, w, 3), dtype=np.float32) * 0.1
    variance.flat[13::101] = np.inf
    return noisy, denoised, variance


@pytest.mark.parametrize("shape", [(61, 47), (1, 40), (40, 1), (130, 90)])
@pytest.mark.parametrize("max_bytes", [1.0, 50e3, 1e9])
@pytest.mark.parametrize("workers", [1, 2, 3])
def test_guard_in_place_is_the_whole_image_guard(shape: tuple[int, int], max_bytes: float, workers: int) -> None:
    """Tiles for the weights, row blocks for the blend, any budget, on any number of threads:
    the whole-image guard's image, weights and mean weight to the last bit."""
    noisy, denoised, variance = _guard_case(*shape)
    expected, mean = guard(clean_render(noisy), denoised, variance, strength=2.0)
    weights = np.full((*shape, 1), np.nan, np.float32)
    out = denoised.copy()
    guard_in_place(noisy, out, variance, weights, max_bytes, strength=2.0, workers=workers)
    assert np.array_equal(out, expected)
    assert np.array_equal(weights, blend_weight(clean_render(noisy), denoised, variance, strength=2.0))
    assert float(weights.mean()) == mean


def test_guard_in_place_refuses_a_wrong_weight_map() -> None:
    noisy, denoised, variance = _guard_case(8, 8)
    with pytest.raises(ValueError, match="weights must be HxWx1 float32"):
        guard_in_place(noisy, denoised, variance, np.zeros((8, 8), np.float32), 1e6)


def _traced_peak(fn) -> int:
    """Peak bytes numpy allocated while ``fn`` ran, beyond what it returns (tracemalloc)."""
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        tracemalloc.reset_peak()
        result = fn()
        return tracemalloc.get_traced_memory()[1] - before - getattr(result, "nbytes", 0)
    finally:
        tracemalloc.stop()


@pytest.mark.parametrize("shape", [(20, 20), (64, 64), (100, 37), (300, 300), (1, 500), (500, 3)])
def test_guard_scratch_per_pixel_stays_under_its_stated_bound(shape: tuple[int, int]) -> None:
    """What the tile planner assumes: blend_weight with clean_render's copy, and blend, within
    their bytes per pixel (+ 16 KiB of Python objects)."""
    noisy, denoised, variance = _guard_case(*shape)
    pixels = shape[0] * shape[1]
    weight = _traced_peak(lambda: blend_weight(clean_render(noisy), denoised, variance))
    assert weight <= GUARD_BYTES_PER_PIXEL * pixels + 16384
    w = blend_weight(clean_render(noisy), denoised, variance)
    assert _traced_peak(lambda: blend(clean_render(noisy), denoised, w)) <= BLEND_BYTES_PER_PIXEL * pixels + 16384


@pytest.mark.parametrize("workers", [1, 2])
def test_guard_in_place_stays_within_its_budget(workers: int) -> None:
    """A 600x500 image within 2 MB (the same guard on the whole image: ~12 MB), also with two
    threads at once (tracemalloc counts every thread's allocations)."""
    noisy, denoised, variance = _guard_case(600, 500)
    weights = np.empty((600, 500, 1), np.float32)
    peak = _traced_peak(lambda: guard_in_place(noisy, denoised, variance, weights, 2e6, workers=workers))
    assert peak <= 2e6 * 1.1
    whole = _traced_peak(lambda: guard(clean_render(noisy), denoised, variance))
    assert whole > 5 * peak


def test_zero_variance_keeps_the_render_and_infinite_variance_the_denoiser() -> None:
    rng = np.random.default_rng(2)
    noisy, denoised = rng.random((9, 11, 3)).astype(np.float32), rng.random((9, 11, 3)).astype(np.float32)
    kept, weight = guard(noisy, denoised, np.zeros_like(noisy))
    assert np.array_equal(kept, noisy) and weight == 0.0
    free, weight = guard(noisy, denoised, np.full_like(noisy, np.inf))
    assert np.array_equal(free, denoised) and weight == 1.0


@pytest.mark.parametrize("bias", [0.1, 1.0])
def test_blend_error_is_the_wiener_error(bias: float) -> None:
    """Render = truth + noise of variance V, denoiser = truth + an error of variance T = bias^2
    (T >= V): the blend's mean square error is V*T/(V+T) within the windows' estimation error."""
    rng = np.random.default_rng(4)
    truth = rng.random((64, 64, 3)) + 1.0
    v = 0.01
    noisy = truth + rng.normal(0, np.sqrt(v), truth.shape)
    denoised = truth + bias * rng.choice([-1.0, 1.0], truth.shape)
    out, weight = guard(noisy, denoised, np.full(truth.shape, v), radius=3)
    mse = float(((out - truth) ** 2).mean())
    t = bias**2
    assert mse == pytest.approx(v * t / (v + t), rel=0.25)
    assert mse < 1.05 * min(v, t) and 0.0 <= weight <= 1.0


@pytest.mark.parametrize("strength,removed", [(1.0, 0.99), (2.0, 0.9999)])
def test_a_perfect_denoiser_is_mostly_kept(strength: float, removed: float) -> None:
    """d = truth: the change is the noise itself, D ~ V, w ~ 1. Window estimates of D scatter
    around V, so with strength 1 some weights fall below 1 and a little noise comes back."""
    rng = np.random.default_rng(5)
    truth = rng.random((64, 64, 3)) + 0.5
    v = 0.04
    noisy = truth + rng.normal(0, np.sqrt(v), truth.shape)
    w = blend_weight(noisy, truth, np.full(truth.shape, v), radius=3, strength=strength)
    assert w.shape == (64, 64, 1) and w.min() > 0.6
    out, _ = guard(noisy, truth, np.full(truth.shape, v), radius=3, strength=strength)
    assert float(((out - truth) ** 2).mean()) < (1 - removed) * v


@pytest.mark.parametrize("strength", [1.0, 256.0])
def test_extreme_finite_values_stay_finite_without_warnings(strength: float) -> None:
    # Variances at float32's maximum and changes near it (a broken file, a firefly of 3e38): the
    # channel and window sums stay finite (no overflow warning), a huge variance frees the
    # denoiser (weight 1) and a huge change where the variance is ordinary keeps the render (weight ~0).
    big = np.finfo(np.float32).max
    noisy = np.ones((12, 12, 3), np.float32)
    denoised = noisy.copy()
    variance = np.full((12, 12, 3), 0.01, np.float32)
    variance[:, :6] = big
    denoised[:, 9:] = -big
    with np.errstate(all="raise"):
        w = blend_weight(noisy, denoised, variance, radius=1, strength=strength)[..., 0]
    assert np.isfinite(w).all() and w.min() >= 0 and w.max() <= 1
    assert (w[:, :6] == 1).all()
    assert (w[:, 10:] < 1e-20).all()


def test_nonfinite_variance_frees_its_window_only() -> None:
    noisy, denoised = np.zeros((1, 9, 3), np.float32), np.ones((1, 9, 3), np.float32)
    variance = np.zeros_like(noisy)
    variance[0, 4, 0] = np.nan
    out, _ = guard(noisy, denoised, variance, radius=1)
    expected = np.array([0, 0, 0, 1, 1, 1, 0, 0, 0], np.float32)
    for c in range(3):  # one weight per pixel: all channels alike
        assert np.array_equal(out[0, :, c], expected)


def test_bad_arguments_are_refused() -> None:
    img = np.zeros((2, 2, 3), np.float32)
    with pytest.raises(ValueError, match="strength"):
        guard(img, img, img, strength=0)
    with pytest.raises(ValueError, match="shapes differ"):
        guard(img, img[:1], img)


def test_render_in_halves_estimates_its_own_noise(plane_scene: dict) -> None:
    """The halves' variance estimate agrees with the spread of independent renders of equal spp."""
    halves = render(plane_scene, spp=8, seed=3, halves=True)
    assert halves.variance is not None and halves.variance.shape == halves.rgb.shape
    assert np.isfinite(halves.variance).all() and halves.variance.min() >= 0
    a, b = (render(plane_scene, spp=8, seed=s).rgb for s in (11, 12))
    spread = float(((a - b) ** 2 / 2).mean())  # E[(a-b)^2]/2 = variance of one 8-spp render
    assert float(halves.variance.mean()) == pytest.approx(spread, rel=0.25)
    assert abs(halves.rgb.mean() - a.mean()) < 0.05 * a.mean()
    assert render(plane_scene, spp=1, halves=True).variance is None
    assert render(plane_scene, spp=8, seed=3).variance is None


@pytest.mark.parametrize("spp, pivot, expected", [(1, 16, 16.0), (4, 16, 4.0), (8, 32, 4.0), (16, 16, 1.0),
                                                  (64, 16, 1.0), (3, 12, 4.0), (1, 0, 1.0), (1000, 0, 1.0)])
def test_strength_grows_as_pivot_over_spp(spp: int, pivot: float, expected: float) -> None:
    """By hand: max(1, pivot / spp); fewer samples, a stronger guard (the variance is trusted less)."""
    assert strength_for(spp, pivot) == expected


def test_default_strength_at_a_few_samples() -> None:
    assert DEFAULT_PIVOT_SPP == 256
    assert (strength_for(1), strength_for(16), strength_for(256), strength_for(4096)) == (256.0, 16.0, 1.0, 1.0)


@pytest.mark.parametrize("strength, weight", [(1.0, 0.48), (2.0, 0.96), (4.0, 1.0)])
def test_blend_weight_and_blend_by_hand(strength: float, weight: float) -> None:
    """A uniform image (every window mean is the pixel's value): V = 0.1 + 0.2 + 0.3 = 0.6,
    D = 0.5^2 + 0 + 1^2 = 1.25, weight min(1, strength 0.6 / 1.25); the blend is
    w denoised + (1 - w) noisy."""
    noisy = np.broadcast_to(np.float32([1.0, 2.0, 3.0]), (5, 4, 3)).copy()
    denoised = np.broadcast_to(np.float32([1.5, 2.0, 2.0]), (5, 4, 3)).copy()
    variance = np.broadcast_to(np.float32([0.1, 0.2, 0.3]), (5, 4, 3)).copy()
    w = blend_weight(noisy, denoised, variance, strength=strength)
    np.testing.assert_allclose(w, weight, rtol=1e-6)
    image, mean = guard(noisy, denoised, variance, strength=strength)
    np.testing.assert_allclose(image, weight * denoised + (1 - weight) * noisy, rtol=1e-6)
    assert mean == pytest.approx(weight, rel=1e-6)


def test_clean_render_by_hand() -> None:
    noisy = np.array([[[np.nan, np.inf, -np.inf], [-2.0, 0.0, 0.5]]], np.float64)
    out = clean_render(noisy)
    assert out.dtype == np.float32 and np.array_equal(out, [[[0, 0, 0], [0, 0, 0.5]]])


def test_the_default_window_is_five_pixels_wide() -> None:
    """One row; the render's variance 0.5 at pixel 4 only, a change of 1 everywhere (D = 1): the
    weight is V = 0.5 / 5 in the 5-px windows (cut at the row's ends) that hold pixel 4, 0 elsewhere."""
    noisy = np.zeros((1, 9, 3), np.float32)
    denoised = noisy.copy()
    denoised[..., 0] = 1.0
    variance = np.zeros_like(noisy)
    variance[0, 4, 0] = 0.5
    np.testing.assert_allclose(blend_weight(noisy, denoised, variance)[0, :, 0],
                               [0, 0, 0.1, 0.1, 0.1, 0.1, 0.1, 0, 0], rtol=1e-6, atol=1e-7)
