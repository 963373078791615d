"""The multi-scale denoisers: Kim & Lee's dense bottleneck layers arranged as an encoder/decoder.

A fully convolutional DenseNet in the spirit of Jegou et al. 2017 ("The One Hundred Layers
Tiramisu") and of OIDN's U-Net, built so that nothing heavy runs at full resolution::

    image (+ gradient channels, + noise channels)      H x W, Cin channels
    -> pixel-unshuffle 2 -> conv3x3 + BN + ReLU         H/2: the stem, w_0 channels
    -> encoder: for i < levels, block i (at 1/2^(i+1)), kept as skip i,
                then BN-ReLU-conv1x1 -> w_(i+1) and 2x2 average pooling
    -> bottom block (at 1/2^(levels+1))
    -> decoder: for i = levels-1 .. 0, BN-ReLU-conv1x1 -> w_i, nearest 2x upsampling,
                concatenated with skip i, block i
    -> BN-ReLU-conv3x3 of the last block + conv3x3 of the unshuffled input (so that every
       pixel's own value reaches the output) -> 12 channels -> pixel-shuffle 2 -> RGB (H x W)
    (+ the input RGB for ``output="residual"``)
    -> with ``head`` > 0, a full-resolution refinement: conv3x3 of [that output, the network input]
       -> ``head`` channels -> ReLU -> conv3x3 -> 3, added to it (the only nonlinearity at full
       resolution; its last conv starts at zero, so it starts as the network without it)
    -> with ``kernel`` k > 0, a predicted filter: a conv1x1 of the tail's BN-ReLU features gives,
       per full-resolution pixel p (pixel-shuffled like the output), k*k - 1 coefficients a_o, and
       sum_o a_o(p) (x(p + o) - x(p)) over the k x k neighbours o of p is added to the output, x the
       input RGB: a per-pixel filter of the input whose weights sum to 1 (kernel-predicting
       denoisers, Bako et al. 2017, without their softmax, so that it starts at zero: the
       coefficients' conv starts at zero and the network starts as the one without it)

With albedo and normal inputs, ``aux_mode`` says which of these steps read them and
``aux_prefilter`` what is done to them first (:mod:`model.aux_input`).

A *block* is ``layers`` of the paper's bottleneck layers (BN-ReLU-Conv1x1-BN-ReLU-Conv3x3), their
outputs concatenated (``dense_unet``), or, for the science table's plain network
(``plain_unet``), the same layers chained at a constant width without concatenation, widths
scaled so that it costs as many MACs per pixel as the dense one. Level i (i = 0 .. levels) has
width ``w_i = round(init_features * (1 + i/2))`` and growth ``k_i = round(growth * (1 + i/2))``:
the deeper levels are cheap (1/4 of the pixels per level), so they get more channels.

Any H, W >= 1: the input is padded at the bottom and right by replicating its last row/column
up to a multiple of :func:`alignment` and the output cropped back. BatchNorm in eval mode is a
per-channel affine map, so the network is translation-equivariant on the alignment grid:
:func:`receptive_radius` bounds how far an output pixel looks, and tiles cut on the grid with that
margin reproduce the whole-image output (:mod:`denoise.tiling`).
"""
from __future__ import annotations

import dataclasses
import functools
import math

import torch
from torch import nn
from torch.nn import functional as F

from model import aux_input
from model.config import ModelConfig
from model.network import BottleneckLayer, init_weights, network_input


def level_width(config: ModelConfig, level: int) -> int:
    """Channels entering the encoder block of ``level`` (the stem's width at level 0)."""
    return round(config.init_features * (1 + level / 2))


def level_growth(config: ModelConfig, level: int) -> int:
    """Growth rate of the blocks at ``level``."""
    return round(config.growth * (1 + level / 2))


def alignment(config: ModelConfig) -> int:
    """Input sides are padded to a multiple of this: 2^(levels+1)."""
    return 2 ** (config.levels + 1)


