"""An inference-only copy of a trained :class:`model.unet.MultiScaleDenoiser`: same function, less work.

The same rewrites as :mod:`denoise.inference_net` (exact up to float32 rounding), plus what the
encoder/decoder shape allows:

* **BatchNorm folded** into the conv before it (stem, every bottleneck's 1x1), and every BN-ReLU
  in front of a 1x1 conv (bottleneck layers, transitions down and up) rewritten as one clamp
  whose scale and shift live in the conv (:class:`denoise.inference_net._ClampConv1x1`).
* **Pool before the transition's 1x1 conv.** 2x2 average pooling and a 1x1 conv (with bias) are
  both linear per pixel, so they commute: the conv runs on a quarter of the pixels.
* **No concatenation.** Each level owns one preallocated buffer laid out as
  ``[encoder block | upsampled decoder input | decoder layers]``: the encoder block's layers write
  their channels into it, the transition up writes the upsampled features next to them, and the
  decoder layers append theirs, so the skip connection costs no copy. The decoder's 1x1 convs
  (and the tail) see the channels in this order instead of the training module's
  ``[up | skip | ...]``, so their weights are permuted to match.
* **Nearest upsampling written in place** through a strided view of the buffer (one pass).
* **channels_last** activations and weights.
* **One scratch for the clamps** (:func:`denoise.inference_net.scratch_view`): every clamp of a
  forward pass writes into one flat buffer sized for the largest; the tail's BN-ReLU runs in place
  on level 0's buffer, which nothing reads after it.
* **The full-resolution head** (``head`` > 0) runs as two plain convs on channels_last input.
* **The predicted filter** (``kernel`` > 0): its coefficients' conv1x1 reads the tail's BN-ReLU
  output like the tail; the filter runs in float32 a band of rows at a time, each band's
  coefficients pixel-shuffled on their own (:func:`model.unet.add_kernel_`).
* **Albedo and normal** (:mod:`model.aux_input`): the stem and skip convs read the whole unshuffled
  input, their weights zero on the columns ``aux_mode`` keeps from them; ``levels`` mode adds its
  convs of the buffers at each level's entry (level 0's reads the whole unshuffled input, zero on
  the other columns), ``kernel`` mode adds its branch to the coefficients; the prefilter runs on
  the input first.
* **Optionally bfloat16** (``dtype``, :mod:`denoise.precision`): weights and activations; the input
  is built and the residual added in float32.
* **Unshuffle and shuffle as strided copies.** The network input (RGB, its gradients, the rest)
  is written into one padded NHWC buffer, and the pixel-unshuffle to half resolution is one copy
  of it (cast to the network's dtype on the way) that moves each 2x2 block's pixels as runs of
  whole pixels: the stem and skip convs read the unshuffled channels in the order
  ``(2i + j) * C + c`` instead of torch's ``4c + 2i + j``, and the tail and skip write the output's
  2x2 blocks in that order too, so their weights are permuted to match (exact). The output comes
  back as an NHWC tensor seen as NCHW (channels_last). Measured at 720p, one thread (u-fast,
  bfloat16): torch's pixel_unshuffle + channels_last + cast took ~60 ms a call, this ~20.

Input and output are those of the original model: NxCxHxW transfer-space image -> Nx3xHxW
transfer-space RGB. ``tests/test_inference_unet.py`` bounds the difference.
"""
from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from model.aux_input import pooled_buffers, prefiltered, widen_weight
from model.config import AUX_CHANNELS, ModelConfig
from denoise.inference_net import _AffineReLU, _ClampConv1x1, _Conv, bn_affine, fold_conv_bn, padded_input
from model.unet import Block, MultiScaleDenoiser, add_kernel_, alignment


def _whole_input(conv: nn.Conv2d, config: ModelConfig) -> nn.Conv2d:
    """``conv`` (the stem's or the skip's) as a conv over the whole unshuffled network input:
    itself where it reads it all, else a copy zero on the columns of the albedo and normal."""
    if conv.in_channels == 4 * config.in_channels:
        return conv
    wide = nn.Conv2d(4 * config.in_channels, conv.out_channels, conv.kernel_size, padding=conv.padding,
                     bias=conv.bias is not None)
    with torch.no_grad():
        wide.weight.copy_(widen_weight(conv.weight, config))
        if conv.bias is not None:
            wide.bias.copy_(conv.bias)
    return wide


