"""The loss: 0.9 * L1 + 0.1 * mean of the x/y gradient L1 terms."""
from __future__ import annotations

import pytest
import torch

from model.loss import denoising_loss, gradient_l1


def test_hand_computed_4x4() -> None:
    ref = torch.zeros(1, 1, 4, 4)
    out = torch.zeros(1, 1, 4, 4)
    out[0, 0, 1, 2] = 1.0  # one pixel off by 1
    # L1: 1/16. x-differences (4 rows x 3): the pixel enters two, each |1| -> 2/12.
    # y-differences (3 x 4 cols): likewise 2/12. Gradient term: (2/12 + 2/12) / 2 = 1/6.
    expected = 0.9 / 16 + 0.1 / 6
    assert float(gradient_l1(out, ref)) == pytest.approx(1 / 6, rel=1e-6)
    assert float(denoising_loss(out, ref)) == pytest.approx(expected, rel=1e-6)


def test_hand_computed_ramp() -> None:
    # out - ref = x-ramp 0,1,2,3 in each row: L1 = 1.5, x-gradient L1 = 1, y-gradient L1 = 0.
    out = torch.arange(4.0).repeat(4, 1).view(1, 1, 4, 4)
    ref = torch.zeros_like(out)
    assert float(denoising_loss(out, ref)) == pytest.approx(0.9 * 1.5 + 0.1 * 0.5, rel=1e-6)


def test_zero_for_identical_and_symmetric() -> None:
    gen = torch.Generator().manual_seed(0)
    a, b = torch.rand(2, 3, 5, 6, generator=gen), torch.rand(2, 3, 5, 6, generator=gen)
    assert float(denoising_loss(a, a)) == 0.0
    assert float(denoising_loss(a, b)) == pytest.approx(float(denoising_loss(b, a)), rel=1e-6)


def test_shape_mismatch() -> None:
    with pytest.raises(ValueError, match="differs from reference shape"):
        denoising_loss(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))
