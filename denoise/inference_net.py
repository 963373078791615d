"""An inference-only copy of a trained :class:`model.network.FlatDenseNet`: same function, less work.

What changes against the training module (eval mode), and why it is exact up to float32 rounding:

* **BatchNorm folded into the conv before it.** Eval-mode BN is an affine map per channel,
  ``y = s*x + t`` with ``s = gamma/sqrt(var+eps)``, ``t = beta - s*mean``. When it directly follows
  a conv (the head's conv7x7 -> BN, every bottleneck's conv1x1 -> BN) the conv becomes
  ``W' = s*W``, ``b' = s*b + t``.
* **BN-ReLU before a 1x1 conv as one clamp.** A BN that follows a ReLU (each bottleneck's first
  BN; in the dense block it acts on the concatenation of earlier outputs with statistics of its
  own) cannot be folded backwards through the ReLU. But ``relu(s*x + t) = s*clamp(x, lo, hi) + c``
  per channel, and a 1x1 conv has no padding, so its scale moves into the conv's weights and
  ``c`` into its bias: one clamp pass instead of a BN pass and a ReLU pass. The tail's BN-ReLU
  precedes a padded 3x3 conv (the constant would be wrong at the border) and stays an affine map
  with an in-place ReLU.
* **No concatenation.** The dense block writes every layer's k new channels into slices of one
  preallocated buffer instead of ``torch.cat``-ing an ever-growing tensor (O(L) instead of O(L^2)
  memory traffic).
* **channels_last** (NHWC) activations and weights, the layout oneDNN convolves without reordering.
* **One scratch for the clamps.** Every clamp (and the tail's affine map) writes into a view of one
  flat buffer allocated once per forward pass (:func:`scratch_view`) instead of a fresh tensor per
  layer: a fresh tensor of more than a megabyte is a fresh mapping (:mod:`denoise.allocator`), whose
  every page faults on first touch. With the one-sided clamp of :class:`_ClampConv1x1`, measured
  on 2 cores: u-fast's network alone at 1080p in bfloat16, 1.22 -> 0.90 s (docs/experiments.md).
* **Optionally bfloat16** (``dtype``, :mod:`denoise.precision`): weights and activations; the input
  is built and the residual added in float32. In bfloat16 each bottleneck's BN-ReLU is one affine
  pass and an in-place ReLU instead of the clamp, whose folded form rounds away small features
  (:class:`_ClampConv1x1`); the multi-scale nets keep the clamp in bfloat16 (the affine form
  measured no better there: unet-l-allspp 39.67 dB either way at 128 spp, 5-10% slower).
* **The input written into one NHWC buffer** (:func:`padded_input`): RGB, its gradients and the
  other channels side by side per pixel, the layout the first conv reads, instead of a
  concatenation of NCHW planes and a reorder.

Input and output are those of the original model: Nx3xHxW (Nx9xHxW with aux) transfer-space image
-> Nx3xHxW transfer-space RGB. ``tests/test_inference_net.py`` bounds the difference.
"""
from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn
from torch.nn import functional as F

from model.config import ModelConfig
from model.network import FlatDenseNet


def bn_affine(bn: nn.BatchNorm2d) -> tuple[torch.Tensor, torch.Tensor]:
    """Eval-mode BN as per-channel (scale, shift), computed in float64, returned float32."""
    var = bn.running_var.double()
    scale = (bn.weight.double() if bn.affine else torch.ones_like(var)) / torch.sqrt(var + bn.eps)
    bias = bn.bias.double() if bn.affine else torch.zeros_like(var)
    shift = bias - scale * bn.running_mean.double()
    return scale.float(), shift.float()


def scratch_view(scratch: torch.Tensor, n: int, c: int, h: int, w: int) -> torch.Tensor:
    """The first ``n*c*h*w`` elements of the flat ``scratch`` as an NxCxHxW channels_last tensor."""
    return scratch[:n * c * h * w].view(n, h, w, c).permute(0, 3, 1, 2)


