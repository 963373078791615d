"""One place that maps a :class:`ModelConfig` to its network, its alignment and its reach.

The flat networks (the paper's ``densenet`` and the ``plaincnn`` control) live in
:mod:`model.network`, the multi-scale ones (``dense_unet``, ``plain_unet``) in :mod:`model.unet`.
All take an NxCxHxW transfer-space image (:attr:`ModelConfig.image_channels`) and return Nx3xHxW.
"""
from __future__ import annotations

import torch
from torch import nn

from model import unet
from model.aux_input import KERNEL_HIDDEN
from model.config import AUX_CHANNELS, ModelConfig
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


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


# Resident bytes of a forward pass per byte of the tensors live_channels_per_pixel counts: oneDNN's
# reordered weights and workspaces, the allocator's slack (with denoise/allocator.py's fixed mmap
# threshold), and for the training modules
# their BatchNorm copies and concatenations. A bound of what benchmarks/denoise_memory.py --parts
# calibrate measures (results/denoise_memory.json).
# Measured on the shipped networks in a warm process (windows of 544x672 to 720x960, float32 and
# bfloat16): 0.81-0.99 of the folded estimate.
FOLDED_ALLOWANCE = 1.1
MODULE_ALLOWANCE = 1.6


def inference_bytes_per_pixel(config: ModelConfig, folded: bool = True, itemsize: int = 4) -> float:
    """Peak resident bytes per input pixel of one forward pass of a tile, beyond a fixed cost
    (:data:`denoise.chain.TILE_FIXED_BYTES`): the folded network's live tensors
    (:func:`live_channels_per_pixel`) times the measured allowance of the folded network
    (``folded``) or of the training module. ``itemsize``: bytes per value of the folded network's
    activations (2 in bfloat16, :mod:`denoise.precision`); the channels of
    :func:`float32_channels_per_pixel` stay float32."""
    live = live_channels_per_pixel(config)
    wide = float32_channels_per_pixel(config)
    itemsize = itemsize if folded else 4
    return (4.0 * wide + itemsize * (live - wide)) * (FOLDED_ALLOWANCE if folded else MODULE_ALLOWANCE)


def float32_channels_per_pixel(config: ModelConfig) -> float:
    """Of :func:`live_channels_per_pixel`, those that stay float32 whatever the network computes
    in: the input image; for the multi-scale nets also the output's shuffled copy and its sum with
    the input, the chain's output bound beside the network (:func:`denoise.chain.neighbourhood_max`)
    and, with a head, the padded network input it reads."""
    if config.multiscale:
        return config.image_channels + 7 + (config.in_channels if config.head else 0)
    return config.image_channels


def live_channels_per_pixel(config: ModelConfig) -> float:
    """float32 channels per input pixel alive at the peak of one forward pass of the folded
    network (:func:`prepare_for_inference`), counted from its code: the input, the buffers a
    level keeps and the largest set of temporaries beside them (a layer's clamped input and
    bottleneck, a transition, the tail). Lower resolutions count their share of the pixels."""
    if config.multiscale:
        return _unet_live_channels(config)
    cimg, k, mid = config.image_channels, config.growth, config.bottleneck * config.growth
    inputs = cimg + 2 * config.in_channels + 12  # network_input's copies and gradient temporaries
    if config.arch == "densenet":
        c0 = config.init_features
        width = c0 + config.layers * k
        return max(inputs + c0, cimg + c0 + width + max(width - k + mid, mid + k, width + 6))
    from model.network import plain_width

    width = plain_width(config)
    return max(inputs + width, cimg + 3 * width + mid, cimg + 3 * width + 6)


def _unet_live_channels(config: ModelConfig) -> float:
    """:func:`live_channels_per_pixel` of the folded multi-scale nets (:mod:`denoise.inference_unet`)."""
    plan = unet._Widths(config, 1.0 if config.arch == "dense_unet" else unet.plain_width_scale(config))
    n, layers, cimg = config.levels, config.layers, config.image_channels
    share = [0.25 ** (i + 1) for i in range(n + 1)]
    inputs = cimg + 3 * config.in_channels + 12  # network_input, its padded copy, the unshuffled input
    # the input and the unshuffled input, kept until the skip conv (the padded input too for the head)
    base = cimg + config.in_channels * (2 if config.head else 1)
    if config.arch == "dense_unet":
        enc = [plan.width[i] + layers * plan.growth[i] for i in range(n + 1)]  # enc[n]: the bottom block
        kept = [enc[i] + plan.width[i] + layers * plan.growth[i] for i in range(n)] + [enc[n]]
        busy = [kept[i] - plan.growth[i] + plan.mid[i] for i in range(n + 1)]  # a layer's clamp + bottleneck
    else:
        kept = plan.width[:n] + [plan.width[n]]  # the encoder outputs kept for the skips, the bottom
        busy = [2 * plan.width[i] * 3 + plan.mid[i] for i in range(n + 1)]  # upsampled, concatenated, x, clamp
    body = base + sum(c * s for c, s in zip(kept, share)) + max(b * s for b, s in zip(busy, share))
    taps = config.kernel_taps  # the predicted filter's coefficients per pixel
    mode = config.aux_mode if config.aux_inputs else None
    if mode == "levels":  # the buffers at every level, kept from the start (model.aux_input)
        body += 4 * AUX_CHANNELS * share[0] + AUX_CHANNELS * sum(share[1:])
    branch = 2 * KERNEL_HIDDEN + 4 * taps if mode == "kernel" else 0  # its hidden layer's two parts, output
    # the tail, the other levels dropped: level 0's buffer and its BN-ReLU copy, two 12-channel convs
    # and the coefficients at half resolution (and the kernel branch's), the output and its sum with the input
    tail = base + (2 * kept[0] + 24 + 4 * taps + branch) * share[0] + 6
    # the prefilter: the filtered copy of the input beside it, and its full-resolution temporaries
    prefilter = 2 * cimg + 6 * AUX_CHANNELS if config.aux_inputs and config.aux_prefilter != "none" else 0
    # the head: the output, its input (output and network input, concatenated and a channels_last
    # copy), its hidden channels and its output, beside the network input and the output
    head = base + 3 + 2 * (3 + config.in_channels) + config.head + 3 if config.head else 0
    # the filter: the outputs and the coefficients at half resolution (model.unet.add_kernel_ works a
    # band of rows at a time: its temporaries are a few rows')
    kernel = cimg + 6 + taps * share[0] * 4 if taps else 0
    return max(inputs, body, tail, head, kernel, prefilter)
