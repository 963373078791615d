"""denoise.image_noise: the noise level and the Nyquist ratio of one image, checked on noise whose
spectrum is known."""
from __future__ import annotations

import math

import numpy as np
import pytest

from denoise.image_noise import FILTERED_BELOW, MAX_SAMPLED_ROWS, noise_stats


def _white(shape: tuple[int, int], sigma: float, seed: int = 0) -> np.ndarray:
    """Radiance whose log(1 + R + G + B) is 1 plus white Gaussian noise of deviation ``sigma``."""
    rng = np.random.default_rng(seed)
    x = 1.0 + rng.normal(0.0, sigma, shape)
    total = np.expm1(x)
    return np.repeat((total / 3)[..., None], 3, axis=2).astype(np.float32)


@pytest.mark.parametrize("sigma", [0.01, 0.05, 0.2])
def test_white_noise_has_ratio_one_and_its_own_deviation(sigma: float) -> None:
    stats = noise_stats(_white((256, 256), sigma))
    assert stats.ratio == pytest.approx(1.0, abs=0.05)
    assert stats.level == pytest.approx(sigma, rel=0.06)
    assert not stats.filtered and stats.pixels == 252 * 252


def test_noise_spread_over_neighbours_is_called_filtered() -> None:
    """White noise through a [1, 2, 1]/4 kernel on each axis (a tent of radius 1, what a wider
    pixel filter does): its Nyquist response vanishes, the ratio falls far below the threshold."""
    rng = np.random.default_rng(1)
    x = rng.normal(0.0, 0.1, (260, 260))
    k = np.array([0.25, 0.5, 0.25])
    x = sum(w * x[:, i:i + 258] for i, w in enumerate(k))
    x = sum(w * x[i:i + 256] for i, w in enumerate(k))
    img = np.repeat((np.expm1(1.0 + x) / 3)[..., None], 3, axis=2).astype(np.float32)
    stats = noise_stats(img)
    assert stats.ratio < FILTERED_BELOW / 2 and stats.filtered


def test_a_flat_image_has_no_noise_and_no_verdict() -> None:
    for img in (np.full((40, 64, 3), 0.3, np.float32), np.zeros((40, 64, 3), np.float32)):
        stats = noise_stats(img)
        assert math.isnan(stats.level) and math.isnan(stats.ratio) and not stats.filtered
    for tiny in ((4, 100, 3), (100, 4, 3), (1, 1, 3)):
        assert noise_stats(np.ones(tiny, np.float32)).pixels == 0


def test_invalid_values_count_as_zero_and_tall_images_are_sampled() -> None:
    img = _white((128, 128), 0.05)
    bad = img.copy()
    bad[::17, ::13] = np.nan
    bad[5, 5] = -np.inf
    assert np.isfinite(noise_stats(bad).level)
    tall = _white((MAX_SAMPLED_ROWS * 4, 64), 0.05, seed=3)
    stats = noise_stats(tall)
    assert stats.level == pytest.approx(0.05, rel=0.08)
    assert stats.pixels < (MAX_SAMPLED_ROWS + 200) * 60  # strips of it, not every row
