"""Training loss of Kim & Lee: 0.9 * L1 + 0.1 * L1 of image gradients, in transfer space.

``loss = 0.9 * mean|out - ref| + 0.1 * (mean|dx(out) - dx(ref)| + mean|dy(out) - dy(ref)|) / 2``
where ``dx``/``dy`` are forward differences along W/H over the valid pixels only (W-1 columns,
H-1 rows; no padded zeros). Inputs: NxCxHxW float tensors in transfer space.
"""
from __future__ import annotations

import torch

L1_WEIGHT = 0.9
GRADIENT_WEIGHT = 0.1


def gradient_l1(out: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean of the x- and y-gradient L1 distances (each a mean over its valid differences)."""
    diff = out - ref
    gx = (diff[..., :, 1:] - diff[..., :, :-1]).abs().mean() if diff.shape[-1] > 1 else diff.new_zeros(())
    gy = (diff[..., 1:, :] - diff[..., :-1, :]).abs().mean() if diff.shape[-2] > 1 else diff.new_zeros(())
    return 0.5 * (gx + gy)


def denoising_loss(out: torch.Tensor, ref: torch.Tensor, gradient_weight: float = GRADIENT_WEIGHT) -> torch.Tensor:
    """Scalar loss ``(1 - g) * L1 + g * gradient L1`` (both in transfer space), float32; the
    paper's ``g = 0.1`` by default, ``g = 0`` is plain L1."""
    if out.shape != ref.shape:
        raise ValueError(f"output shape {tuple(out.shape)} differs from reference shape {tuple(ref.shape)}")
    out, ref = out.float(), ref.float()
    l1 = (out - ref).abs().mean()
    return l1 if gradient_weight == 0 else (1.0 - gradient_weight) * l1 + gradient_weight * gradient_l1(out, ref)