def fold_conv_bn(conv: nn.Conv2d, bn: nn.BatchNorm2d) -> tuple[torch.Tensor, torch.Tensor]:
    """(weight, bias) of ``conv`` followed by eval-mode ``bn`` as a single conv (float64 maths)."""
    scale, shift = (v.double() for v in bn_affine(bn))
    weight = conv.weight.double() * scale.view(-1, 1, 1, 1)
    bias = shift if conv.bias is None else scale * conv.bias.double() + shift
    return weight.float(), bias.float()


def padded_input(image: torch.Tensor, align: int = 1) -> torch.Tensor:
    """The network input of an NxCxHxW ``image`` (:func:`model.network.network_input`: RGB, its x
    and y forward differences, the other channels) as an NxHpxWpx(C+6) float32 NHWC tensor, padded
    at the bottom and right to sides that are multiples of ``align`` by replicating the last row
    and column (:func:`model.unet.pad_to_alignment`); written part by part into one buffer, which
    reads an image with channels_last strides fastest."""
    n, c, h, w = image.shape
    hp, wp = h + -h % align, w + -w % align
    src = image.permute(0, 2, 3, 1)
    rgb = src[..., :3]
    p = torch.empty(n, hp, wp, c + 6)
    p[:, :h, :w, :3] = rgb
    torch.sub(rgb[:, :, 1:], rgb[:, :, :-1], out=p[:, :h, :w - 1, 3:6])
    p[:, :h, w - 1, 3:6] = 0.0
    torch.sub(rgb[:, 1:], rgb[:, :-1], out=p[:, :h - 1, :w, 6:9])
    p[:, h - 1, :w, 6:9] = 0.0
    if c > 3:
        p[:, :h, :w, 9:] = src[..., 3:]
    if wp > w:
        p[:, :h, w:] = p[:, :h, w - 1:w]
    if hp > h:
        p[:, h:] = p[:, h - 1:h]
    return p


def _fused_conv_relu() -> Callable[..., torch.Tensor] | None:
    """oneDNN's convolution with a ReLU post-op (what torch.compile's CPU backend calls), or None
    where this torch build has none."""
    try:
        return torch.ops.mkldnn._convolution_pointwise if torch.backends.mkldnn.is_available() else None
    except (AttributeError, RuntimeError):
        return None


_CONV_RELU = _fused_conv_relu()


class _Conv(nn.Module):
    """A folded conv: fixed weight, optional bias, 'same' padding, optional ReLU after it.

    On the CPU the ReLU is oneDNN's post-op of the convolution (:func:`_fused_conv_relu`): the same
    values bit for bit, without a pass of its own over the output (a bfloat16 ReLU over a
    48-channel 640x368 map took 10 ms on 2 cores, the 1x1 conv before it 2; fused: 3.3 in all)."""

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor | None, relu: bool) -> None:
        super().__init__()
        self.register_buffer("weight", weight.contiguous(memory_format=torch.channels_last))
        self.register_buffer("bias", bias)
        self.padding = weight.shape[-1] // 2
        self.relu = relu

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.relu and _CONV_RELU is not None and x.device.type == "cpu" and not torch.is_grad_enabled():
            p = self.padding
            return _CONV_RELU(x, self.weight, self.bias, [p, p], [1, 1], [1, 1], 1, "relu", [], "")
        y = F.conv2d(x, self.weight, self.bias, padding=self.padding)
        return y.relu_() if self.relu else y


class _AffineReLU(nn.Module):
    """relu(scale*x + shift) per channel: a BN that follows a ReLU, kept as one pass + in-place ReLU."""

    def __init__(self, scale: torch.Tensor, shift: torch.Tensor) -> None:
        super().__init__()
        self.register_buffer("scale", scale.view(1, -1, 1, 1))
        self.register_buffer("shift", shift.view(1, -1, 1, 1))

    def forward(self, x: torch.Tensor, scratch: torch.Tensor | None = None) -> torch.Tensor:
        if scratch is None:
            return torch.addcmul(self.shift, x, self.scale).relu_()
        return torch.addcmul(self.shift, x, self.scale, out=scratch_view(scratch, *x.shape)).relu_()

    def in_place(self, x: torch.Tensor) -> torch.Tensor:
        """``relu(scale*x + shift)`` written over ``x`` (the same values as :meth:`forward`)."""
        return torch.addcmul(self.shift, x, self.scale, out=x).relu_()