class Block(nn.Module):
    """``layers`` bottleneck layers at one resolution: dense (outputs concatenated to the input)
    or plain (chained at the input's width). ``out_channels`` is what it returns."""

    def __init__(self, cin: int, layers: int, growth: int, bottleneck: int, dense: bool,
                 plain_mid: int = 0) -> None:
        super().__init__()
        self.dense = dense
        if dense:
            self.layers = nn.ModuleList(BottleneckLayer(cin + i * growth, bottleneck * growth, growth)
                                        for i in range(layers))
            self.out_channels = cin + layers * growth
        else:
            self.layers = nn.ModuleList(BottleneckLayer(cin, plain_mid, cin) for _ in range(layers))
            self.out_channels = cin

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for layer in self.layers:
            x = torch.cat([x, layer(x)], dim=1) if self.dense else layer(x)
        return x


def _bn_relu_conv1x1(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(nn.BatchNorm2d(cin), nn.ReLU(inplace=True), nn.Conv2d(cin, cout, 1, bias=False))


class _Widths:
    """Channel plan of a multi-scale net: per level the block input width, growth, plain width."""

    def __init__(self, config: ModelConfig, plain_scale: float = 1.0) -> None:
        dense = config.arch == "dense_unet"
        n = config.levels
        self.width = [level_width(config, i) for i in range(n + 1)]
        self.growth = [level_growth(config, i) for i in range(n + 1)]
        if not dense:  # plain: constant width per block, scaled to the dense net's cost
            self.width = [max(1, round(w * plain_scale)) for w in self.width]
        self.mid = [config.bottleneck * k for k in self.growth]


class MultiScaleDenoiser(nn.Module):
    """The encoder/decoder network of this module's docstring (``dense_unet`` or ``plain_unet``).

    Input: NxCxHxW float32 image in transfer space (RGB, then aux, then noise channels, as
    :attr:`ModelConfig.image_channels`). Output: Nx3xHxW transfer-space RGB.
    """

    def __init__(self, config: ModelConfig, plain_scale: float | None = None) -> None:
        super().__init__()
        if not config.multiscale:
            raise ValueError(f"{config.arch} is not a multi-scale arch")
        self.config = config
        dense = config.arch == "dense_unet"
        if plain_scale is None:
            plain_scale = 1.0 if dense else plain_width_scale(config)
        plan = _Widths(config, plain_scale)
        n, layers = config.levels, config.layers
        w = plan.width
        self.stem = nn.Sequential(nn.Conv2d(4 * config.stem_channels, w[0], 3, padding=1, bias=False),
                                  nn.BatchNorm2d(w[0]),
                                  nn.ReLU(inplace=True))

        def block(cin: int, level: int) -> Block:
            return Block(cin, layers, plan.growth[level], config.bottleneck, dense, plan.mid[level])

        self.enc = nn.ModuleList()
        self.down = nn.ModuleList()
        for i in range(n):
            self.enc.append(block(w[i], i))
            self.down.append(_bn_relu_conv1x1(self.enc[i].out_channels, w[i + 1]))
        self.bottom = block(w[n], n)
        self.up = nn.ModuleList()
        self.dec = nn.ModuleList()
        below = self.bottom.out_channels
        for i in reversed(range(n)):
            self.up.append(_bn_relu_conv1x1(below, w[i]))
            self.dec.append(block(w[i] + self.enc[i].out_channels, i))
            below = self.dec[-1].out_channels
        self.tail_bn = nn.BatchNorm2d(below)
        self.tail = nn.Conv2d(below, 12, 3, padding=1, bias=False)
        self.skip = nn.Conv2d(4 * config.skip_channels, 12, 3, padding=1, bias=True)
        init_weights(self)
        if config.output == "residual":
            # the correction starts at zero: the untrained model is the identity
            nn.init.zeros_(self.tail.weight)
            nn.init.zeros_(self.skip.weight)
        nn.init.zeros_(self.skip.bias)
        self.head = make_head(config)
        self.kernel = None
        if config.kernel:
            self.kernel = nn.Conv2d(below, 4 * config.kernel_taps, 1, bias=True)
            nn.init.zeros_(self.kernel.weight)
            nn.init.zeros_(self.kernel.bias)
        mode = config.aux_mode if config.aux_inputs else None
        self.aux_levels = aux_input.LevelInjection(w) if mode == "levels" else None
        self.aux_kernel = aux_input.KernelBranch(below, config.kernel_taps) if mode == "kernel" else None
        # the columns of a stem or skip weight reading both (``stem``, ``noskip``) that the RGB part
        # and the buffers meet
        self.aux_columns = aux_input.aux_columns(config) if config.aux_inputs else None

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        h, w = image.shape[-2:]
        if self.config.aux_inputs and self.config.aux_prefilter != "none":
            image = aux_input.prefiltered(image)
        net_in = network_input(image)
        raw_aux, levels = None, None
        if self.config.aux_inputs:
            raw, raw_aux, levels = self._split(net_in)
            x = self.stem[2](self.stem[1](self._stem_conv(raw, raw_aux)))
        else:
            raw = F.pixel_unshuffle(pad_to_alignment(net_in, alignment(self.config)), 2)
            x = self.stem(raw)
        skips = []
        for i, (enc, down) in enumerate(zip(self.enc, self.down)):
            x = enc(x if self.aux_levels is None else self.aux_levels(x, i, levels))
            skips.append(x)
            x = F.avg_pool2d(down(x), 2)
        x = self.bottom(x if self.aux_levels is None else self.aux_levels(x, len(self.enc), levels))
        for up, dec in zip(self.up, self.dec):
            x = dec(torch.cat([F.interpolate(up(x), scale_factor=2.0, mode="nearest"), skips.pop()], dim=1))
        features = F.relu(self.tail_bn(x))
        x = self.tail(features) + self._skip(raw, raw_aux)
        out = F.pixel_shuffle(x, 2)[..., :h, :w]
        if self.kernel is not None:
            coefficients = self.kernel(features)
            if self.aux_kernel is not None:
                coefficients = coefficients + self.aux_kernel(features, raw_aux)
            coefficients = F.pixel_shuffle(coefficients, 2)[..., :h, :w]
            out = out + apply_kernel(image[:, :3], coefficients, self.config.kernel)
        out = out + image[:, :3] if self.config.output == "residual" else out
        return out if self.head is None else out + self.head(torch.cat([out, net_in], dim=1))

    def _split(self, net_in: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor] | None]:
        """The 2x2 unshuffles of the padded network input without the albedo and normal and of
        those alone, and (``levels`` mode) the buffers at every level (:func:`aux_input.pooled_buffers`)."""
        main, aux = aux_input.split_input(net_in)
        align = alignment(self.config)
        aux = pad_to_alignment(aux, align)
        raw_aux = F.pixel_unshuffle(aux, 2)
        levels = [raw_aux, *aux_input.pooled_buffers(aux, self.config.levels)] if self.aux_levels is not None else None
        return F.pixel_unshuffle(pad_to_alignment(main, align), 2), raw_aux, levels

    def _stem_conv(self, raw: torch.Tensor, raw_aux: torch.Tensor) -> torch.Tensor:
        """The stem conv (before its BN) of a net with buffers: on the RGB part, plus on the
        buffers where ``aux_mode`` lets them in (one weight, its columns split)."""
        conv = self.stem[0]
        if conv.in_channels == raw.shape[1]:
            return conv(raw)
        main, aux = self.aux_columns
        return (F.conv2d(raw, conv.weight[:, main].contiguous(), padding=1)
                + F.conv2d(raw_aux, conv.weight[:, aux].contiguous(), padding=1))

    def _skip(self, raw: torch.Tensor, raw_aux: torch.Tensor | None) -> torch.Tensor:
        """The input skip conv: on the unshuffled input (with buffers: on its RGB part, plus on
        the buffers in ``stem`` mode, one weight, its columns split)."""
        if self.skip.in_channels == raw.shape[1]:
            return self.skip(raw)
        main, aux = self.aux_columns
        return (F.conv2d(raw, self.skip.weight[:, main].contiguous(), self.skip.bias, padding=1)
                + F.conv2d(raw_aux, self.skip.weight[:, aux].contiguous(), padding=1))


