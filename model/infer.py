"""Whole-image inference with a trained network: the one chain every caller uses.

exposure (an image whose log-average luminance lies outside the training data's range is scaled
by a power of two towards the training median, undone at the end) -> sanitise (NaN/Inf/negative
-> 0, > HDR_MAX clamped) -> transfer -> network on core tiles with a margin of the receptive-field
radius (exact: :mod:`pipeline.tiling`) -> clamp to [0, 1] in transfer space (radiance 0..HDR_MAX,
so a wild output cannot overflow to Inf) -> inverse transfer -> undo the exposure. All of it tile
by tile: no whole-image temporaries besides the output.
Validation during training and :class:`pipeline.denoise.Denoiser` both call :func:`denoise_image`.
"""
from __future__ import annotations

import math
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


# Log-average luminance (geometric mean over pixels with luminance > 0; a firefly barely moves it)
# of the training references: data/train, 64 scenes, 4.6e-4 .. 2.25, median 0.085. Inside this band
# an image goes to the network as it is; outside, it is scaled by a power of two to near the median.
EXPOSURE_BAND = (2.5e-4, 4.0)
EXPOSURE_TARGET = 0.08
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def log_average_luminance(color: np.ndarray, rows: int = 256) -> float:
    """exp(mean(log L)) over the pixels of HxWx3 radiance whose luminance L is finite and > 0
    (0.0 if there are none); computed in row blocks, without a whole-image copy."""
    total, count = 0.0, 0
    for y in range(0, color.shape[0], rows):
        lum = np.asarray(color[y:y + rows], dtype=np.float64) @ _LUMINANCE
        lum = lum[np.isfinite(lum) & (lum > 0)]
        total, count = total + float(np.log(lum).sum()), count + lum.size
    return math.exp(total / count) if count else 0.0


def exposure_scale(color: np.ndarray) -> float:
    """Power of two to multiply HxWx3 radiance by before the network, and divide its output by:
    1.0 when the log-average luminance lies inside ``EXPOSURE_BAND`` (or the image is black).
    A power of two scales without rounding; a very bright image (mean 1e3, emitters beyond
    65504) is then not clamped, and a very dark one (mean 1e-4) is seen as the network knows it."""
    key = log_average_luminance(color)
    if key == 0.0 or EXPOSURE_BAND[0] <= key <= EXPOSURE_BAND[1]:
        return 1.0
    return 2.0 ** min(64, max(-64, round(math.log2(EXPOSURE_TARGET / key))))


def sanitize(color: np.ndarray) -> np.ndarray:
    """float32 copy of HxWxC radiance with NaN and negatives -> 0, +Inf and > HDR_MAX -> HDR_MAX."""
    return np.clip(np.nan_to_num(np.asarray(color, dtype=np.float32), nan=0.0, posinf=HDR_MAX,
                                 neginf=0.0), 0.0, HDR_MAX)


def denoise_image(model: Denoiser, color: np.ndarray, aux: np.ndarray | None = None,
                  core: int = 256, progress: Callable[[int, int], None] | None = None) -> np.ndarray:
    """Denoise HxWx3 linear radiance -> HxWx3 float32 linear radiance >= 0 (at most HDR_MAX divided
    by :func:`exposure_scale`, i.e. HDR_MAX unless the image is unusually bright).

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
    image = color  # sanitised and transferred tile by tile: no whole-image float64 temporaries
    if aux is not None:
        if aux.shape != color.shape[:2] + (6,):
            raise ValueError(f"aux must be HxWx6 like the image, got shape {aux.shape}")
        aux = np.nan_to_num(np.asarray(aux, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        image = np.concatenate([np.asarray(color, dtype=np.float32), aux], axis=2)
    scale = exposure_scale(color)

    def net(window: np.ndarray) -> np.ndarray:
        rgb = window[..., :3]
        if scale != 1.0:
            with np.errstate(over="ignore"):  # a huge value may overflow to Inf: sanitised below
                rgb = np.asarray(rgb, np.float32) * np.float32(scale)
        x = torch.cat([transfer.forward(torch.from_numpy(sanitize(rgb))),
                       torch.from_numpy(np.asarray(window[..., 3:], np.float32))], dim=2)
        y = model(x.permute(2, 0, 1).contiguous()[None])[0]
        out = transfer.inverse(torch.nan_to_num(y, nan=0.0).clamp(0.0, 1.0)).permute(1, 2, 0).numpy()
        return out if scale == 1.0 else out / np.float32(scale)

    was_training = model.training
    model.eval()
    try:
        with torch.inference_mode():
            out = run_tiled(net, image, core, receptive_radius(config), progress)
    finally:
        model.train(was_training)
    return out.astype(np.float32, copy=False)
