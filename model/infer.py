"""Whole-image inference with a trained :class:`~model.network.Denoiser` (used by validation).

Chain: sanitise (NaN -> 0, clamp to [0, HDR_MAX]) -> transfer -> model on overlapping tiles ->
clamp to [0, 1] in transfer space (i.e. radiance 0..HDR_MAX, so a wild output of an early model
cannot overflow to Inf) -> inverse transfer. Tiles overlap by the network's receptive-field radius and only
their centres are kept, so in eval mode the result equals a single whole-image pass exactly
(up to float summation order) while memory stays bounded by the tile size.
"""
from __future__ import annotations

import numpy as np
import torch

from model.network import Denoiser
from model.transfer import HDR_MAX, get_transfer


def receptive_radius(model: Denoiser) -> int:
    """Pixels on each side an output pixel depends on: gradient 1 + 7x7 conv 3 + L + tail 1."""
    return 1 + 3 + model.config.layers + 1


@torch.no_grad()
def forward_tiled(model: Denoiser, image: torch.Tensor, tile: int = 256) -> torch.Tensor:
    """Model output for a 1xCxHxW transfer-space tensor, computed tile by tile (``tile`` px)."""
    _, _, h, w = image.shape
    margin = receptive_radius(model)
    out = image.new_empty((1, 3, h, w))
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            ya, xa = max(y0 - margin, 0), max(x0 - margin, 0)
            yb, xb = min(y1 + margin, h), min(x1 + margin, w)
            res = model(image[:, :, ya:yb, xa:xb])
            out[:, :, y0:y1, x0:x1] = res[:, :, y0 - ya:y1 - ya, x0 - xa:x1 - xa]
    return out


def denoise_image(model: Denoiser, color: np.ndarray, aux: np.ndarray | None = None,
                  tile: int = 256) -> np.ndarray:
    """Denoise HxWx3 float32 linear radiance -> HxWx3 float32 linear radiance in [0, HDR_MAX].

    ``aux``: HxWx6 (albedo RGB in [0,1], normal XYZ in [-1,1]); required iff the model was built
    with ``aux_inputs``. The model is run in eval mode; its previous mode is restored.
    """
    config = model.config
    if config.aux_inputs != (aux is not None):
        raise ValueError("aux buffers are required by this model" if config.aux_inputs
                         else "this model takes no aux buffers")
    if color.ndim != 3 or color.shape[2] != 3:
        raise ValueError(f"color must be HxWx3, got shape {color.shape}")
    transfer = get_transfer(config.transfer)
    rgb = np.clip(np.nan_to_num(color.astype(np.float32), nan=0.0, posinf=HDR_MAX, neginf=0.0), 0.0, HDR_MAX)
    planes = [transfer.forward(torch.from_numpy(rgb))]
    if aux is not None:
        planes.append(torch.from_numpy(np.nan_to_num(aux.astype(np.float32))))
    image = torch.cat(planes, dim=-1).permute(2, 0, 1).unsqueeze(0).contiguous()
    was_training = model.training
    model.eval()
    try:
        out = forward_tiled(model, image, tile)
    finally:
        model.train(was_training)
    radiance = transfer.inverse(torch.nan_to_num(out, nan=0.0).clamp(0.0, 1.0))
    return radiance[0].permute(1, 2, 0).contiguous().numpy()