KERNEL_ROWS = 64  # rows of a band of add_kernel_ (720p, two threads: 39 ms a call at 64 or 128, 45 at 16)


def kernel_offsets(size: int) -> list[tuple[int, int]]:
    """The (dy, dx) neighbours of a size x size filter's centre, centre excluded, row-major: the
    order of :func:`apply_kernel`'s coefficient channels."""
    r = size // 2
    return [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if dy or dx]


def _edge_padded(rgb: torch.Tensor, r: int, y0: int, y1: int) -> torch.Tensor:
    """Rows ``y0 - r`` .. ``y1 + r`` and columns ``-r`` .. ``W + r`` of an NxCxHxW ``rgb``, pixels beyond
    its edges repeating the edge's (any r: a 1x1 image too): the window the filters read, as a
    contiguous NCHW tensor. The rows are sliced (clamped by an index only at the image's top and
    bottom) and the columns padded by replication: two advanced indexings of a channels_last
    image cost 4x the time."""
    h = rgb.shape[-2]
    if y0 - r >= 0 and y1 + r <= h:
        rows = rgb[:, :, y0 - r:y1 + r]
    else:
        rows = rgb.index_select(2, torch.arange(y0 - r, y1 + r).clamp(0, h - 1))
    return F.pad(rows.contiguous(), (r, r, 0, 0), mode="replicate")