DEAD_SCALE = 1e-12  # |s| below this: the channel counts as constant (s*x is lost in rounding)


def relu_affine_as_clamp(scale: torch.Tensor, shift: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Rewrite ``relu(s*x + t)`` per channel as ``s*clamp(x, lo, hi) + c`` (exact, float64).

    s > 0: lo = -t/s, hi = +inf, c = t. s < 0: lo = -inf, hi = -t/s, c = t. s = 0 (or
    |s| < DEAD_SCALE, where -t/s could overflow): s := 0, no clamp, c = relu(t). Returns float32
    (s, lo, hi, c) shaped C, 1xCx1x1, 1xCx1x1, 1xCx1x1.
    """
    s, t = scale.double(), shift.double()
    s = torch.where(s.abs() < DEAD_SCALE, torch.zeros_like(s), s)
    safe = torch.where(s == 0, torch.ones_like(s), s)
    inf = torch.full_like(s, float("inf"))
    lo = torch.where(s > 0, -t / safe, -inf)
    hi = torch.where(s < 0, -t / safe, inf)
    c = torch.where(s == 0, t.clamp(min=0.0), t)
    return (s.float(), *(v.float().view(1, -1, 1, 1) for v in (lo, hi, c)))


class _ClampConv1x1(nn.Module):
    """A BN-ReLU-Conv1x1 (-BN-ReLU) in two passes: the pre-activation, then a conv with bias (+ ReLU).

    ``relu(s*x + t) = s*clamp(x, lo, hi) + c`` (:func:`relu_affine_as_clamp`), and a 1x1 conv has
    no padding, so ``W @ (s*clamp(x) + c) = (W*s) @ clamp(x) + W @ c`` holds at every pixel: the
    first pass is one clamp. ``affine``: the first pass is ``relu(s*x + t)`` itself (one affine map,
    then an in-place ReLU) and the conv keeps ``W``. Both are exact in float32; in bfloat16 only the
    affine form is precise: a clamped feature sits near ``lo = -t/s``, often far from 0, so
    ``(W*s) @ clamp(x)`` and the bias ``W @ c`` are large terms that cancel, and the rounding of
    ``W*s`` and ``W @ c`` to 8 bits survives the cancellation (flat-s-allspp on the eval scenes at
    128 spp: 40.67 dB in the clamp form, 40.99 affine, 41.12 in float32; docs/experiments.md).
    ``bn2`` (the bottleneck's BN after the conv) is folded into the conv, followed by a ReLU;
    without it the conv's output is returned as it is (a transition). ``order``: the input
    channels arrive in this order of the training module's channels (a permutation).
    """

    def __init__(self, bn1: nn.BatchNorm2d, conv: nn.Conv2d, bn2: nn.BatchNorm2d | None = None,
                 order: torch.Tensor | None = None, affine: bool = False) -> None:
        super().__init__()
        if bn2 is not None:
            weight, bias = fold_conv_bn(conv, bn2)
        else:
            weight, bias = conv.weight.detach(), torch.zeros(conv.out_channels)
        w = weight.double()[:, :, 0, 0]
        self.affine = affine
        self.in_channels = w.shape[1]
        if affine:
            scale, shift = (v.view(1, -1, 1, 1) for v in bn_affine(bn1))
            if order is not None:
                w, scale, shift = w[:, order], scale[:, order], shift[:, order]
            self.register_buffer("scale", scale.contiguous())
            self.register_buffer("shift", shift.contiguous())
        else:
            scale, lo, hi, const = relu_affine_as_clamp(*bn_affine(bn1))
            bias = bias.double() + w @ const.double().view(-1)
            w = w * scale.double()
            if order is not None:
                w, lo, hi = w[:, order], lo[:, order], hi[:, order]
            self.register_buffer("lo", lo.contiguous())
            self.register_buffer("hi", hi.contiguous())
            # trained BN scales are positive in practice (every clamp of the shipped weights): then the
            # clamp has no upper bound and is one maximum, measured 1.6x faster than clamp in bfloat16
            self.upper = bool(torch.isfinite(hi).any())
        self.conv = _Conv(w.float()[:, :, None, None], bias.float(), relu=bn2 is not None)

    def clamp(self, x: torch.Tensor, scratch: torch.Tensor | None = None) -> torch.Tensor:
        """The first pass alone: the input clamped per channel, or ``relu(s*x + t)`` where
        ``affine`` (into a view of the flat ``scratch`` when given, :func:`scratch_view`)."""
        out = None if scratch is None else scratch_view(scratch, *x.shape)
        if self.affine:
            return torch.addcmul(self.shift, x, self.scale, out=out).relu_()
        if self.upper:
            return torch.clamp(x, self.lo, self.hi, out=out)
        return torch.maximum(x, self.lo, out=out)

    def forward(self, x: torch.Tensor, scratch: torch.Tensor | None = None) -> torch.Tensor:
        return self.conv(self.clamp(x, scratch))


class InferenceNet(nn.Module):
    """The folded, concatenation-free, channels_last equivalent of a FlatDenseNet in eval mode."""

    def __init__(self, model: FlatDenseNet, dtype: torch.dtype = torch.float32) -> None:
        super().__init__()
        self.config: ModelConfig = model.config
        self.dtype = dtype
        self.width = model.body.out_channels
        with torch.no_grad():
            conv0, bn0, _ = model.head
            self.head = _Conv(*fold_conv_bn(conv0, bn0), relu=True)
            layers = [layer.body for layer in model.body.layers]
            affine = dtype == torch.bfloat16  # precise in bfloat16 (_ClampConv1x1)
            self.conv1 = nn.ModuleList(_ClampConv1x1(b[0], b[2], b[3], affine=affine) for b in layers)
            self.conv3 = nn.ModuleList(_Conv(b[5].weight.detach().clone(), None, relu=False) for b in layers)
            tail_bn, _, tail_conv = model.tail
            self.tail_pre = _AffineReLU(*bn_affine(tail_bn))
            self.tail = _Conv(tail_conv.weight.detach().clone(), None, relu=False)
        # channels of the widest clamp input (the tail's affine map included): the scratch's per pixel
        self.clamp_width = max([c.in_channels for c in self.conv1] + [self.tail_pre.scale.shape[1]])
        self.to(dtype)
        self.eval()

    def _dense(self, x: torch.Tensor, scratch: torch.Tensor) -> torch.Tensor:
        c0, k = self.config.init_features, self.config.growth
        n, _, h, w = x.shape
        buf = torch.empty(n, self.width, h, w, dtype=x.dtype, memory_format=torch.channels_last)
        buf[:, :c0] = x
        for i, (conv1, conv3) in enumerate(zip(self.conv1, self.conv3)):
            cin = c0 + i * k
            buf[:, cin:cin + k] = conv3(conv1(buf[:, :cin], scratch))
        return buf

    def _plain(self, x: torch.Tensor, scratch: torch.Tensor) -> torch.Tensor:
        for conv1, conv3 in zip(self.conv1, self.conv3):
            x = conv3(conv1(x, scratch))
        return x

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = padded_input(image).to(self.dtype).permute(0, 3, 1, 2)
        x = self.head(x)
        n, _, h, w = x.shape
        scratch = torch.empty(n * self.clamp_width * h * w, dtype=self.dtype)  # the clamps' (scratch_view)
        x = self._dense(x, scratch) if self.config.arch == "densenet" else self._plain(x, scratch)
        out = self.tail(self.tail_pre(x, scratch)).float()
        return out + image[:, :3] if self.config.output == "residual" else out