class _FoldedBlock(nn.Module):
    """A block's layers as (clamp-conv1x1, conv3x3) pairs; dense ones write into a buffer."""

    def __init__(self, block: Block, order: torch.Tensor | None = None) -> None:
        super().__init__()
        self.dense = block.dense
        self.conv1 = nn.ModuleList()
        self.conv3 = nn.ModuleList()
        for layer in block.layers:
            bn1, _, conv1, bn2, _, conv3 = layer.body
            cin = conv1.in_channels
            self.conv1.append(_ClampConv1x1(bn1, conv1, bn2, None if order is None else order[:cin]))
            self.conv3.append(_Conv(conv3.weight.detach().clone(), None, relu=False))
        self.out_channels = block.out_channels

    def run_dense(self, buf: torch.Tensor, start: int, scratch: torch.Tensor) -> None:
        """Layer i reads ``buf[:, :start + i*k]`` and writes its k channels right after (its
        clamp into ``scratch``)."""
        c = start
        for conv1, conv3 in zip(self.conv1, self.conv3):
            y = conv3(conv1(buf[:, :c], scratch))
            buf[:, c:c + y.shape[1]] = y
            c += y.shape[1]

    def run_plain(self, x: torch.Tensor, scratch: torch.Tensor) -> torch.Tensor:
        for conv1, conv3 in zip(self.conv1, self.conv3):
            x = conv3(conv1(x, scratch))
        return x


def _upsample_into(target: torch.Tensor, low: torch.Tensor) -> None:
    """``target[n, c, y, x] = low[n, c, y // 2, x // 2]`` for an NxCx2hx2w ``target`` (any strides)."""
    n, c, h, w = low.shape
    s = target.stride()
    view = target.as_strided((n, c, h, 2, w, 2), (s[0], s[1], 2 * s[2], s[2], 2 * s[3], s[3]),
                             target.storage_offset())
    view.copy_(low[:, :, :, None, :, None].expand(n, c, h, 2, w, 2))


def shuffle_order(channels: int) -> torch.Tensor:
    """For each channel ``q = (2i + j) * channels + c`` of a 2x2 unshuffle written block-major, the
    index ``4c + 2i + j`` of the same value in :func:`torch.nn.functional.pixel_unshuffle`'s order."""
    q = torch.arange(4 * channels)
    return (q % channels) * 4 + q // channels


