"""The loss: 0.9 * L1 + 0.1 * mean of the x/y gradient L1 terms; the MS-SSIM mix."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from training.loss import (SSIM_C1, SSIM_C2, SSIM_SIGMA, SSIM_WINDOW, denoising_loss, gradient_l1, ms_ssim,
                        ms_ssim_scales)


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


def _brute_ssim(x: np.ndarray, y: np.ndarray) -> float:
    """Single-scale SSIM of two CxPxP arrays, float64: every valid 11x11 window's Gaussian-weighted
    statistics computed directly, averaged over windows and channels."""
    r = np.arange(SSIM_WINDOW) - SSIM_WINDOW // 2
    g = np.exp(-r * r / (2 * SSIM_SIGMA ** 2))
    w = np.outer(g, g) / np.outer(g, g).sum()
    values = []
    for c in range(x.shape[0]):
        for i in range(x.shape[1] - SSIM_WINDOW + 1):
            for j in range(x.shape[2] - SSIM_WINDOW + 1):
                a, b = x[c, i:i + SSIM_WINDOW, j:j + SSIM_WINDOW], y[c, i:i + SSIM_WINDOW, j:j + SSIM_WINDOW]
                ma, mb = (w * a).sum(), (w * b).sum()
                va, vb = (w * a * a).sum() - ma * ma, (w * b * b).sum() - mb * mb
                cov = (w * a * b).sum() - ma * mb
                values.append((2 * ma * mb + SSIM_C1) * (2 * cov + SSIM_C2)
                              / ((ma * ma + mb * mb + SSIM_C1) * (va + vb + SSIM_C2)))
    return float(np.mean(values))


def test_ms_ssim_scales_keep_the_window_inside_the_patch() -> None:
    assert [ms_ssim_scales(s) for s in (11, 16, 21, 22, 28, 64, 128, 256, 1024)] == [1, 1, 1, 2, 2, 3, 4, 5, 5]
    for size in (11, 28, 64, 128, 176):
        assert size // 2 ** (ms_ssim_scales(size) - 1) >= SSIM_WINDOW


def test_single_scale_ms_ssim_is_brute_force_ssim() -> None:
    rng = np.random.default_rng(5)
    x = rng.random((2, 3, 16, 16))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    got = ms_ssim(torch.from_numpy(x).float(), torch.from_numpy(y).float())
    want = [_brute_ssim(x[n], y[n]) for n in range(2)]
    assert ms_ssim_scales(16) == 1
    np.testing.assert_allclose(got.numpy(), want, rtol=0, atol=2e-5)


def test_ms_ssim_is_one_for_identical_patches_and_falls_with_noise() -> None:
    rng = np.random.default_rng(6)
    ref = torch.from_numpy(rng.random((4, 3, 64, 64))).float() * 0.5
    torch.testing.assert_close(ms_ssim(ref, ref), torch.ones(4), rtol=0, atol=1e-5)
    values = [float(ms_ssim(ref + torch.randn_like(ref) * s, ref).mean()) for s in (0.01, 0.05, 0.2)]
    assert 1 > values[0] > values[1] > values[2]


def test_ms_ssim_weight_mixes_per_patch_and_keeps_gradients_finite() -> None:
    torch.manual_seed(7)
    ref = torch.rand(3, 3, 28, 28)
    ref[0] = 0.25  # a flat patch: zero variances on both sides
    out = (ref + 0.05 * torch.randn_like(ref)).requires_grad_()
    base = denoising_loss(out, ref)
    assert torch.equal(denoising_loss(out, ref, ms_ssim_weight=0.0), base)
    mixed = denoising_loss(out, ref, ms_ssim_weight=0.84)
    expected = 0.16 * denoising_loss(out, ref) + 0.84 * (1 - ms_ssim(out, ref)).mean()
    torch.testing.assert_close(mixed, expected)
    only = denoising_loss(out, ref, gradient_weight=0.0, ms_ssim_weight=1.0)
    torch.testing.assert_close(only, (1 - ms_ssim(out, ref)).mean())
    mixed.backward()
    assert out.grad is not None and torch.isfinite(out.grad).all() and out.grad.abs().sum() > 0


def test_l2_norm_squares_both_terms() -> None:
    # The ramp of test_hand_computed_ramp: squared values 0,1,4,9 -> mean 3.5; x-differences all
    # 1 -> squared 1; y-differences 0.
    out = torch.arange(4.0).repeat(4, 1).view(1, 1, 4, 4)
    ref = torch.zeros_like(out)
    assert float(denoising_loss(out, ref, norm="l2")) == pytest.approx(0.9 * 3.5 + 0.1 * 0.5, rel=1e-6)
    with pytest.raises(ValueError, match="unknown loss norm 'l3'"):
        denoising_loss(out, ref, norm="l3")


def test_l2_is_minimised_by_the_mean_l1_by_the_median() -> None:
    # A constant prediction c of skewed samples: the L2 loss is least at their mean, L1 at their median.
    samples = torch.tensor([0.0, 0.0, 0.0, 1.0]).view(4, 1, 1, 1)
    def loss(c: float, norm: str) -> float:
        return float(denoising_loss(torch.full_like(samples, c), samples, gradient_weight=0, norm=norm))
    grid = [i / 100 for i in range(101)]
    assert min(grid, key=lambda c: loss(c, "l2")) == pytest.approx(0.25)
    assert min(grid, key=lambda c: loss(c, "l1")) == pytest.approx(0.0)


def test_to_space_maps_both_images_before_the_differences() -> None:
    gen = torch.Generator().manual_seed(2)
    a, b = torch.rand(2, 3, 6, 6, generator=gen), torch.rand(2, 3, 6, 6, generator=gen)
    mapped = denoising_loss(a, b, norm="l2", to_space=torch.sqrt)
    assert float(mapped) == pytest.approx(float(denoising_loss(a.sqrt(), b.sqrt(), norm="l2")), rel=1e-6)
    assert float(mapped) != pytest.approx(float(denoising_loss(a, b, norm="l2")), rel=1e-3)