def apply_kernel(rgb: torch.Tensor, coefficients: torch.Tensor, size: int) -> torch.Tensor:
    """``sum_o coefficients[:, j] * (rgb(p + o) - rgb(p))`` over the :func:`kernel_offsets` o (j their
    index): NxCxHxW ``rgb``, Nx(size^2 - 1)xHxW ``coefficients`` (one filter for all channels);
    pixels beyond the edge repeat the edge's. Float32 whatever the coefficients' dtype.
    Differentiable in the coefficients only: ``rgb`` is the network's input, and a ValueError if it
    needs a gradient. The forward pass is :func:`add_kernel_`'s; nothing per offset is kept for the
    backward pass (about a third of the time of autograd through the sum's terms at K 5-7)."""
    if rgb.requires_grad:
        raise ValueError("apply_kernel gives no gradient to rgb (the network's input)")
    return _KernelFilter.apply(rgb, coefficients.float(), size)


class _KernelFilter(torch.autograd.Function):
    """:func:`apply_kernel` with a hand-written backward pass: the gradient of coefficient j is
    ``sum_c g * (rgb(p + o_j) - rgb(p))``, one pass over the gradient per offset."""

    @staticmethod
    def forward(ctx, rgb: torch.Tensor, coefficients: torch.Tensor, size: int) -> torch.Tensor:
        ctx.save_for_backward(rgb)
        ctx.size = size
        out = torch.zeros_like(rgb, memory_format=torch.contiguous_format)
        add_kernel_(out, rgb, coefficients, size)
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[None, torch.Tensor, None]:
        (rgb,) = ctx.saved_tensors
        size, r = ctx.size, ctx.size // 2
        n, _, h, w = rgb.shape
        grad = grad.float().contiguous()
        padded = _edge_padded(rgb, r, 0, h)
        offsets = kernel_offsets(size)
        out = torch.empty(n, len(offsets), h, w)
        for j, (dy, dx) in enumerate(offsets):
            torch.sum(grad * padded[..., r + dy:r + dy + h, r + dx:r + dx + w], dim=1, out=out[:, j])
        out -= (grad * rgb).sum(dim=1, keepdim=True)
        return None, out, None


