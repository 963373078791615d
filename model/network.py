"""The denoising networks: Kim & Lee's densely connected CNN and a parameter-matched plain CNN.

Both take an NCHW float32 image tensor in transfer space — RGB (+ albedo RGB in [0,1] + normal XYZ
in [-1,1] when ``aux_inputs``) — append the x/y gradient channels of the RGB, and return NCHW RGB
in transfer space (not clamped). Fully convolutional, no pooling: any H, W >= 1 works, alignment 1.
Receptive field radius: 3 (7x7 conv) + L (3x3 convs) + 1 (last conv) pixels.
"""
from __future__ import annotations

import torch
from torch import nn

from model.config import ModelConfig


def gradient_channels(rgb: torch.Tensor) -> torch.Tensor:
    """Forward differences of an NxCxHxW tensor: N x 2C x H x W = [d/dx (C), d/dy (C)].

    ``dx[..., x] = img[..., x+1] - img[..., x]``, zero in the last column; likewise ``dy`` along H,
    zero in the last row.
    """
    dx = torch.nn.functional.pad(rgb[..., :, 1:] - rgb[..., :, :-1], (0, 1, 0, 0))
    dy = torch.nn.functional.pad(rgb[..., 1:, :] - rgb[..., :-1, :], (0, 0, 0, 1))
    return torch.cat([dx, dy], dim=1)


def network_input(image: torch.Tensor) -> torch.Tensor:
    """Image tensor (RGB first, then aux) -> network input [RGB, dRGB/dx, dRGB/dy, aux]."""
    rgb = image[:, :3]
    return torch.cat([rgb, gradient_channels(rgb), image[:, 3:]], dim=1)


def _bn_relu_conv(cin: int, cout: int, kernel: int) -> list[nn.Module]:
    return [nn.BatchNorm2d(cin), nn.ReLU(inplace=True),
            nn.Conv2d(cin, cout, kernel, padding=kernel // 2, bias=False)]


class BottleneckLayer(nn.Module):
    """BN-ReLU-Conv1x1 (cin -> mid) - BN-ReLU-Conv3x3 (mid -> cout)."""

    def __init__(self, cin: int, mid: int, cout: int) -> None:
        super().__init__()
        self.body = nn.Sequential(*_bn_relu_conv(cin, mid, 1), *_bn_relu_conv(mid, cout, 3))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body(x)


class DenseBlock(nn.Module):
    """L bottleneck layers; each one's k output channels are concatenated to its input."""

    def __init__(self, cin: int, layers: int, growth: int, bottleneck: int) -> None:
        super().__init__()
        self.layers = nn.ModuleList(
            BottleneckLayer(cin + i * growth, bottleneck * growth, growth) for i in range(layers))
        self.out_channels = cin + layers * growth

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self.layers:
            x = torch.cat([x, layer(x)], dim=1)
        return x


class PlainStack(nn.Module):
    """L bottleneck layers of constant width, chained without concatenation or skips."""

    def __init__(self, width: int, layers: int, mid: int) -> None:
        super().__init__()
        self.layers = nn.Sequential(*(BottleneckLayer(width, mid, width) for _ in range(layers)))
        self.out_channels = width

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layers(x)


class FlatDenseNet(nn.Module):
    """7x7 conv (+BN, ReLU) -> body -> BN-ReLU-Conv3x3 -> RGB, plus the residual input if asked.

    Input: Nx3xHxW (or Nx9xHxW with aux) float32 in transfer space. Output: Nx3xHxW transfer-space
    RGB — the clean image (``output="direct"``) or input RGB + predicted correction (``"residual"``).
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        width = config.init_features if config.arch == "densenet" else plain_width(config)
        self.head = nn.Sequential(nn.Conv2d(config.in_channels, width, 7, padding=3, bias=False),
                                  nn.BatchNorm2d(width), nn.ReLU(inplace=True))
        mid = config.bottleneck * config.growth
        if config.arch == "densenet":
            self.body: nn.Module = DenseBlock(width, config.layers, config.growth, config.bottleneck)
        else:
            self.body = PlainStack(width, config.layers, mid)
        self.tail = nn.Sequential(*_bn_relu_conv(self.body.out_channels, 3, 3))
        init_weights(self)
        if config.output == "residual":
            # The correction starts at zero: the untrained model is the identity (the noisy input),
            # not a He-scaled random image that the log transfer would blow up to ~1e4 radiance.
            nn.init.zeros_(self.tail[-1].weight)

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        out = self.tail(self.body(self.head(network_input(image))))
        return out + image[:, :3] if self.config.output == "residual" else out


def init_weights(module: nn.Module) -> None:
    """He (kaiming normal, fan_in, ReLU) init for convs; BN weight 1, bias 0."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_in", nonlinearity="relu")
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)


def _plain_params(config: ModelConfig, width: int) -> int:
    mid = config.bottleneck * config.growth
    head = config.in_channels * 49 * width + 2 * width
    layer = 2 * width + width * mid + 2 * mid + 9 * mid * width
    return head + config.layers * layer + 2 * width + 9 * width * 3


def densenet_params(config: ModelConfig) -> int:
    """Trainable parameters of the densenet with this config's sizes (BN affine included)."""
    k, mid, c0 = config.growth, config.bottleneck * config.growth, config.init_features
    total = config.in_channels * 49 * c0 + 2 * c0
    for i in range(config.layers):
        cin = c0 + i * k
        total += 2 * cin + cin * mid + 2 * mid + 9 * mid * k
    cout = c0 + config.layers * k
    return total + 2 * cout + 9 * cout * 3


def plain_width(config: ModelConfig) -> int:
    """Constant width of the plain CNN whose parameter count is closest to the densenet's."""
    target = densenet_params(config)
    return min(range(1, 4097), key=lambda w: abs(_plain_params(config, w) - target))
