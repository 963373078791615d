"""One place that maps a :class:`ModelConfig` to its network, its alignment and its reach.

The flat networks (the paper's ``densenet`` and the ``plaincnn`` control) live in
:mod:`model.network`, the multi-scale ones (``dense_unet``, ``plain_unet``) in :mod:`model.unet`.
All take an NxCxHxW transfer-space image (:attr:`ModelConfig.image_channels`) and return Nx3xHxW.
"""
from __future__ import annotations

from torch import nn

from model import unet
from model.config import ModelConfig
from model.inference_net import InferenceNet
from model.inference_unet import InferenceUNet
from model.network import FlatDenseNet


def build_model(config: ModelConfig) -> nn.Module:
    """A freshly initialised (He init, current torch RNG) float32 model on the CPU."""
    return unet.MultiScaleDenoiser(config) if config.multiscale else FlatDenseNet(config)


def receptive_radius(config: ModelConfig) -> int:
    """Pixels on each side an output pixel may depend on (an upper bound for the multi-scale
    nets; for the flat ones exact: gradient 1 + 7x7 conv 3 + L + tail 1), plus the window the
    noise input averages the variance over."""
    reach = unet.receptive_radius(config) if config.multiscale else 1 + 3 + config.layers + 1
    return reach + (config.noise_radius if config.noise_input else 0)


def alignment(config: ModelConfig) -> int:
    """Tiles must start on multiples of this many pixels to reproduce the whole-image output."""
    return unet.alignment(config) if config.multiscale else 1


def prepare_for_inference(model: nn.Module) -> nn.Module:
    """A folded copy of a trained network for inference (equal up to float32 rounding; the
    original is left unchanged): :mod:`model.inference_net` or :mod:`model.inference_unet`."""
    return InferenceUNet(model) if model.config.multiscale else InferenceNet(model)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
