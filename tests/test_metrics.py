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


def reference_ssim_map(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """SSIM per pixel and channel as Wang et al. 2004 define it, computed here from the paper and
    not from the module: display values x/(1+x) to the power 1/2.2 (negatives 0), one 11x11 2-D
    Gaussian window of standard deviation 1.5 normalised to sum 1, images mirrored at the edges
    (symmetric padding, as the module promises), means, variances and covariance as weighted sums
    over each pixel's window, K1 = 0.01, K2 = 0.03, peak 1."""
    def display(v: np.ndarray) -> np.ndarray:
        v = np.maximum(v.astype(np.float64), 0.0)
        return (v / (1.0 + v)) ** (1.0 / 2.2)

    dy, dx = np.mgrid[-5:6, -5:6]
    window = np.exp(-(dx * dx + dy * dy) / (2.0 * 1.5 * 1.5))
    window /= window.sum()

    def local_mean(v: np.ndarray) -> np.ndarray:
        padded = np.pad(v, ((5, 5), (5, 5), (0, 0)), mode="symmetric")
        return np.einsum("hwcij,ij->hwc", np.lib.stride_tricks.sliding_window_view(padded, (11, 11), axis=(0, 1)),
                         window)

    a, b = display(x), display(ref)
    mu_a, mu_b = local_mean(a), local_mean(b)
    var_a, var_b = local_mean(a * a) - mu_a**2, local_mean(b * b) - mu_b**2
    cov = local_mean(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    return (2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))


@pytest.mark.parametrize("h, w", [(1, 1), (7, 5), (23, 31)])
def test_ssim_is_the_papers_ssim(rng, h: int, w: int) -> None:
    """Against :func:`reference_ssim_map` (window, sigma, constants, tonemap: any of them changed
    moves the mean of a noisy image by far more than rounding)."""
    ref = (rng.random((h, w, 3)) * 4).astype(np.float32)
    x = np.abs(ref + rng.normal(0, 0.5, ref.shape)).astype(np.float32)
    expected = reference_ssim_map(x, ref)
    assert metrics.ssim(x, ref) == pytest.approx(float(expected.mean()), rel=1e-10)
    assert np.allclose(metrics._ssim_rows(x, ref, slice(0, h)), expected, rtol=1e-10, atol=1e-12)


def test_ssim_window_is_the_papers_gaussian() -> None:
    """A single bright pixel on black: SSIM at a pixel d = (dy, dx) from it depends on the window's
    weight w(d) only (mu = w v, sigma^2 = w v^2 - (w v)^2 with v its display value; the reference is
    0), so the image's mean pins the window's shape: sigma 1.5 in pixels, not 1/1.5."""
    size, v = 21, 0.5 ** (1 / 2.2)  # radiance 1 displays as 0.5^(1/2.2)
    x = np.zeros((size, size, 1), np.float32)
    x[10, 10, 0] = 1.0
    g = np.exp(-np.arange(-5, 6) ** 2 / (2 * 1.5**2))
    w2 = np.outer(g, g) / g.sum() ** 2
    c1, c2 = 0.01**2, 0.03**2
    weights = np.zeros((size, size))
    weights[5:16, 5:16] = w2  # the window around each pixel within 5 of the bright one covers it
    mu, var = weights * v, weights * v * v - (weights * v) ** 2
    expected = (c1 * c2) / ((mu**2 + c1) * (var + c2))
    assert metrics.ssim(x, np.zeros_like(x)) == pytest.approx(float(expected.mean()), rel=1e-9)


def whole_image_metrics(x: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """PSNR, SSIM, relMSE and SMAPE computed on whole images at once (as before the row blocks)."""
    a, b = metrics.tonemap(x), metrics.tonemap(ref)
    blur = metrics._gaussian_blur
    mu_a, mu_b = blur(a), blur(b)
    var_a, var_b, cov = blur(a * a) - mu_a**2, blur(b * b) - mu_b**2, blur(a * b) - mu_a * mu_b
    c1, c2 = 0.01**2, 0.03**2
    ssim_map = (2 * mu_a * mu_b + c1) * (2 * cov + c2) / ((mu_a**2 + mu_b**2 + c1) * (var_a + var_b + c2))
    x64, r64 = x.astype(np.float64), ref.astype(np.float64)
    return {"psnr": 10 * np.log10(1 / np.mean((a - b) ** 2)), "ssim": np.mean(ssim_map),
            "relmse": np.mean((x64 - r64) ** 2 / (r64 * r64 + 0.01)),
            "smape": np.mean(np.abs(x64 - r64) / (np.abs(x64) + np.abs(r64) + 0.01))}, ssim_map


@pytest.mark.parametrize("h, w", [(1, 1), (3, 2), (24, 24), (61, 17)])
@pytest.mark.parametrize("max_bytes", [1, 20000, 64 * 2**20])  # one row per block, a few, all
def test_blocked_metrics_are_the_whole_image_ones(rng, h: int, w: int, max_bytes: int) -> None:
    ref = (rng.random((h, w, 3)) * 10 ** rng.uniform(-2, 2, (h, w, 1))).astype(np.float32)
    x = (ref + rng.normal(0, 0.3, ref.shape)).astype(np.float32)
    whole, ssim_map = whole_image_metrics(x, ref)
    got = {"psnr": metrics.psnr(x, ref, max_bytes), "ssim": metrics.ssim(x, ref, max_bytes),
           "relmse": metrics.relmse(x, ref, max_bytes=max_bytes), "smape": metrics.smape(x, ref, max_bytes=max_bytes)}
    for name, value in whole.items():
        assert got[name] == pytest.approx(value, rel=1e-12), name  # sums in blocks: rounding only
    rows = [metrics._ssim_rows(x, ref, slice(y, min(h, y + 2))) for y in range(0, h, 2)]
    assert np.array_equal(np.concatenate(rows), ssim_map)  # every value of the SSIM map exact


def test_blocked_metrics_scratch_stays_within_its_blocks(rng) -> None:
    import tracemalloc

    ref = rng.random((256, 256, 3), dtype=np.float32)
    x = ref * np.float32(1.1)
    max_bytes = 128 * 2**10
    for metric in (metrics.psnr, metrics.ssim, metrics.relmse, metrics.smape, metrics.percentile):
        args = (x, 99) if metric is metrics.percentile else (x, ref)
        tracemalloc.start()
        try:
            metric(*args, max_bytes=max_bytes)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        # SSIM's blocks carry the blur's 10 rows around them
        bound = max_bytes + (11 * 256 * 3 * 128 if metric is metrics.ssim else 64 * 2**10)
        assert peak < bound, (metric.__name__, peak)


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
def test_percentile_is_numpys(rng, dtype: type) -> None:
    for values in (rng.normal(size=(37, 11, 3)), np.round(rng.normal(size=(50, 7, 3)) * 2),
                   np.abs(rng.normal(size=(1, 1, 3))), rng.random((64, 9, 3)) * 1e4):
        values = values.astype(dtype)
        for q in (99, 50, 0, 100, 37.5):
            for max_bytes in (1, 10**9):
                assert metrics.percentile(values, q, max_bytes) == np.percentile(values, q), (q, max_bytes)
    values = rng.random((20, 5, 3)).astype(dtype)
    values[3, 2, 1] = np.inf
    assert metrics.percentile(values, 99) == np.percentile(values, 99)
    values[0, 0, 0] = np.nan
    assert np.isnan(metrics.percentile(values, 99))
