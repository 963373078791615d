"""Transfer functions: round trip, exact zero, maximum, monotonicity, negative clamping."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from imaging.errors import ConfigError
from model.transfer import HDR_MAX, get_transfer

NAMES = ("log", "pu")


def _radiance() -> torch.Tensor:
    dense = torch.linspace(0.0, HDR_MAX, 200_001, dtype=torch.float64)
    small = torch.logspace(-12, np.log10(HDR_MAX), 50_001, dtype=torch.float64)
    return torch.cat([torch.zeros(1, dtype=torch.float64), small, dense]).float()


@pytest.mark.parametrize("name", NAMES)
def test_round_trip_float32(name: str) -> None:
    t = get_transfer(name)
    y = _radiance()
    back = t.inverse(t.forward(y))
    assert back.dtype == torch.float32
    torch.testing.assert_close(back, y, rtol=1e-5, atol=0.0)


@pytest.mark.parametrize("name", NAMES)
def test_zero_and_max(name: str) -> None:
    t = get_transfer(name)
    assert t.forward(torch.zeros(3)).tolist() == [0.0, 0.0, 0.0]
    assert t.inverse(torch.zeros(3)).tolist() == [0.0, 0.0, 0.0]
    assert float(t.forward(torch.tensor([HDR_MAX], dtype=torch.float64))) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("name", NAMES)
def test_monotone(name: str) -> None:
    t = get_transfer(name)
    y = torch.sort(_radiance().double()).values.unique()
    x = t.forward(y)
    assert bool((x[1:] > x[:-1]).all()), "forward must be strictly increasing (float64)"
    x32 = t.forward(y.float())
    assert bool((x32[1:] >= x32[:-1]).all()), "forward must be non-decreasing (float32)"


@pytest.mark.parametrize("name", NAMES)
def test_negatives_clamped(name: str) -> None:
    t = get_transfer(name)
    assert t.forward(torch.tensor([-5.0, -1e-20])).tolist() == [0.0, 0.0]


def test_unknown_name() -> None:
    with pytest.raises(ConfigError, match="unknown transfer function 'srgb'"):
        get_transfer("srgb")


@pytest.mark.parametrize("name", NAMES)
def test_display_is_the_metrics_tonemap(name: str) -> None:
    # display(forward(y)) = imaging.metrics.tonemap(y) wherever y / (1 + y) is above the floor
    # (y >= ~1e-5), within the floor's bound below it; finite, bounded gradients everywhere.
    from imaging.metrics import tonemap
    from model.transfer import DISPLAY_FLOOR, DISPLAY_GAMMA
    t = get_transfer(name)
    y = _radiance()[::20]
    x = t.forward(y).requires_grad_()
    shown = t.display(x)
    expected = torch.from_numpy(tonemap(y.numpy())).float()
    above = y / (1 + y) >= DISPLAY_FLOOR * 1.01
    torch.testing.assert_close(shown[above], expected[above], rtol=2e-5, atol=1e-6)
    assert float((shown.detach()[~above] - expected[~above]).abs().max()) <= DISPLAY_FLOOR ** (1 / DISPLAY_GAMMA)
    shown.sum().backward()
    assert bool(torch.isfinite(x.grad).all()) and float(x.grad.min()) >= 0.0


@pytest.mark.parametrize("name", NAMES)
def test_display_clamps_out_of_range_codes(name: str) -> None:
    # A network output outside [0, 1] shows as black / the brightest value, with no gradient
    # (the metric clamps negative radiance; nothing above HDR_MAX exists), and never NaN.
    t = get_transfer(name)
    x = torch.tensor([-3.0, 0.0, 1.0, 7.0], requires_grad=True)
    shown = t.display(x)
    assert float(shown[0]) == float(shown[1]) and float(shown[2]) == float(shown[3])
    shown.sum().backward()
    assert x.grad.tolist()[0] == 0.0 and x.grad.tolist()[3] == 0.0
    assert bool(torch.isfinite(x.grad).all())