def unshuffled_input(image: torch.Tensor, align: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """The network input of an NxCxHxW ``image`` padded to ``align`` (:func:`denoise.inference_net.padded_input`)
    and its 2x2 unshuffle in :func:`shuffle_order`. Returns (the padded input, NxHpxWpx(C+6)
    float32 NHWC, the unshuffle, an Nx4(C+6)x(Hp/2)x(Wp/2) channels_last tensor of ``dtype``)."""
    p = padded_input(image, align)
    n, hp, wp, cin = p.shape
    raw = torch.empty(n, hp // 2, wp // 2, 2, 2, cin, dtype=dtype)
    raw.copy_(p.view(n, hp // 2, 2, wp // 2, 2, cin).permute(0, 1, 3, 2, 4, 5))
    return p, raw.view(n, hp // 2, wp // 2, 4 * cin).permute(0, 3, 1, 2)


def shuffled_output(y: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """The 2x2 pixel-shuffle of an Nx12x(h2)x(w2) tensor whose channels are in :func:`shuffle_order`
    (3 colours), as float32, cropped to ``h`` x ``w``: an Nx3xhxw channels_last tensor."""
    n, _, h2, w2 = y.shape
    full = torch.empty(n, 2 * h2, 2 * w2, 3)
    blocks = y.permute(0, 2, 3, 1).reshape(n, h2, w2, 2, 2, 3)
    full.view(n, h2, 2, w2, 2, 3).copy_(blocks.permute(0, 1, 3, 2, 4, 5))
    return full[:, :h, :w].permute(0, 3, 1, 2)


def _buffer(x: torch.Tensor, channels: int, h: int, w: int) -> torch.Tensor:
    return torch.empty(x.shape[0], channels, h, w, dtype=x.dtype, memory_format=torch.channels_last)


class InferenceUNet(nn.Module):
    """The folded, concatenation-free, channels_last equivalent of a MultiScaleDenoiser in eval mode."""

    def __init__(self, model: MultiScaleDenoiser, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        self.config: ModelConfig = model.config
        self.dtype = dtype
        self.dense = model.config.arch == "dense_unet"
        n = model.config.levels
        with torch.no_grad():
            conv0, bn0, _ = model.stem
            order_in = shuffle_order(model.config.in_channels)  # stem and skip read block-major input
            order_out = shuffle_order(3)  # tail and skip write block-major output
            weight, bias = fold_conv_bn(_whole_input(conv0, model.config), bn0)
            self.stem = _Conv(weight[:, order_in], bias, relu=True)
            self.enc = nn.ModuleList(_FoldedBlock(b) for b in model.enc)
            self.enc_width = [b.out_channels for b in model.enc]
            self.width = [seq[2].out_channels for seq in model.up][::-1]  # w_i per level (up -> level i)
            self.level_channels = []
            orders = []
            for i in range(n):
                e, w = self.enc_width[i], self.width[i]
                total = model.dec[n - 1 - i].out_channels
                self.level_channels.append(total)
                orders.append(torch.cat([torch.arange(w, w + e), torch.arange(w), torch.arange(w + e, total)])
                              if self.dense else None)
            self.down = nn.ModuleList(_ClampConv1x1(seq[0], seq[2]) for seq in model.down)
            self.bottom = _FoldedBlock(model.bottom)
            self.bottom_channels = model.bottom.out_channels
            # up[j] and dec[j] belong to level n-1-j; store them by level
            self.up = nn.ModuleList(
                _ClampConv1x1(model.up[n - 1 - i][0], model.up[n - 1 - i][2],
                              order=orders[i + 1][:model.up[n - 1 - i][2].in_channels]
                              if i + 1 < n and self.dense else None)
                for i in range(n))
            self.dec = nn.ModuleList(_FoldedBlock(model.dec[n - 1 - i], orders[i]) for i in range(n))
            scale, shift = bn_affine(model.tail_bn)
            tail_weight = model.tail.weight.detach().clone()
            if self.dense:
                scale, shift, tail_weight = scale[orders[0]], shift[orders[0]], tail_weight[:, orders[0]]
            self.tail_pre = _AffineReLU(scale, shift)
            self.tail = _Conv(tail_weight[order_out], None, relu=False)
            self.kernel = None
            if model.kernel is not None:  # writes pixel_shuffle's order: add_kernel_ shuffles it band by band
                weight = model.kernel.weight.detach()[:, orders[0]] if self.dense else model.kernel.weight.detach()
                self.kernel = _Conv(weight.clone(), model.kernel.bias.detach().clone(), relu=False)
            self.skip = _Conv(_whole_input(model.skip, model.config).weight.detach()[order_out][:, order_in].clone(),
                              model.skip.bias.detach()[order_out].clone(), relu=False)
            self.aux_levels = None if model.aux_levels is None else nn.ModuleList(
                _Conv((widen_weight(conv.weight.detach(), model.config, "aux")[:, order_in] if i == 0
                       else conv.weight.detach()).clone(), None, relu=False)
                for i, conv in enumerate(model.aux_levels.convs))
            self.aux_kernel = None
            if model.aux_kernel is not None:
                branch = model.aux_kernel
                weight = branch.from_features.weight.detach()
                self.aux_kernel = nn.ModuleList([
                    _Conv((weight[:, orders[0]] if self.dense else weight).clone(),
                          branch.from_features.bias.detach().clone(), relu=False),
                    _Conv(widen_weight(branch.from_aux.weight.detach(), model.config, "aux")[:, order_in].clone(), None,
                          relu=False),
                    _Conv(branch.out.weight.detach().clone(), branch.out.bias.detach().clone(), relu=False)])
            self.head = None if model.head is None else nn.Sequential(
                *(_Conv(conv.weight.detach().clone(), conv.bias.detach().clone(), relu=i == 0)
                  for i, conv in enumerate((model.head[0], model.head[2]))))
        # per level, the channels of its widest clamp input (level i runs its encoder and decoder
        # blocks' clamps, its transition down's and, for i > 0, the transition up from it to level
        # i-1; level n the bottom block's; level 0 also the tail's affine map): the scratch's size
        clamps = [[*self.enc[i].conv1, *self.dec[i].conv1, self.down[i]] for i in range(n)] + [list(self.bottom.conv1)]
        for i in range(1, n + 1):
            clamps[i].append(self.up[i - 1])
        self.clamp_widths = [max(c.in_channels for c in level) for level in clamps]
        self.clamp_widths[0] = max(self.clamp_widths[0], self.tail_pre.scale.shape[1])
        self.to(dtype)
        self.eval()

    def _encode(self, x: torch.Tensor, level: int, scratch: torch.Tensor) -> torch.Tensor:
        """Run encoder block ``level`` on its input ``x``; returns the level's buffer (dense) or
        the block's output (plain)."""
        if not self.dense:
            return self.enc[level].run_plain(x, scratch)
        h, w = x.shape[-2:]
        buf = _buffer(x, self.level_channels[level], h, w)
        buf[:, :x.shape[1]] = x
        self.enc[level].run_dense(buf, x.shape[1], scratch)
        return buf

    def _bottom(self, x: torch.Tensor, scratch: torch.Tensor) -> torch.Tensor:
        if not self.dense:
            return self.bottom.run_plain(x, scratch)
        buf = _buffer(x, self.bottom_channels, *x.shape[-2:])
        buf[:, :x.shape[1]] = x
        self.bottom.run_dense(buf, x.shape[1], scratch)
        return buf

    def _decode(self, below: torch.Tensor, skip: torch.Tensor, level: int, scratch: torch.Tensor) -> torch.Tensor:
        """Transition up from ``below`` and decoder block ``level`` (``skip``: the level's
        buffer for dense nets, whose encoder part is already filled)."""
        up = self.up[level](below, scratch)
        if not self.dense:
            big = F.interpolate(up, scale_factor=2.0, mode="nearest")
            return self.dec[level].run_plain(torch.cat([big, skip], dim=1), scratch)
        e, w = self.enc_width[level], self.width[level]
        _upsample_into(skip[:, e:e + w], up)
        self.dec[level].run_dense(skip, e + w, scratch)
        return skip

    def scratch_elements(self, n: int, h: int, w: int) -> int:
        """Elements of the clamps' scratch for a stem output of n x h x w pixels: the largest
        clamp input (:attr:`clamp_widths` x pixels of its level; level i has (h >> i) x (w >> i))."""
        return n * max(c * (h >> i) * (w >> i) for i, c in enumerate(self.clamp_widths))

    def _level_buffers(self, padded: torch.Tensor, raw: torch.Tensor) -> list[torch.Tensor] | None:
        """``levels`` mode: the input each level's buffer conv reads (level 0 the whole unshuffled
        input, the others :func:`model.aux_input.pooled_buffers`'s averages), in the net's dtype."""
        if self.aux_levels is None:
            return None
        pooled = pooled_buffers(padded[..., 9:9 + AUX_CHANNELS].permute(0, 3, 1, 2), self.config.levels)
        return [raw] + [p.to(self.dtype).contiguous(memory_format=torch.channels_last) for p in pooled]

    def _inject(self, x: torch.Tensor, level: int, buffers: list[torch.Tensor] | None) -> torch.Tensor:
        return x if buffers is None else x + self.aux_levels[level](buffers[level])

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        # each tensor is dropped once the rest of the pass no longer needs it: a tile's peak is
        # what is alive at once (model.architectures.live_channels_per_pixel counts it)
        h, w = image.shape[-2:]
        if self.config.aux_inputs and self.config.aux_prefilter != "none":
            image = prefiltered(image)
        padded, raw = unshuffled_input(image, alignment(self.config), self.dtype)
        buffers = self._level_buffers(padded, raw)
        net_in = None if self.head is None else padded[:, :h, :w].permute(0, 3, 1, 2)
        del padded  # only the head and the levels' buffers read it
        x = self.stem(raw)
        scratch = torch.empty(self.scratch_elements(x.shape[0], *x.shape[-2:]), dtype=self.dtype)
        levels = []
        for i, down in enumerate(self.down):
            buf = self._encode(self._inject(x, i, buffers), i, scratch)
            levels.append(buf)
            e = self.enc_width[i]
            x = down.conv(F.avg_pool2d(down.clamp(buf[:, :e], scratch), 2))
        x = self._bottom(self._inject(x, len(self.down), buffers), scratch)
        del buffers
        for i in reversed(range(len(levels))):
            x = self._decode(x, levels.pop(), i, scratch)
        del scratch
        features = self.tail_pre.in_place(x)  # level 0's buffer is read no more
        del x
        y = self.tail(features)
        coefficients = None if self.kernel is None else self.kernel(features)
        if self.aux_kernel is not None:
            from_features, from_aux, out = self.aux_kernel
            coefficients += out(from_features(features).add_(from_aux(raw)).relu_())
        del features
        y += self.skip(raw)
        del raw
        out = shuffled_output(y, h, w)
        del y
        out = out + image[:, :3] if self.config.output == "residual" else out
        if coefficients is not None:
            add_kernel_(out, image[:, :3], coefficients, self.config.kernel, scale=2)
        if net_in is None:
            return out
        both = torch.cat([out, net_in], dim=1).contiguous(memory_format=torch.channels_last)
        return out + self.head(both.to(self.dtype)).float()
