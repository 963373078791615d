"""Training loss of Kim & Lee: 0.9 * L1 + 0.1 * L1 of image gradients, in transfer space.

``loss = 0.9 * mean|out - ref| + 0.1 * (mean|dx(out) - dx(ref)| + mean|dy(out) - dy(ref)|) / 2``
where ``dx``/``dy`` are forward differences along W/H over the valid pixels only (W-1 columns,
H-1 rows; no padded zeros). Inputs: NxCxHxW float tensors in transfer space.

``log_eps`` > 0 replaces the mean over the batch by the mean over patches of
``log(patch loss + log_eps)``: each patch's gradient is weighted by ``1 / (its loss + eps)``, so a
patch of a 256-spp render, whose errors are ~20x smaller than a 1-spp one's, counts as much per
relative improvement. Validation scores the mean PSNR over images, a mean of logs of errors; the
plain mean lets the noisiest patches drive training.

``ms_ssim_weight`` m > 0 mixes in multi-scale SSIM (Wang et al. 2003) as Zhao et al. 2017 and
OIDN's training do: ``(1 - m) * loss + m * (1 - MS-SSIM)``, per patch, in transfer space (data
range 1; the PU curve is OIDN's choice of space too). SSIM uses an 11-px Gaussian window (sigma 1.5)
without padding; a patch of side P gets as many scales (at most 5, halving each time) as keep the
window inside it (28 px: 2, 64 px: 3, 128 px: 4), weighted by Wang's first weights renormalised.
Zhao's mix is m = 0.84 with ``gradient_weight`` 0.

``norm`` "l2" squares the differences of both terms instead of taking their absolute values: L1
trains for each pixel's conditional median, L2 for its mean, which is what PSNR (a mean squared
error) rewards; the two differ where the network cannot resolve a skewed, heavy-tailed signal.
``to_space``, when given, maps both images before the differences (e.g. the metric's display
tonemap of :meth:`model.transfer.TransferFunction.display`); MS-SSIM stays in transfer space.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F

L1_WEIGHT = 0.9
GRADIENT_WEIGHT = 0.1
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
SSIM_C1, SSIM_C2 = 0.01 ** 2, 0.03 ** 2  # data range 1
MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)  # Wang et al., finest scale first
_SSIM_FLOOR = 1e-4  # contrast terms are clamped to this before the fractional powers (finite gradients)


NORMS = {"l1": torch.abs, "l2": torch.square}  # --loss-norm: per-value error of both terms


def _gradient_error(diff: torch.Tensor, dims: tuple[int, ...],
                    error: Callable[[torch.Tensor], torch.Tensor] = torch.abs) -> torch.Tensor:
    gx = error(diff[..., :, 1:] - diff[..., :, :-1]).mean(dims) if diff.shape[-1] > 1 else diff.new_zeros(())
    gy = error(diff[..., 1:, :] - diff[..., :-1, :]).mean(dims) if diff.shape[-2] > 1 else diff.new_zeros(())
    return 0.5 * (gx + gy)


def ms_ssim_scales(size: int) -> int:
    """Scales of :func:`ms_ssim` for patches of side ``size``: as many as keep the SSIM window
    inside the patch at the coarsest one (at least 1, at most 5)."""
    return max(1, min(len(MS_SSIM_WEIGHTS), int(math.log2(max(size, 1) / SSIM_WINDOW)) + 1))


def _gaussian(channels: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    x = torch.arange(SSIM_WINDOW, dtype=torch.float64) - SSIM_WINDOW // 2
    g = torch.exp(-x * x / (2 * SSIM_SIGMA ** 2))
    g = (g / g.sum()).to(dtype)
    return g.view(1, 1, 1, -1).repeat(channels, 1, 1, 1), g.view(1, 1, -1, 1).repeat(channels, 1, 1, 1)


def _ssim_terms(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per patch (dim 0): the mean SSIM and the mean contrast-structure term over the valid
    window positions and the channels."""
    c = x.shape[1]
    gx, gy = _gaussian(c, x.dtype)

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(t, gx, groups=c), gy, groups=c)

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    cs = (2 * sxy + SSIM_C2) / (sxx + syy + SSIM_C2)
    luminance = (2 * mx * my + SSIM_C1) / (mx * mx + my * my + SSIM_C1)
    return (luminance * cs).mean((1, 2, 3)), cs.mean((1, 2, 3))


def ms_ssim(out: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Multi-scale SSIM of each NxCxPxP patch pair -> N values (1: identical), float32; the
    scales of :func:`ms_ssim_scales` with Wang's weights renormalised (module docstring)."""
    x, y = out.float(), ref.float()
    scales = ms_ssim_scales(min(x.shape[-2:]))
    weights = torch.tensor(MS_SSIM_WEIGHTS[:scales], dtype=torch.float64)
    weights = (weights / weights.sum()).tolist()
    value = x.new_ones(x.shape[0])
    for i, w in enumerate(weights):
        ssim, cs = _ssim_terms(x, y)
        term = ssim if i == scales - 1 else cs
        value = value * term.clamp(min=_SSIM_FLOOR) ** w
        if i < scales - 1:
            x, y = F.avg_pool2d(x, 2), F.avg_pool2d(y, 2)
    return value


def gradient_l1(out: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean of the x- and y-gradient L1 distances (each a mean over its valid differences)."""
    return _gradient_error(out - ref, tuple(range(out.dim())))


def denoising_loss(out: torch.Tensor, ref: torch.Tensor, gradient_weight: float = GRADIENT_WEIGHT,
                   log_eps: float = 0.0, ms_ssim_weight: float = 0.0, norm: str = "l1",
                   to_space: Callable[[torch.Tensor], torch.Tensor] | None = None) -> torch.Tensor:
    """Scalar loss ``(1 - g) * L1 + g * gradient L1`` (both in transfer space), float32; the
    paper's ``g = 0.1`` by default, ``g = 0`` is plain L1. ``ms_ssim_weight`` m > 0: that loss
    times ``1 - m`` plus ``m * (1 - MS-SSIM)`` (:func:`ms_ssim`). ``log_eps`` > 0: the mean over
    the batch's patches (dim 0) of ``log(that patch's loss + log_eps)`` (module docstring).
    ``norm`` "l2": squared instead of absolute differences in both terms; ``to_space``: a map of
    both images (float32) before the differences (module docstring)."""
    if out.shape != ref.shape:
        raise ValueError(f"output shape {tuple(out.shape)} differs from reference shape {tuple(ref.shape)}")
    if norm not in NORMS:
        raise ValueError(f"unknown loss norm {norm!r} (known: {', '.join(NORMS)})")
    error = NORMS[norm]
    a, b = out.float(), ref.float()
    if to_space is not None:
        a, b = to_space(a), to_space(b)
    diff = a - b
    per_patch = log_eps != 0 or ms_ssim_weight != 0
    dims = tuple(range(1, diff.dim())) if per_patch else tuple(range(diff.dim()))
    loss = error(diff).mean(dims)
    if gradient_weight != 0:
        loss = (1.0 - gradient_weight) * loss + gradient_weight * _gradient_error(diff, dims, error)
    if ms_ssim_weight != 0:
        loss = (1.0 - ms_ssim_weight) * loss + ms_ssim_weight * (1.0 - ms_ssim(out, ref))
    if log_eps != 0:
        return torch.log(loss + log_eps).mean()
    return loss.mean() if per_patch else loss
