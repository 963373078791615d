"""What one image tells about its own noise where no halves, spp or file attribute says it.

Two statistics of ``x = log(1 + R + G + B)`` (log: a firefly does not dominate), each a median over
the pixels where the image is not flat, computed on row strips:

* ``level``: the noise's standard deviation in ``x``, from the Nyquist-frequency response
  ``h = [1, -2, 1] (x) [1, -2, 1]`` (a checkerboard detector: zero on any linear ramp). For white
  noise of deviation s the response has deviation 6 s and ``median |h x| = 0.6745 * 6 s``.
* ``ratio``: ``median |h x|`` over ``median |g x|`` with ``g = [1, 0, -2, 0, 1] (x) [1, 0, -2, 0, 1]``,
  the same filter at half the frequency. Both have the same energy for white noise, so the ratio
  of a box-filtered render (every sample in one pixel: independent pixels) is near 1, while a
  render through a wider pixel filter (Mitsuba's default Gaussian, a tent) spreads each sample over
  neighbours, which removes the Nyquist band. Measured on eval scenes at 128^2
  (benchmarks/image_noise.py): box 0.75-0.98, tent 0.50-0.64, Gaussian 0.40-0.51 at 4-1024 spp;
  the box's falls with spp as the image's own detail takes over the residual.

Neither needs the whole image in memory: strips of ``STRIP_ROWS`` rows, at most
``MAX_SAMPLED_ROWS`` rows in all (evenly spread), each strip's responses kept as float32.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FILTERED_BELOW = 0.55  # ratio under which the noise is called filtered (benchmarks/image_noise.py)
STRIP_ROWS = 64
MAX_SAMPLED_ROWS = 1024
_MEDIAN_TO_SIGMA = 0.6745 * 6.0
_NYQ = np.array([1.0, -2.0, 1.0], np.float32)
_MID = np.array([1.0, 0.0, -2.0, 0.0, 1.0], np.float32)


@dataclass(frozen=True)
class NoiseStats:
    """``level``: noise deviation in log(1 + R + G + B) (NaN where the image is flat); ``ratio``:
    Nyquist over half-Nyquist response (about 1 for independent pixels, NaN where flat);
    ``pixels``: how many pixels the medians saw."""

    level: float
    ratio: float
    pixels: int

    @property
    def filtered(self) -> bool:
        """True when the noise looks spread over neighbouring pixels by a pixel filter other than a box."""
        return bool(np.isfinite(self.ratio) and self.ratio < FILTERED_BELOW)


def _separable(x: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``kernel`` (x) ``kernel`` applied to 2-D ``x``, valid part only."""
    n = len(kernel)
    rows = sum(k * x[:, i:x.shape[1] - n + 1 + i] for i, k in enumerate(kernel) if k)
    return sum(k * rows[i:rows.shape[0] - n + 1 + i] for i, k in enumerate(kernel) if k)


def _strip_starts(height: int) -> list[int]:
    strips = -(-height // STRIP_ROWS)
    keep = max(1, MAX_SAMPLED_ROWS // STRIP_ROWS)
    if strips <= keep:
        return list(range(0, height, STRIP_ROWS))
    return [int(i * (strips - 1) / (keep - 1)) * STRIP_ROWS if keep > 1 else 0 for i in range(keep)]


def noise_stats(rgb: np.ndarray) -> NoiseStats:
    """:class:`NoiseStats` of HxWx3 linear radiance (non-finite and negative values count as 0)."""
    height, width = rgb.shape[:2]
    nyq_parts, mid_parts = [], []
    if height >= 5 and width >= 5:
        for y in _strip_starts(height):
            block = np.asarray(rgb[y:y + STRIP_ROWS + 4, :, :3], np.float64)  # float64: no sum overflows
            if block.shape[0] < 5:
                continue
            total = np.nan_to_num(block, nan=0.0, posinf=0.0, neginf=0.0).clip(0.0, None).sum(axis=2)
            x = np.log1p(total).astype(np.float32)
            nyq = np.abs(_separable(x, _NYQ))[1:-1, 1:-1]
            mid = np.abs(_separable(x, _MID))
            busy = (nyq > 0) | (mid > 0)
            nyq_parts.append(nyq[busy])
            mid_parts.append(mid[busy])
    nyq = np.concatenate(nyq_parts) if nyq_parts else np.empty(0, np.float32)
    mid = np.concatenate(mid_parts) if mid_parts else np.empty(0, np.float32)
    if nyq.size == 0:
        return NoiseStats(float("nan"), float("nan"), 0)
    med_nyq, med_mid = float(np.median(nyq)), float(np.median(mid))
    ratio = med_nyq / med_mid if med_mid > 0 else float("nan")
    return NoiseStats(med_nyq / _MEDIAN_TO_SIGMA, ratio, int(nyq.size))
