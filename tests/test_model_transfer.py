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
