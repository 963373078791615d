"""Whole-image inference with a trained network: the one chain every caller uses.

exposure (an image whose log-average luminance lies outside the training data's range is scaled
by a power of two towards the training median, undone at the end) -> sanitise (NaN/Inf/negative
-> 0, > HDR_MAX clamped) -> transfer (+ the noise channels of :mod:`model.noise_input` for a model
that takes them) -> network on core tiles with a margin of the receptive-field radius, on the
network's alignment grid (exact: :mod:`denoise.tiling`) -> clamp in transfer space to [0, the
largest input value (of any channel) within ``BOUND_RADIUS`` pixels] (:func:`neighbourhood_max`; a
denoiser averages, so an output brighter than every input around it is a network failure, not
detail: the multi-scale nets were measured turning a firefly's neighbourhood into a patch of 65504,
benchmarks/results/evaluate.json; never above 1, radiance HDR_MAX, so nothing overflows to Inf)
-> inverse transfer -> undo the exposure. All of it tile by tile: no whole-image temporaries
besides the output. The caller sizes the tiles (:func:`tile_bytes_per_pixel` per window pixel);
the passes over the whole image (exposure, the skip test below) work in blocks within ``max_bytes``.

With a variance and ``skip_below``, the parts of the image whose noise is already below that
level (transfer-space standard deviation, per 64-px cell) are not run through the network: they
come back as the (sanitised) render, and the network runs on the smallest aligned rectangle that
holds every noisy cell, with its full margin, so its output there is unchanged.
Validation during training and :class:`denoise.denoiser.Denoiser` both call :func:`denoise_image`.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch import nn

from imaging.blocks import block_rows, parallel_map, pass_workers, row_blocks
from denoise.tiling import Core, Tile, region_tiles, run_windows
from model.architectures import alignment, inference_bytes_per_pixel, receptive_radius
from model.config import ModelConfig
from model.device import module_device
from denoise.flips import FLIPS, check_flips
from model.noise_input import noise_channels
from model.transfer import HDR_MAX, TransferFunction, get_transfer
from model.unet import pad_to_alignment
from rendering.camera import rotate_normals

SKIP_CELL = 64  # pixels per side of the cells the skip test looks at (a multiple of every alignment <= 64)
# Scratch of the passes over the whole image (log-average luminance, the skip test, sanitising)
# per pixel of a block, a bound of what benchmarks/denoise_memory.py measures; and their default
# bound when the caller gives none.
PASS_BYTES_PER_PIXEL = 320
DEFAULT_PASS_BYTES = 64 * 2**20
# Scratch of a tile's steps around the network (transfer, noise channels, output bound, inverse)
# per window pixel, beside its float32 input channels: a bound of what was measured with the
# network included (u-fast in bfloat16 with the noise input: 150 B/px at 1024^2); the network's
# own estimate is larger for every preset in float32.
TILE_CHAIN_BYTES_PER_PIXEL = 160
# One tile's fixed cost beside its pixels: the first forward pass's oneDNN kernels and reordered
# weights, the allocator's small blocks (benchmarks/denoise_memory.py --parts calibrate); and what
# each further network of another shape or float format adds (its own kernels: measured 11-18 MiB
# resident after a few windows of each shipped network).
TILE_FIXED_BYTES = 32 * 2**20
NETWORK_FIXED_BYTES = 16 * 2**20
Aux = np.ndarray | tuple[np.ndarray, np.ndarray] | None
# Radius of the window whose largest input value bounds each output value (at most the margin).
BOUND_RADIUS = 8


# Log-average luminance (geometric mean over pixels with luminance > 0; a firefly barely moves it)
# of the training references: data/train, 64 scenes, 4.6e-4 .. 2.25, median 0.085. Inside this band
# an image goes to the network as it is; outside, it is scaled by a power of two to near the median.
EXPOSURE_BAND = (2.5e-4, 4.0)
EXPOSURE_TARGET = 0.08
_LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def log_average_luminance(color: np.ndarray, rows: int = 256, workers: int = 1) -> float:
    """exp(mean(log L)) over the pixels of HxWx3 radiance whose luminance L is finite and > 0
    (0.0 if there are none); computed in blocks of ``rows`` rows, ``workers`` blocks at a time
    (:func:`imaging.blocks.parallel_map`; the same result), without a whole-image copy."""
    def block(y: int) -> tuple[float, int]:
        with np.errstate(invalid="ignore", over="ignore"):  # inf - inf: NaN, dropped below
            lum = np.asarray(color[y:y + rows], dtype=np.float64) @ _LUMINANCE
        lum = lum[np.isfinite(lum) & (lum > 0)]
        return float(np.log(lum).sum()), lum.size

    total, count = 0.0, 0
    for block_total, block_count in parallel_map(block, range(0, color.shape[0], rows), workers):
        total, count = total + block_total, count + block_count
    return math.exp(total / count) if count else 0.0


def exposure_scale(color: np.ndarray, rows: int = 256, workers: int = 1) -> float:
    """Power of two to multiply HxWx3 radiance by before the network, and divide its output by:
    1.0 when the log-average luminance lies inside ``EXPOSURE_BAND`` (or the image is black).
    A power of two scales without rounding; a very bright image (mean 1e3, emitters beyond
    65504) is then not clamped, and a very dark one (mean 1e-4) is seen as the network knows it.
    ``rows``, ``workers``: the blocks of :func:`log_average_luminance`."""
    key = log_average_luminance(color, rows, workers)
    if key == 0.0 or EXPOSURE_BAND[0] <= key <= EXPOSURE_BAND[1]:
        return 1.0
    return 2.0 ** min(64, max(-64, round(math.log2(EXPOSURE_TARGET / key))))


def sanitize(color: np.ndarray) -> np.ndarray:
    """float32 copy of HxWxC radiance with NaN and negatives -> 0, +Inf and > HDR_MAX -> HDR_MAX
    (three passes: 3x faster than nan_to_num + clip)."""
    out = np.array(color, dtype=np.float32)
    np.clip(out, 0.0, HDR_MAX, out=out)  # -Inf -> 0, +Inf -> HDR_MAX; NaN stays
    np.putmask(out, np.isnan(out), 0.0)
    return out


def _check_inputs(config: ModelConfig, color: np.ndarray, aux: Aux, variance: np.ndarray | None) -> None:
    if config.aux_inputs != (aux is not None):
        raise ValueError("aux buffers are required by this model" if config.aux_inputs
                         else "this model takes no aux buffers")
    if color.ndim != 3 or color.shape[2] != 3 or min(color.shape[:2]) < 1:
        raise ValueError(f"color must be HxWx3, got shape {color.shape}")
    if aux is not None:
        shapes = [np.shape(a) for a in (aux if isinstance(aux, (tuple, list)) else [aux])]
        if any(s[:2] != color.shape[:2] or len(s) != 3 for s in shapes) or sum(s[2] for s in shapes) != 6:
            raise ValueError(f"aux must be HxWx6 like the image (or HxWx3 albedo and normals), got "
                             f"shape {' and '.join(str(s) for s in shapes)}")
    if variance is not None and variance.shape != color.shape:
        raise ValueError(f"variance must be HxWx3 like the image, got shape {variance.shape}")


def _scaled(rgb: np.ndarray, scale: float) -> np.ndarray:
    """Sanitised float32 radiance times the exposure ``scale``."""
    if scale != 1.0:
        # a huge value may overflow to Inf, and Inf times a scale that is 0 in float32 is NaN: sanitised below
        with np.errstate(over="ignore", invalid="ignore"):
            rgb = np.asarray(rgb, np.float32) * np.float32(scale)
    return sanitize(rgb)


def tile_bytes_per_pixel(config: ModelConfig, folded: bool = True, itemsize: int = 4, flips: int = 1) -> float:
    """Peak scratch bytes per window pixel of one tile of :func:`denoise_image`, beyond
    :data:`TILE_FIXED_BYTES`: the forward pass (:func:`model.architectures.inference_bytes_per_pixel`)
    or the chain's steps around it (transfer, noise channels, inverse, with the input tensor),
    whichever needs more; with ``flips`` > 1, plus what :func:`flip_average` holds beside a
    forward pass (the padded and the mirrored input, float32; the sum, an output and its mirror,
    3 channels float32 each)."""
    flip_bytes = 8.0 * config.image_channels + 36.0 if flips > 1 else 0.0
    return max(inference_bytes_per_pixel(config, folded, itemsize) + flip_bytes,
               TILE_CHAIN_BYTES_PER_PIXEL + 4.0 * config.image_channels)


def noisy_region(color: np.ndarray, variance: np.ndarray, transfer: TransferFunction, scale: float,
                 threshold: float, align: int, max_bytes: float = DEFAULT_PASS_BYTES
                 ) -> tuple[int, int, int, int] | None:
    """The smallest rectangle (y0, y1, x0, x1), on ``SKIP_CELL``-px cells (multiples of ``align``),
    that holds every cell whose RMS transfer-space noise (:func:`model.noise_input.noise_channels`)
    is at least ``threshold``; None when no cell is. Computed a block of cells at a time, each
    within ``max_bytes`` of scratch (at least one cell)."""
    height, width = color.shape[:2]
    cell = max(align, SKIP_CELL // align * align)
    step = cell * max(1, int(max_bytes // (PASS_BYTES_PER_PIXEL * cell * cell)))  # columns per block
    rows: list[int] = []
    cols: set[int] = set()
    for y in range(0, height, cell):
        for x0 in range(0, width, step):
            block = slice(y, y + cell), slice(x0, x0 + step)
            strip = noise_channels(_scaled(color[block], scale),
                                   np.asarray(variance[block], np.float32) * np.float32(scale * scale),
                                   transfer)[..., :3]
            power = (strip * strip).sum(axis=2)
            for x in range(0, power.shape[1], cell):
                if float(power[:, x:x + cell].mean()) >= threshold * threshold:
                    rows.append(y)
                    cols.add(x0 + x)
    if not rows:
        return None
    return min(rows), min(height, max(rows) + cell), min(cols), min(width, max(cols) + cell)


def _window_max(x: torch.Tensor, dim: int, radius: int) -> torch.Tensor:
    """Largest value of ``x`` within ``radius`` along ``dim`` (the window clipped at the ends:
    the ends are repeated, which changes no maximum), by doubling: O(log radius) passes."""
    if radius == 0:
        return x
    n = x.shape[dim]
    reps = [1] * x.dim()
    reps[dim] = radius
    m = torch.cat([x.narrow(dim, 0, 1).repeat(reps), x, x.narrow(dim, n - 1, 1).repeat(reps)], dim)
    width, span = 1, 2 * radius + 1
    while 2 * width <= span:  # m[i] = max over [i, i + 2*width)
        m = torch.maximum(m.narrow(dim, 0, m.shape[dim] - width), m.narrow(dim, width, m.shape[dim] - width))
        width *= 2
    return torch.maximum(m.narrow(dim, 0, n), m.narrow(dim, span - width, n))


def neighbourhood_max(image: torch.Tensor, radius: int) -> torch.Tensor:
    """HxW: the largest value of HxWxC ``image`` (any channel) within the (2r+1)^2 window around
    each pixel, the window clipped at the image's border."""
    return _window_max(_window_max(image.amax(dim=2), 1, radius), 0, radius)