def _band_coefficients(coefficients: torch.Tensor, y0: int, y1: int, width: int, scale: int,
                       taps: int) -> torch.Tensor:
    """Rows ``y0`` .. ``y1`` of the filter's ``taps`` coefficient planes at full resolution, float32:
    the band of ``coefficients`` made planar in its own dtype (a channels_last conv output: one
    transpose of half the bytes), then pixel-shuffled into float32 by one strided copy."""
    band = coefficients[:, :, y0 // scale:-(-y1 // scale)].contiguous()
    if scale == 1:
        return band[:, :, :y1 - y0, :width].float()
    n, _, hb, wb = band.shape
    full = torch.empty(n, taps, hb * scale, wb * scale)
    full.view(n, taps, hb, scale, wb, scale).copy_(
        band.view(n, taps, scale, scale, hb, wb).permute(0, 1, 4, 2, 5, 3))  # pixel_shuffle's order
    return full[:, :, :y1 - y0, :width]


def add_kernel_(out: torch.Tensor, rgb: torch.Tensor, coefficients: torch.Tensor, size: int,
                rows: int = KERNEL_ROWS, scale: int = 1) -> None:
    """``out += apply_kernel(rgb, coefficients, size)`` in place, ``rows`` rows at a time (no
    autograd): each band's coefficients, edge-padded RGB and sum stay small, where the whole-image
    passes of :func:`apply_kernel` stream every term through memory. ``scale`` 2: ``coefficients``
    are at half resolution, ``4 (size^2 - 1)`` channels in :func:`torch.nn.functional.pixel_shuffle`'s
    order (the conv's output as it is, at least half the image's size), each band shuffled on its
    own. Any layout and dtype of ``coefficients``; the sum is float32."""
    r = size // 2
    n, c, h, w = rgb.shape
    offsets = kernel_offsets(size)
    rows += rows % scale  # bands start on the coefficients' grid
    for y0 in range(0, h, rows):
        y1 = min(h, y0 + rows)
        padded = _edge_padded(rgb, r, y0, y1)
        a = _band_coefficients(coefficients, y0, y1, w, scale, len(offsets))
        total = torch.zeros(n, c, y1 - y0, w)
        for j, (dy, dx) in enumerate(offsets):
            total.addcmul_(a[:, j:j + 1], padded[:, :, r + dy:r + dy + y1 - y0, r + dx:r + dx + w])
        total.addcmul_(a.sum(dim=1, keepdim=True), rgb[:, :, y0:y1], value=-1.0)
        out[:, :, y0:y1] += total


def make_head(config: ModelConfig) -> nn.Sequential | None:
    """The full-resolution refinement head of ``config`` (None if ``config.head`` is 0):
    conv3x3 (3 + in_channels -> head) -> ReLU -> conv3x3 (head -> 3), the last one zero."""
    if not config.head:
        return None
    head = nn.Sequential(nn.Conv2d(3 + config.in_channels, config.head, 3, padding=1), nn.ReLU(inplace=True),
                         nn.Conv2d(config.head, 3, 3, padding=1))
    init_weights(head)
    for p in head.parameters():
        if p.dim() == 1 or p is head[2].weight:
            nn.init.zeros_(p)
    return head


def pad_to_alignment(x: torch.Tensor, align: int) -> torch.Tensor:
    """Pad an NxCxHxW tensor at the bottom and right, replicating the last row/column, to sides
    that are multiples of ``align`` (unchanged if they already are)."""
    h, w = x.shape[-2:]
    ph, pw = -h % align, -w % align
    if ph == 0 and pw == 0:
        return x
    if ph < h and pw < w:
        return F.pad(x, (0, pw, 0, ph), mode="replicate")
    # replicate padding is limited to the input size in some torch versions: repeat the edge
    x = torch.cat([x, x[..., :, -1:].expand(*x.shape[:-1], pw)], dim=-1) if pw else x
    return torch.cat([x, x[..., -1:, :].expand(*x.shape[:-2], ph, x.shape[-1])], dim=-2) if ph else x


def receptive_radius(config: ModelConfig) -> int:
    """An upper bound, in input pixels, on how far from an output pixel an input pixel can
    change it (gradient channels and the 2x2 cells of the resampling steps included)."""
    r = 1 + 1  # forward-difference gradients, then the unshuffle's 2x2 cell
    jump = 2
    r += jump  # stem conv3x3
    for i in range(config.levels):
        r += config.layers * jump  # each layer's one 3x3 conv
        r += jump  # 2x2 pooling cell
        jump *= 2
    r += config.layers * jump  # bottom block
    for i in reversed(range(config.levels)):
        jump //= 2
        r += jump  # nearest upsampling cell
        r += config.layers * jump
    r += jump + 1  # tail / skip conv3x3 at half resolution, pixel-shuffle cell
    r = r + 2 if config.head else r  # the head's two conv3x3 at full resolution
    # the predicted filter reads its k x k neighbours; the buffers' paths of aux_mode levels and
    # kernel (a cell and a conv3x3 at a level's entry) reach no further than the stem's path there
    # (its unshuffle cell, conv3x3 and the levels above, each at least one layer), but a
    # prefilter first looks its radius further
    return max(r, config.kernel // 2) + aux_input.prefilter_reach(config)


def conv_macs_per_pixel(model: nn.Module, height: int = 64, width: int = 64) -> float:
    """Multiply-accumulates per input pixel of every convolution of ``model`` (measured with
    forward hooks on one HxW image; for the multi-scale nets H, W multiples of the alignment)."""
    total = 0

    def hook(module: nn.Conv2d, _inputs: tuple, output: torch.Tensor) -> None:
        nonlocal total
        k = module.kernel_size[0] * module.kernel_size[1]
        total += output.shape[-1] * output.shape[-2] * module.out_channels * k * module.in_channels // module.groups

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Conv2d)]
    try:
        was = model.training
        model.eval()
        with torch.no_grad():
            model(torch.zeros(1, model.config.image_channels, height, width))
        model.train(was)
    finally:
        for h in handles:
            h.remove()
    return total / (height * width)


