"""What the network is told about a render's noise: four channels made from its variance.

A render made of two independent halves carries, per pixel and channel, an estimate ``V`` of the
variance of its mean (:func:`rendering.render.half_variance`; a variance layer of an EXR is the
same thing). The network works in transfer space, so it is told how far one standard deviation
moves each channel there::

    noise_c = T(x_c + sqrt(V_c)) - T(x_c)     (x: the noisy radiance, T: the transfer function)

which is 0 where the render has converged, and in the units of the RGB it sees. The fourth
channel is 1 where the variance is known and 0 where it is not (a single EXR without halves, a
1-spp render): then the three noise channels are 0 as well, and the model falls back to RGB alone
(it is trained with the noise channels dropped on a share of its patches, ``TrainConfig.noise_dropout``).

Per-pixel estimates from two halves have one degree of freedom each; with ``ModelConfig.noise_radius``
the variance is averaged over a small window first, which gives a local noise level instead.

Layout: HxWx4 float32 (noise R, G, B, known flag), or Nx4xHxW for tensors.
"""
from __future__ import annotations

import numpy as np
import torch
from torch.nn import functional as F

from model.transfer import HDR_MAX, TransferFunction


def noise_channels(color: np.ndarray, variance: np.ndarray | None, transfer: TransferFunction,
                   radius: int = 0, encoded: torch.Tensor | None = None) -> np.ndarray:
    """HxWx4 float32 noise channels of HxWx3 sanitised radiance ``color`` (finite, >= 0) and its
    HxWx3 variance estimate (NaN -> 0, +Inf -> the largest radiance; None: unknown -> all 0).

    ``radius`` > 0: the variance is averaged over a (2r+1)^2 window first (cut at the borders),
    so a pixel's channel tells the local noise level rather than its own one-degree-of-freedom
    estimate (an output pixel then depends on inputs up to ``radius`` pixels further away).
    ``encoded``: ``transfer.forward`` of ``color`` (HxWx3) when the caller has it already.
    """
    h, w = color.shape[:2]
    out = np.zeros((h, w, 4), np.float32)
    if variance is None:
        return out
    var = np.clip(np.nan_to_num(np.asarray(variance, np.float32), nan=0.0, posinf=HDR_MAX * HDR_MAX,
                                neginf=0.0), 0.0, HDR_MAX * HDR_MAX)
    if radius > 0:
        planes = torch.from_numpy(np.ascontiguousarray(var.transpose(2, 0, 1), np.float64))[None]
        var = F.avg_pool2d(planes, 2 * radius + 1, stride=1, padding=radius,
                           count_include_pad=False)[0].permute(1, 2, 0).numpy()
    sigma = np.sqrt(var).astype(np.float32)
    if encoded is None:
        encoded = transfer.forward(torch.from_numpy(np.ascontiguousarray(color, np.float32)))
    upper = torch.from_numpy(np.minimum(np.asarray(color, np.float32) + sigma, HDR_MAX))
    out[..., :3] = (transfer.forward(upper) - encoded).clamp(min=0.0).numpy()
    out[..., 3] = 1.0
    return out


def drop_noise(batch: np.ndarray, start: int, rate: float, rng: np.random.Generator) -> None:
    """In place: for a share ``rate`` of the NxPxPxC patches, zero the 4 noise channels that
    begin at channel ``start`` (the model then sees them as unknown)."""
    if rate <= 0:
        return
    drop = rng.random(len(batch)) < rate
    batch[drop, :, :, start:start + 4] = 0.0
