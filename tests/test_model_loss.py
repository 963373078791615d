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


def test_log_loss_is_mean_of_patch_logs() -> None:
    # Two patches whose plain losses are 1.5 and 0.0 (see test_hand_computed_ramp): the log loss
    # is the mean of their logs with eps added, and matches each patch scored on its own.
    ramp = torch.arange(4.0).repeat(4, 1).view(1, 1, 4, 4)
    out = torch.cat([ramp, torch.zeros_like(ramp)])
    ref = torch.zeros_like(out)
    eps = 0.01
    expected = (torch.log(torch.tensor(1.4 + eps)) + torch.log(torch.tensor(eps))) / 2
    assert float(denoising_loss(out, ref, log_eps=eps)) == pytest.approx(float(expected), rel=1e-6)
    singles = [float(denoising_loss(out[i:i + 1], ref[i:i + 1], log_eps=eps)) for i in range(2)]
    assert float(denoising_loss(out, ref, log_eps=eps)) == pytest.approx(sum(singles) / 2, rel=1e-6)


def test_log_loss_weights_patches_by_their_inverse_loss() -> None:
    # d/d(out) of log(l + eps) is dl/d(out) / (l + eps): a patch with 10x the error gets 1/10 the
    # weight per unit of its own loss's gradient.
    gen = torch.Generator().manual_seed(1)
    ref = torch.rand(2, 3, 8, 8, generator=gen)
    out = ref + torch.cat([torch.full((1, 3, 8, 8), 0.5), torch.full((1, 3, 8, 8), 0.05)])
    out.requires_grad_(True)
    eps = 1e-3
    denoising_loss(out, ref, gradient_weight=0.0, log_eps=eps).backward()
    g = out.grad.abs().mean((1, 2, 3))
    expected_ratio = (0.05 + eps) / (0.5 + eps)
    assert float(g[0] / g[1]) == pytest.approx(expected_ratio, rel=1e-4)
