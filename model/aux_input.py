"""What a multi-scale denoiser does with its albedo and normal buffers (``ModelConfig.aux_mode``,
``aux_prefilter``); the modules and helpers that :mod:`model.unet` and its folded copy share.

The image tensor carries albedo RGB in [0,1] and normal XYZ in [-1,1] in channels 3:9
(:attr:`ModelConfig.image_channels`); the network input (:func:`model.network.network_input`)
carries them in channels 9:15, after RGB and its gradients. Where they go:

* ``stem``: with everything else into the stem conv and the input skip conv (both read the 2x2
  unshuffle of the whole network input). The two convs each run as one conv on the unshuffled
  RGB part and one on the unshuffled buffers, summed, so a net whose buffer weights are zero
  computes exactly what the RGB net computes (:func:`model.grow.grow_model`).
* ``noskip``: the same stem; the skip conv reads the RGB part only.
* ``levels``: neither the stem nor the skip. At the input of every encoder block and of the bottom
  block, a 3x3 conv of the buffers at that level's resolution is added to the features: at level
  0 (half resolution) of their 2x2 unshuffle (24 channels, as the stem would see them), at level
  i > 0 of their averages over 2^(i+1) x 2^(i+1) cells (6 channels). The convs start at zero.
* ``kernel``: only the predicted filter's coefficients (``ModelConfig.kernel``): a hidden layer
  ReLU(conv1x1 of the tail's BN-ReLU features + conv3x3 of the buffers' 2x2 unshuffle + bias),
  :data:`KERNEL_HIDDEN` channels at half resolution, and a conv1x1 of it (zero at the start) added
  to the coefficients: the buffers decide where the filter's weights go, as in a cross-bilateral
  filter or a kernel-predicting network, and never enter the colour path.

``aux_prefilter="bilateral"`` replaces both buffers, inside the network, by a joint bilateral
filter of them (:func:`prefilter`) before any of this: a fixed function, no weights.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from model.config import AUX_CHANNELS, ModelConfig

KERNEL_HIDDEN = 32  # hidden channels of the ``kernel`` mode's branch
# The bilateral prefilter: a (2r+1)^2 window; weights exp(-|da|^2 / (2 sa^2) - |dn|^2 / (2 sn^2)
# - |o|^2 / (2 so^2)) of a neighbour o whose albedo differs by da and normal by dn.
PREFILTER_RADIUS = 2
PREFILTER_SIGMA_ALBEDO = 0.1  # albedo in [0,1]: two materials 0.2 apart weigh e^-2 per channel
PREFILTER_SIGMA_NORMAL = 0.2  # unit normals 12 degrees apart weigh e^-0.5
PREFILTER_SIGMA_SPACE = 2.0  # pixels


def aux_columns(config: ModelConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """(RGB-part, buffer) channel indices of the 2x2 unshuffle of ``config``'s whole network input,
    in :func:`torch.nn.functional.pixel_unshuffle`'s order (input channel c -> 4c .. 4c + 3): the
    columns of a ``stem``-mode stem or skip weight that the RGB part and the buffers meet."""
    first = 4 * 9  # RGB and its 6 gradient channels come first
    aux = torch.arange(first, first + 4 * AUX_CHANNELS)
    main = torch.cat([torch.arange(first), torch.arange(first + 4 * AUX_CHANNELS, 4 * config.in_channels)])
    return main, aux


def widen_weight(weight: torch.Tensor, config: ModelConfig, part: str = "main") -> torch.Tensor:
    """A conv weight over the unshuffled RGB part (``part="main"``: all but the buffers) or over
    the unshuffled buffers alone (``"aux"``) as one over the whole unshuffled network input,
    zero on the other columns: the same function of the whole input."""
    columns = aux_columns(config)[part == "aux"]
    out = weight.new_zeros(weight.shape[0], 4 * config.in_channels, *weight.shape[2:])
    out[:, columns] = weight
    return out


def split_input(net_in: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A network input (RGB, gradients, buffers, noise) as (everything but the buffers, the buffers)."""
    return torch.cat([net_in[:, :9], net_in[:, 9 + AUX_CHANNELS:]], dim=1), net_in[:, 9:9 + AUX_CHANNELS]


def _edge_padded(x: torch.Tensor, r: int) -> torch.Tensor:
    """``x`` (NxCxHxW) with ``r`` pixels around it repeating its edge (any size, 1x1 too)."""
    h, w = x.shape[-2:]
    return x[..., torch.arange(-r, h + r).clamp(0, h - 1), :][..., torch.arange(-r, w + r).clamp(0, w - 1)]


