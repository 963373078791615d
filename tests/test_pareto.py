"""Pareto frontier and equal-quality interpolation on synthetic curves with known answers."""
from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.pareto import (equal_quality, error_at_spp, metric_error, pareto_front, spp_at_error,
                             time_at_spp)

SPP = [1, 2, 4, 8, 16, 32, 64, 128]
C = 0.5  # noisy relMSE = C / spp: a power law of slope -1


def _noisy_error(spp: float) -> float:
    return C / spp


def _render_s(spp: float) -> float:
    return 0.2 + 0.01 * spp  # fixed cost + cost per sample


def test_pareto_front_known_points() -> None:
    times = [1.0, 2.0, 3.0, 4.0, 2.0, 0.5, 5.0]
    errors = [5.0, 3.0, 4.0, 1.0, 3.0, 9.0, 1.0]
    # (3, 4) is beaten by (2, 3); (2, 3) appears twice (first kept); (5, 1) is beaten by (4, 1)
    assert pareto_front(times, errors) == [5, 0, 1, 3]


def test_pareto_front_ignores_non_finite_and_checks_lengths() -> None:
    assert pareto_front([1.0, 2.0, math.nan], [math.inf, 1.0, 0.1]) == [1]
    with pytest.raises(ValueError, match="2 times but 1 errors"):
        pareto_front([1.0, 2.0], [1.0])


@pytest.mark.parametrize("spp", [1.0, 3.0, 37.0, 100.0, 128.0])
def test_spp_at_error_inside_range_is_exact_on_a_power_law(spp: float) -> None:
    eq = spp_at_error(SPP, [_noisy_error(s) for s in SPP], _noisy_error(spp))
    assert not eq.extrapolated
    assert eq.spp == pytest.approx(spp, rel=1e-9)


@pytest.mark.parametrize("spp", [0.25, 512.0, 4096.0])
def test_spp_at_error_extrapolates_along_the_power_law(spp: float) -> None:
    eq = spp_at_error(SPP, [_noisy_error(s) for s in SPP], _noisy_error(spp))
    assert eq.extrapolated
    assert eq.spp == pytest.approx(spp, rel=1e-9)


def test_spp_at_error_uses_the_running_minimum_of_a_noisy_curve() -> None:
    errors = [1.0, 0.5, 0.6, 0.25]  # 4 spp measured worse than 2 spp: ignored
    eq = spp_at_error([1, 2, 4, 8], errors, 0.35)
    # between (2, 0.5) and (8, 0.25) in log-log: slope -0.5 -> spp = 2 * (0.35/0.5)^-2
    assert eq.spp == pytest.approx(2 * (0.35 / 0.5) ** -2, rel=1e-9)


def test_spp_at_error_degenerate_curves() -> None:
    assert math.isnan(spp_at_error([4], [0.1], 0.05).spp)
    assert math.isnan(spp_at_error([1, 2], [0.1, 0.1], 0.05).spp)  # flat: no second point
    assert spp_at_error(SPP, [_noisy_error(s) for s in SPP], 0.0).spp == math.inf


def test_time_at_spp_linear_cost() -> None:
    times = [_render_s(s) for s in SPP]
    for spp in (1, 6, 100, 128, 1000, 5000):
        assert time_at_spp(SPP, times, spp) == pytest.approx(_render_s(spp), rel=1e-9)
    assert time_at_spp([4], [0.8], 8) == pytest.approx(1.6)


def test_equal_quality_known_saving() -> None:
    errors = [_noisy_error(s) for s in SPP]
    times = [_render_s(s) for s in SPP]
    # a denoiser that at 4 spp reaches the raw 64-spp error, in 0.1 s of denoising
    eq = equal_quality(SPP, errors, times, spp=4, total_s=_render_s(4) + 0.1, error=_noisy_error(64))
    assert eq.raw_spp == pytest.approx(64, rel=1e-9) and not eq.extrapolated
    assert eq.raw_s == pytest.approx(_render_s(64))
    assert eq.saving == pytest.approx(_render_s(64) / (_render_s(4) + 0.1))
    assert eq.spp_ratio == pytest.approx(16)
    far = equal_quality(SPP, errors, times, spp=4, total_s=1.0, error=_noisy_error(1024))
    assert far.extrapolated and far.raw_spp == pytest.approx(1024)
    assert far.saving == pytest.approx(_render_s(1024))


def test_error_at_spp_interpolates_and_never_rises() -> None:
    spp = [1, 4, 16]
    errors = [_noisy_error(s) for s in spp]
    assert error_at_spp(spp, errors, 8) == pytest.approx(_noisy_error(8))
    assert error_at_spp(spp, errors, 64) == pytest.approx(_noisy_error(64))
    flat_then_up = [0.1, 0.05, 0.06]  # a denoiser's curve flattening with timing noise
    assert error_at_spp(spp, flat_then_up, 64) == pytest.approx(0.06)


def test_metric_error_conversions() -> None:
    assert metric_error("psnr", 20.0) == pytest.approx(0.01)
    assert metric_error("psnr", None) == 0.0  # identical images
    assert metric_error("relmse", 0.3) == 0.3
    with pytest.raises(ValueError, match="unknown metric 'ssim'"):
        metric_error("ssim", 0.9)
    assert np.isfinite(metric_error("flip", 0.1))
