"""The noise guard: window means, the Wiener blend of render and denoiser."""
from __future__ import annotations

import numpy as np
import pytest

from imaging.render import render
from pipeline.noise_guard import blend_weight, box_mean, guard


def _brute_box_mean(img: np.ndarray, r: int) -> np.ndarray:
    h, w, _ = img.shape
    out = np.empty_like(img, dtype=np.float64)
    for y in range(h):
        for x in range(w):
            out[y, x] = img[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1].mean(axis=(0, 1))
    return out


@pytest.mark.parametrize("radius", [0, 1, 3, 20])
def test_box_mean_matches_brute_force(radius: int) -> None:
    img = np.random.default_rng(0).random((7, 5, 2)).astype(np.float32)
    np.testing.assert_allclose(box_mean(img, radius), _brute_box_mean(img, radius), rtol=1e-5)


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
    with pytest.raises(ValueError, match="radius"):
        box_mean(img, -1)


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