@torch.no_grad()
def prefilter(aux: torch.Tensor, radius: int = PREFILTER_RADIUS) -> torch.Tensor:
    """A joint bilateral filter of Nx6xHxW albedo (channels 0:3) and normals (3:6), each guided by
    both: ``x(p) + sum_o w_o (x(p+o) - x(p)) / (1 + sum_o w_o)`` over the (2r+1)^2 - 1 neighbours
    o (beyond the edge the edge's pixels), ``w_o`` as the module's constants say; the centre
    weighs 1. Float32; an input where the buffers are constant comes back unchanged (exactly), and
    a step between two materials much further apart than the sigmas stays a step."""
    x = aux.float()
    h, w = x.shape[-2:]
    padded = _edge_padded(x, radius)
    inv_a, inv_n = 0.5 / PREFILTER_SIGMA_ALBEDO ** 2, 0.5 / PREFILTER_SIGMA_NORMAL ** 2
    total = torch.zeros_like(x)
    weights = torch.ones_like(x[:, :1])
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if not (dy or dx):
                continue
            d = padded[..., radius + dy:radius + dy + h, radius + dx:radius + dx + w] - x
            sq = d * d
            distance = sq[:, :3].sum(1, keepdim=True) * inv_a + sq[:, 3:].sum(1, keepdim=True) * inv_n
            weight = torch.exp(-(distance + (dy * dy + dx * dx) * (0.5 / PREFILTER_SIGMA_SPACE ** 2)))
            total.addcmul_(weight, d)
            weights += weight
    return x + total / weights


def prefiltered(image: torch.Tensor) -> torch.Tensor:
    """The image tensor with its buffers (channels 3:9) replaced by :func:`prefilter`'s output."""
    return torch.cat([image[:, :3], prefilter(image[:, 3:9]).to(image.dtype), image[:, 9:]], dim=1)


def pooled_buffers(aux: torch.Tensor, levels: int) -> list[torch.Tensor]:
    """The buffers at the resolution of levels 1 .. ``levels`` for ``levels`` mode: the averages of
    ``aux`` (Nx6xHxW, padded to the alignment) over 2^(i+1) x 2^(i+1) cells (level 0 reads
    their 2x2 unshuffle instead)."""
    return [F.avg_pool2d(aux, 2 ** (i + 1)) for i in range(1, levels + 1)]


@torch.no_grad()
def _zero(conv: nn.Conv2d) -> None:
    conv.weight.zero_()
    if conv.bias is not None:
        conv.bias.zero_()


class LevelInjection(nn.Module):
    """``levels`` mode: per level i (0 .. levels, the last the bottom block) a 3x3 conv of the
    level's buffers (level 0: their 2x2 unshuffle; :func:`pooled_buffers`) -> ``widths[i]``
    channels, no bias, starting at zero."""

    def __init__(self, widths: list[int]) -> None:
        super().__init__()
        self.convs = nn.ModuleList(nn.Conv2d(4 * AUX_CHANNELS if i == 0 else AUX_CHANNELS, width, 3, padding=1,
                                             bias=False) for i, width in enumerate(widths))
        self.start_at_zero()

    def start_at_zero(self) -> None:
        """Zero every conv: the branch adds nothing."""
        for conv in self.convs:
            _zero(conv)

    def forward(self, x: torch.Tensor, level: int, buffers: list[torch.Tensor]) -> torch.Tensor:
        """``x`` plus level ``level``'s conv of its buffers."""
        return x + self.convs[level](buffers[level])


class KernelBranch(nn.Module):
    """``kernel`` mode: ReLU(conv1x1(features) + conv3x3(unshuffled buffers) + b) -> conv1x1 -> the
    coefficients' correction (4 (k^2 - 1) channels, pixel-shuffled like the coefficients); the
    last conv starts at zero, the others He-initialised."""

    def __init__(self, features: int, taps: int) -> None:
        super().__init__()
        self.from_features = nn.Conv2d(features, KERNEL_HIDDEN, 1, bias=True)
        self.from_aux = nn.Conv2d(4 * AUX_CHANNELS, KERNEL_HIDDEN, 3, padding=1, bias=False)
        for conv in (self.from_features, self.from_aux):
            nn.init.kaiming_normal_(conv.weight, mode="fan_in", nonlinearity="relu")
        nn.init.zeros_(self.from_features.bias)
        self.out = nn.Conv2d(KERNEL_HIDDEN, 4 * taps, 1, bias=True)
        self.start_at_zero()

    def start_at_zero(self) -> None:
        """Zero the last conv: the branch adds nothing, and its hidden layer learns from the start."""
        _zero(self.out)

    def forward(self, features: torch.Tensor, raw_aux: torch.Tensor) -> torch.Tensor:
        return self.out(F.relu(self.from_features(features) + self.from_aux(raw_aux)))


def prefilter_reach(config: ModelConfig) -> int:
    """Pixels the prefilter adds to how far an output pixel looks (0 without one)."""
    return PREFILTER_RADIUS if config.aux_inputs and config.aux_prefilter != "none" else 0