def macs_per_pixel(config: ModelConfig, plain_scale: float | None = None, pool_first: bool = True) -> float:
    """Multiply-accumulates per input pixel of every convolution, counted from the channel plan.

    ``pool_first``: the transitions down pool before their 1x1 conv, as the folded inference
    net does (:mod:`denoise.inference_unet`); False counts the training module, which convolves
    first (what :func:`conv_macs_per_pixel` measures on it).
    """
    dense = config.arch == "dense_unet"
    if plain_scale is None:
        plain_scale = 1.0 if dense else plain_width_scale(config)
    plan = _Widths(config, plain_scale)
    n, layers, b = config.levels, config.layers, config.bottleneck
    w = plan.width
    share = [0.25 ** (i + 1) for i in range(n + 1)]  # pixels of level i per input pixel

    def block(cin: int, i: int) -> tuple[float, int]:
        k, mid = plan.growth[i], plan.mid[i]
        if not dense:
            return layers * (cin * mid + 9 * mid * cin) * share[i], cin
        macs = sum((cin + j * k) * mid + 9 * mid * k for j in range(layers))
        return macs * share[i], cin + layers * k

    total = 9 * 4 * config.stem_channels * w[0] * share[0]
    enc_out = []
    for i in range(n):
        macs, e = block(w[i], i)
        enc_out.append(e)
        total += macs + e * w[i + 1] * share[i + 1 if pool_first else i]
    macs, below = block(w[n], n)
    total += macs
    for i in reversed(range(n)):
        total += below * w[i] * share[i + 1]
        macs, below = block(w[i] + enc_out[i], i)
        total += macs
    total += 9 * (below + 4 * config.skip_channels) * 12 * share[0]
    total += below * 4 * config.kernel_taps * share[0]  # the filter's coefficients
    total += _aux_macs(config, w, below, share)
    return total + 9 * (3 + config.in_channels + 3) * config.head


def _aux_macs(config: ModelConfig, width: list[int], below: int, share: list[float]) -> float:
    """Multiply-accumulates per input pixel of the convs of :mod:`model.aux_input`'s branches."""
    if not config.aux_inputs or config.aux_mode not in ("levels", "kernel"):
        return 0.0
    raw = 4 * aux_input.AUX_CHANNELS
    if config.aux_mode == "levels":
        return sum(9 * (raw if i == 0 else aux_input.AUX_CHANNELS) * c * share[i] for i, c in enumerate(width))
    hidden = aux_input.KERNEL_HIDDEN
    return (below * hidden + 9 * raw * hidden + hidden * 4 * config.kernel_taps) * share[0]


@functools.lru_cache(maxsize=64)
def plain_width_scale(config: ModelConfig) -> float:
    """Width factor of ``plain_unet`` whose MACs per pixel are closest to the ``dense_unet`` of
    the same sizes (bisection on :func:`macs_per_pixel`)."""
    plain = dataclasses.replace(config, arch="plain_unet")
    target = macs_per_pixel(dataclasses.replace(config, arch="dense_unet"))
    lo, hi = 0.25, 8.0
    for _ in range(40):
        mid = math.sqrt(lo * hi)
        lo, hi = (mid, hi) if macs_per_pixel(plain, mid) < target else (lo, mid)
    return round(math.sqrt(lo * hi), 4)