def flip_average(model: nn.Module, x: torch.Tensor, flips: int, align: int) -> torch.Tensor:
    """The mean of ``model``'s outputs over the ``flips`` mirrored copies of ``x`` (:mod:`denoise.flips`),
    each mirrored back. The input is first padded to the network's alignment (bottom and right,
    as the network itself pads), so that a mirrored tile window keeps the whole image's pooling
    grid and tiles stay exact; the output is cropped back."""
    if flips == 1:
        return model(x)
    h, w = x.shape[-2:]
    padded = pad_to_alignment(x, align)
    total = None
    for dims in FLIPS[flips]:
        y = model(padded.flip(dims)).flip(dims) if dims else model(padded)
        total = y if total is None else total.add_(y)
    return total.div_(len(FLIPS[flips]))[..., :h, :w]


def _aux_window(aux: Aux, t: Tile, normals_rotation: np.ndarray | None = None) -> torch.Tensor:
    """The tile window of the aux buffers as an hxwx6 float32 tensor, non-finite values -> 0, the
    normals multiplied by ``normals_rotation`` where one is given."""
    parts = aux if isinstance(aux, (tuple, list)) else [aux]
    window = np.concatenate([np.asarray(a[t.wy0:t.wy1, t.wx0:t.wx1], np.float32) for a in parts], axis=2)
    window = np.nan_to_num(window, nan=0.0, posinf=0.0, neginf=0.0)
    if normals_rotation is not None:
        window[..., 3:6] = rotate_normals(window[..., 3:6], normals_rotation)
    return torch.from_numpy(window)


