"""The folded copy of a trained network that inference runs: :mod:`denoise.inference_net` for the
flat networks, :mod:`denoise.inference_unet` for the multi-scale ones."""
from __future__ import annotations

import torch
from torch import nn

from denoise.inference_net import InferenceNet
from denoise.inference_unet import InferenceUNet


def prepare_for_inference(model: nn.Module, dtype: torch.dtype = torch.float32) -> nn.Module:
    """A folded copy of a trained network for inference (equal up to float32 rounding; the
    original is left unchanged): :mod:`denoise.inference_net` or :mod:`denoise.inference_unet`,
    computing in ``dtype`` (:mod:`denoise.precision`; input and output stay float32)."""
    return InferenceUNet(model, dtype) if model.config.multiscale else InferenceNet(model, dtype)
