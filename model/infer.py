"""Whole-image inference with a trained network: the one chain every caller uses.

sanitise (NaN/Inf/negative -> 0, > HDR_MAX clamped) -> transfer -> network on core tiles with a
margin of the receptive-field radius (exact: :mod:`pipeline.tiling`) -> clamp to [0, 1] in transfer
space (radiance 0..HDR_MAX, so a wild output cannot overflow to Inf) -> inverse transfer.
Validation during training and :class:`pipeline.denoise.Denoiser` both call :func:`denoise_image`.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from model.config import ModelConfig
from model.network import Denoiser
from model.transfer import HDR_MAX, get_transfer
from pipeline.tiling import run_tiled


def receptive_radius(config: ModelConfig) -> int:
    """Pixels on each side an output pixel depends on: gradient 1 + 7x7 conv 3 + L + tail 1."""
    return 1 + 3 + config.layers + 1


def sanitize(color: np.ndarray) -> np.ndarray:
    """float32 copy of HxWxC radiance with NaN and negatives -> 0, +Inf and > HDR_MAX -> HDR_MAX."""
    return np.clip(np.nan_to_num(np.asarray(color, dtype=np.float32), nan=0.0, posinf=HDR_MAX,
                                 neginf=0.0), 0.0, HDR_MAX)


def denoise_image(model: Denoiser, color: np.ndarray, aux: np.ndarray | None = None,
                  core: int = 256, progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Denoise HxWx3 linear radiance -> HxWx3 float32 linear radiance in [0, HDR_MAX].

    ``aux``: HxWx6 (albedo RGB in [0,1], normal XYZ in [-1,1]); required iff the model was built
    with ``aux_inputs``. ``core``: tile core side in pixels (memory bound; the result does not
    depend on it). The model runs in eval mode; its previous mode is restored.
    """
    config = model.config
    if config.aux_inputs != (aux is not None):
        raise ValueError("aux buffers are required by this model" if config.aux_inputs
                         else "this model takes no aux buffers")
    if color.ndim != 3 or color.shape[2] != 3 or min(color.shape[:2]) < 1:
        raise ValueError(f"color must be HxWx3, got shape {color.shape}")
    transfer = get_transfer(config.transfer)
    planes = [transfer.forward(torch.from_numpy(sanitize(color))).numpy()]
    if aux is not None:
        if aux.shape != color.shape[:2] + (6,):
            raise ValueError(f"aux must be HxWx6 like the image, got shape {aux.shape}")
        planes.append(np.nan_to_num(np.asarray(aux, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0))
    encoded = np.concatenate(planes, axis=2)

    def net(window: np.ndarray) -> np.ndarray:
        x = torch.from_numpy(np.ascontiguousarray(window.transpose(2, 0, 1)))[None]
        return model(x)[0].numpy().transpose(1, 2, 0)

    was_training = model.training
    model.eval()
    try:
        with torch.inference_mode():
            out = run_tiled(net, encoded, core, receptive_radius(config), progress)
    finally:
        model.train(was_training)
    out = torch.from_numpy(np.ascontiguousarray(out))
    radiance = transfer.inverse(torch.nan_to_num(out, nan=0.0).clamp(0.0, 1.0))
    return radiance.numpy().astype(np.float32, copy=False)