def image_exposure(color: np.ndarray, max_bytes: float = DEFAULT_PASS_BYTES) -> float:
    """:func:`exposure_scale` of an HxWx3 image as :func:`denoise_image` computes it: blocks of at
    most 256 rows within ``max_bytes``, on the numpy passes' threads."""
    height, width = color.shape[:2]
    workers = pass_workers(height * width, torch.get_num_threads())
    blocks = workers * -(-height // (256 * workers))  # blocks of <= 256 rows, a multiple of workers
    return exposure_scale(color, block_rows(width, PASS_BYTES_PER_PIXEL, max_bytes / workers,
                                            -(-height // blocks)), workers)


class ChainRun:
    """One network's chain (the module docstring) over one image, a window or a rectangle at a
    time: what :func:`denoise_image` stitches, and what an ensemble computes member by member on
    shared tiles (:func:`denoise.ensemble.denoise_combined`). Arguments as :func:`denoise_image`'s;
    the skip test (``variance`` and ``skip_below``) runs when it is made. Use it as a context
    manager: the model runs in eval mode under ``torch.inference_mode`` inside, its previous mode
    restored after. ``windows``: the network windows run so far."""

    def __init__(self, model: nn.Module, color: np.ndarray, aux: Aux = None, variance: np.ndarray | None = None,
                 skip_below: float | None = None, max_bytes: float = DEFAULT_PASS_BYTES, flips: int = 1,
                 exposure: float | None = None, normals_rotation: np.ndarray | None = None) -> None:
        config = model.config
        _check_inputs(config, color, aux, variance)
        check_flips(flips)
        if flips > 1 and config.aux_inputs:  # a mirrored image has mirrored normals: not modelled
            raise ValueError("test-time flips need a model without albedo/normal inputs (flips 1 here)")
        self.model, self.config, self.color, self.aux, self.variance = model, config, color, aux, variance
        self.normals_rotation = normals_rotation
        self.flips, self.max_bytes = flips, max_bytes
        self.transfer = get_transfer(config.transfer)
        self.scale = image_exposure(color, max_bytes) if exposure is None else exposure
        self.align = alignment(config)
        self.margin = receptive_radius(config)
        self.radius = min(BOUND_RADIUS, self.margin)  # within the margin: tiles see the whole window
        self.device = module_device(model)
        self.skipping = variance is not None and skip_below is not None
        self.region = noisy_region(color, variance, self.transfer, self.scale, skip_below, self.align,
                                   max_bytes) if self.skipping else None
        self.windows = 0
        self._mode = torch.inference_mode()
        self._was_training = False

    def __enter__(self) -> ChainRun:
        self._was_training = self.model.training
        if self._was_training:  # (each switch walks every submodule: ~3 ms a call at 128^2 for a folded u-net)
            self.model.eval()
        self._mode.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._mode.__exit__(*exc)
        if self._was_training:
            self.model.train()

    def window(self, t: Tile) -> np.ndarray:
        """The chain's output over ``t``'s window (hxwx3 float32 radiance); exact over its core
        when the window has the network's margin and alignment (:mod:`denoise.tiling`)."""
        config, transfer, scale, color, variance, aux = (self.config, self.transfer, self.scale, self.color,
                                                         self.variance, self.aux)
        self.windows += 1
        h, w = t.wy1 - t.wy0, t.wx1 - t.wx0
        rgb = _scaled(color[t.wy0:t.wy1, t.wx0:t.wx1], scale)
        # filled part by part (no concatenation), each pixel's channels side by side as the folded
        # nets read them (denoise.inference_net.padded_input: 1.5x faster from channels_last at 720p)
        x = torch.empty(1, config.image_channels, h, w, memory_format=torch.channels_last)
        encoded = transfer.forward(torch.from_numpy(rgb))
        x[0, :3] = encoded.permute(2, 0, 1)
        if aux is not None:
            x[0, 3:9] = _aux_window(aux, t, self.normals_rotation).permute(2, 0, 1)
        if config.noise_input:
            var = None if variance is None else \
                np.asarray(variance[t.wy0:t.wy1, t.wx0:t.wx1], np.float32) * np.float32(scale * scale)
            x[0, config.noise_start:] = torch.from_numpy(
                noise_channels(rgb, var, transfer, config.noise_radius, encoded)).permute(2, 0, 1)
            del var
        bound = neighbourhood_max(encoded, self.radius)
        del rgb, encoded
        y = flip_average(self.model, x.to(self.device, non_blocking=True), self.flips, self.align)[0].cpu()
        del x  # (a GPU's output is back on the CPU here)
        y = torch.minimum(torch.nan_to_num_(y, nan=0.0).clamp_(0.0, 1.0), bound, out=y)
        del bound
        y = transfer.inverse(y).permute(1, 2, 0).numpy()
        return y if scale == 1.0 else np.divide(y, np.float32(scale), out=y)

    def rect(self, y0: int, y1: int, x0: int, x1: int, core: Core) -> np.ndarray:
        """The chain's output over the rectangle [y0:y1, x0:x1] (any corners) as :func:`denoise_image`
        gives it there: the rectangle cut into cores of at most ``core`` px, each run in a window
        with the network's margin taken from the whole image (the sanitised render outside the
        skip test's noisy region). A new (y1-y0)x(x1-x0)x3 float32 array."""
        height, width = self.color.shape[:2]
        a, b, c, d = y0, y1, x0, x1
        if self.skipping:
            out = self.render_copy(y0, y1, x0, x1)
            if self.region is None:
                return out
            ry0, ry1, rx0, rx1 = self.region
            a, b, c, d = max(y0, ry0), min(y1, ry1), max(x0, rx0), min(x1, rx1)
            if a >= b or c >= d:
                return out
        else:
            out = np.empty((y1 - y0, x1 - x0, 3), np.float32)
        for t in region_tiles(height, width, core, self.margin, self.align, (a, b, c, d)):
            out[t.y0 - y0:t.y1 - y0, t.x0 - x0:t.x1 - x0] = \
                self.window(t)[t.y0 - t.wy0:t.y1 - t.wy0, t.x0 - t.wx0:t.x1 - t.wx0]
        return out

    def render_copy(self, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        """The sanitised render over [y0:y1, x0:x1] (what the skip test leaves outside its noisy
        region), copied in row blocks within ``max_bytes``: a new float32 array."""
        out = np.empty((y1 - y0, x1 - x0, 3), np.float32)
        for rows in row_blocks(y1 - y0, x1 - x0, PASS_BYTES_PER_PIXEL, self.max_bytes):
            out[rows] = sanitize(self.color[y0 + rows.start:y0 + rows.stop, x0:x1])
        return out


def denoise_image(model: nn.Module, color: np.ndarray, aux: Aux = None,
                  core: Core = 256, progress: Callable[[int, int], None] | None = None,
                  variance: np.ndarray | None = None, skip_below: float | None = None,
                  max_bytes: float = DEFAULT_PASS_BYTES, flips: int = 1, exposure: float | None = None,
                  normals_rotation: np.ndarray | None = None) -> np.ndarray:
    """Denoise HxWx3 linear radiance -> HxWx3 float32 linear radiance >= 0 (at most HDR_MAX divided
    by :func:`exposure_scale`, i.e. HDR_MAX unless the image is unusually bright).

    ``model``: a network of :mod:`model.architectures` or its folded inference copy (anything
    with the ``config`` of the network). ``aux``: HxWx6 (albedo RGB in [0,1], normal XYZ in
    [-1,1]), or the two HxWx3 buffers as a pair; required iff the model was built with
    ``aux_inputs``; its normals in the frame the model's ``aux_normals`` names, or turned into it
    by ``normals_rotation`` (3x3, ``n -> R @ n`` per pixel, tile by tile: world normals and
    :func:`rendering.camera.sensor_rotation` for a model that takes them in camera space). ``variance``: HxWx3 variance
    estimate of the image's mean (two halves); fed to a model with ``noise_input`` (without it
    such a model is told the noise is unknown) and used by ``skip_below`` (see the module
    docstring). ``core``: tile core side in pixels, or (rows, columns) (memory bound of the tiles,
    :func:`tile_bytes_per_pixel`; the result does not depend on it). ``max_bytes``: scratch
    bound of the passes over the whole image (exposure, the skip test, copying skipped parts);
    the result does not depend on it either. ``flips``: average the network over 1, 2 or 4
    mirrored copies of each window (:func:`flip_average`; more time, a little more accuracy,
    docs/experiments.md). ``exposure``: :func:`image_exposure` of ``color`` when the caller has it
    (several models on one image), else computed here. The model runs in eval mode; its previous
    mode is restored. A model on a GPU gets each tile's input there; the rest runs on the CPU.
    """
    run = ChainRun(model, color, aux, variance, skip_below, max_bytes, flips, exposure, normals_rotation)
    height, width = color.shape[:2]
    out = None
    if run.skipping:
        out = run.render_copy(0, height, 0, width)
        if run.region is None:
            return out
    with run:
        out = run_windows(run.window, height, width, core, run.margin, progress, run.align, out, run.region)
    return out.astype(np.float32, copy=False)
