"""Training loss of Kim & Lee: 0.9 * L1 + 0.1 * L1 of image gradients, in transfer space.

``loss = 0.9 * mean|out - ref| + 0.1 * (mean|dx(out) - dx(ref)| + mean|dy(out) - dy(ref)|) / 2``
where ``dx``/``dy`` are forward differences along W/H over the valid pixels only (W-1 columns,
H-1 rows; no padded zeros). Inputs: NxCxHxW float tensors in transfer space.

``log_eps`` > 0 replaces the mean over the batch by the mean over patches of
``log(patch loss + log_eps)``: each patch's gradient is weighted by ``1 / (its loss + eps)``, so a
patch of a 256-spp render, whose errors are ~20x smaller than a 1-spp one's, counts as much per
relative improvement. Validation scores the mean PSNR over images, a mean of logs of errors; the
plain mean lets the noisiest patches drive training.
"""
from __future__ import annotations

import torch

L1_WEIGHT = 0.9
GRADIENT_WEIGHT = 0.1


def _gradient_l1(diff: torch.Tensor, dims: tuple[int, ...]) -> torch.Tensor:
    gx = (diff[..., :, 1:] - diff[..., :, :-1]).abs().mean(dims) if diff.shape[-1] > 1 else diff.new_zeros(())
    gy = (diff[..., 1:, :] - diff[..., :-1, :]).abs().mean(dims) if diff.shape[-2] > 1 else diff.new_zeros(())
    return 0.5 * (gx + gy)


def gradient_l1(out: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean of the x- and y-gradient L1 distances (each a mean over its valid differences)."""
    return _gradient_l1(out - ref, tuple(range(out.dim())))


def denoising_loss(out: torch.Tensor, ref: torch.Tensor, gradient_weight: float = GRADIENT_WEIGHT,
                   log_eps: float = 0.0) -> torch.Tensor:
    """Scalar loss ``(1 - g) * L1 + g * gradient L1`` (both in transfer space), float32; the
    paper's ``g = 0.1`` by default, ``g = 0`` is plain L1. ``log_eps`` > 0: the mean over the
    batch's patches (dim 0) of ``log(that patch's loss + log_eps)`` (module docstring)."""
    if out.shape != ref.shape:
        raise ValueError(f"output shape {tuple(out.shape)} differs from reference shape {tuple(ref.shape)}")
    diff = out.float() - ref.float()
    dims = tuple(range(diff.dim())) if log_eps == 0 else tuple(range(1, diff.dim()))
    loss = diff.abs().mean(dims)
    if gradient_weight != 0:
        loss = (1.0 - gradient_weight) * loss + gradient_weight * _gradient_l1(diff, dims)
    return loss if log_eps == 0 else torch.log(loss + log_eps).mean()
