"""Metrics against hand-computed values on tiny arrays."""
from __future__ import annotations

import math

import numpy as np
import pytest

from imaging import metrics


def test_tonemap_known_values() -> None:
    out = metrics.tonemap(np.array([0.0, 1.0, -3.0, 1e9]))
    np.testing.assert_allclose(out, [0.0, 0.5 ** (1 / 2.2), 0.0, 1.0], atol=1e-8)


def test_psnr_hand_computed_and_identical() -> None:
    ref = np.zeros((2, 2, 3))
    x = np.zeros((2, 2, 3))
    x[0, 0, 0] = 1.0  # tonemaps to 0.5**(1/2.2); one value in 12
    mse = (0.5 ** (1 / 2.2)) ** 2 / 12
    assert metrics.psnr(x, ref) == pytest.approx(10 * math.log10(1 / mse), rel=1e-9)
    assert metrics.psnr(ref, ref) == math.inf


def test_relmse_and_smape_epsilon_handling() -> None:
    ref = np.array([[[0.0, 1.0, 2.0]]])
    x = np.array([[[0.1, 1.0, 1.0]]])
    assert metrics.relmse(x, ref) == pytest.approx(((0.01 / 0.01) + 0 + (1 / 4.01)) / 3)
    assert metrics.smape(x, ref) == pytest.approx((0.1 / 0.11 + 0 + 1 / 3.01) / 3)
    assert metrics.relmse(ref, ref) == 0 and metrics.smape(ref, ref) == 0


def test_ssim_identical_is_one_and_noise_lowers_it(rng) -> None:
    ref = rng.random((24, 24, 3))
    assert metrics.ssim(ref, ref) == pytest.approx(1.0)
    noisy = ref + rng.normal(0, 0.3, ref.shape)
    assert metrics.ssim(noisy, ref) < 0.9
    assert metrics.ssim(np.ones((1, 1, 3)), np.ones((1, 1, 3))) == pytest.approx(1.0)


def test_flip_known_pair(rng) -> None:
    ref = rng.random((32, 32, 3)).astype(np.float32)
    assert metrics.flip(ref, ref) == pytest.approx(0.0, abs=1e-6)
    assert metrics.flip(ref, ref, hdr=True) == pytest.approx(0.0, abs=1e-6)
    slightly, very = ref * 1.05, ref[::-1]
    assert 0 < metrics.flip(slightly, ref) < metrics.flip(very, ref) <= 1
    assert 0 < metrics.flip(slightly, ref, hdr=True) < metrics.flip(very, ref, hdr=True)


def test_shape_mismatch_raises() -> None:
    with pytest.raises(ValueError, match="differs from reference shape"):
        metrics.psnr(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)))


def test_all_metrics_keys(rng) -> None:
    ref = rng.random((16, 16, 3))
    out = metrics.all_metrics(ref * 1.1, ref)
    assert set(out) == {"psnr", "ssim", "relmse", "smape", "flip", "hdr_flip"}
    assert all(np.isfinite(v) for v in out.values())
