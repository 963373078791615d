"""The maths of speed against accuracy: Pareto frontier and equal-quality savings. No I/O.

A *point* is one way of making an image: its total wall time (render + denoise, seconds, > 0)
and its error against the reference (> 0, lower is better). The *noisy curve* is the raw render's
error as a function of spp; Monte Carlo error falls as a power of spp (relMSE ~ 1/spp), so it is
interpolated and inverted linearly in log(spp)-log(error). The *equal-quality saving* of a
denoised point is how long a raw render needs to reach the same error, divided by the point's own
total time.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# metric name -> how it becomes an error (> 0, lower is better); PSNR becomes its MSE.
ERROR_OF_METRIC = {
    "relmse": lambda v: v,
    "psnr": lambda v: 10.0 ** (-v / 10.0),
    "flip": lambda v: v,
}
ERROR_LABEL = {"relmse": "relMSE", "psnr": "tonemapped MSE (10^(-PSNR/10))", "flip": "mean FLIP"}


def metric_error(metric: str, value: float | None) -> float:
    """The error (> 0, lower is better) that ``value`` of ``metric`` stands for; PSNR None/inf -> 0."""
    if metric not in ERROR_OF_METRIC:
        raise ValueError(f"unknown metric {metric!r} (known: {', '.join(ERROR_OF_METRIC)})")
    if value is None:
        return 0.0
    return float(ERROR_OF_METRIC[metric](float(value)))


def pareto_front(times: Sequence[float], errors: Sequence[float]) -> list[int]:
    """Indices of the points no other point beats in both time and error, fastest first.

    A point is dropped when another is at most as slow and at most as wrong (and not identical in
    both; of identical points the first is kept). Non-finite points are never on the front.
    """
    if len(times) != len(errors):
        raise ValueError(f"{len(times)} times but {len(errors)} errors")
    ok = [i for i in range(len(times)) if math.isfinite(times[i]) and math.isfinite(errors[i])]
    order = sorted(ok, key=lambda i: (times[i], errors[i], i))
    front: list[int] = []
    best = math.inf
    for i in order:
        if errors[i] < best:
            front.append(i)
            best = errors[i]
    return front


def _monotone(spp: Sequence[float], errors: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Sorted (log spp, log error) of the running-minimum envelope, strictly decreasing in error."""
    pairs = sorted((float(s), float(e)) for s, e in zip(spp, errors)
                   if s > 0 and e > 0 and math.isfinite(e))
    xs: list[float] = []
    ys: list[float] = []
    for s, e in pairs:
        if not ys or math.log(e) < ys[-1]:
            xs.append(math.log(s))
            ys.append(math.log(e))
    return np.array(xs), np.array(ys)


def _tail_slope(xs: np.ndarray, ys: np.ndarray, count: int) -> float:
    """Least-squares slope of the last (or first, for negative ``count``) |count| points."""
    sel = slice(-count, None) if count > 0 else slice(None, -count)
    x, y = xs[sel], ys[sel]
    return float(np.polyfit(x, y, 1)[0]) if len(x) >= 2 else math.nan


def error_at_spp(spp: Sequence[float], errors: Sequence[float], target: float) -> float:
    """A measured error curve read at ``target`` spp: linear in log-log between points; outside
    them the end segment's power law, flattened where it would rise (more samples never hurt)."""
    pairs = sorted((math.log(s), math.log(e)) for s, e in zip(spp, errors)
                   if s > 0 and e > 0 and math.isfinite(e))
    if not pairs or target <= 0:
        return math.nan
    xs, ys = [p[0] for p in pairs], [p[1] for p in pairs]
    x = math.log(target)
    if len(pairs) == 1 or xs[0] <= x <= xs[-1]:
        return float(math.exp(np.interp(x, xs, ys)))
    i, j = (-2, -1) if x > xs[-1] else (0, 1)
    slope = min(0.0, (ys[j] - ys[i]) / (xs[j] - xs[i])) if xs[j] != xs[i] else 0.0
    end = j if x > xs[-1] else i
    return float(math.exp(ys[end] + slope * (x - xs[end])))


@dataclass(frozen=True)
class EqualSpp:
    """Raw spp at which the noisy curve reaches a target error; ``extrapolated`` when outside
    the measured range (then along the fitted power law of the curve's end)."""

    spp: float
    extrapolated: bool


def spp_at_error(spp: Sequence[float], errors: Sequence[float], target: float,
                 fit_points: int = 3) -> EqualSpp:
    """Invert the noisy curve: the spp whose raw error equals ``target`` (log-log interpolation).

    Noise in the measurements can make the curve rise locally; its running minimum is used. Beyond
    the measured range the curve is extended by a least-squares power law through its last (or
    first) ``fit_points`` points. NaN when the curve cannot be inverted (fewer than 2 usable points,
    or a non-decreasing end); +inf spp for a target error of 0.
    """
    if target <= 0:
        return EqualSpp(math.inf, True)
    xs, ys = _monotone(spp, errors)
    if len(xs) < 2:
        return EqualSpp(math.nan, True)
    y = math.log(target)
    if ys[-1] <= y <= ys[0]:
        # ys is strictly decreasing: interpolate on the reversed arrays
        return EqualSpp(float(math.exp(np.interp(y, ys[::-1], xs[::-1]))), False)
    beyond = y < ys[-1]
    slope = _tail_slope(xs, ys, fit_points if beyond else -fit_points)
    if not slope < 0:
        return EqualSpp(math.nan, True)
    anchor = -1 if beyond else 0
    return EqualSpp(float(math.exp(xs[anchor] + (y - ys[anchor]) / slope)), True)


def time_at_spp(spp: Sequence[float], seconds: Sequence[float], target: float) -> float:
    """Render time at ``target`` spp: piecewise linear in spp between measured points, and
    beyond them the straight line (fixed cost + cost per sample) through the two nearest ends."""
    pairs = sorted(zip((float(s) for s in spp), (float(t) for t in seconds)))
    if not pairs:
        raise ValueError("no render times to interpolate")
    if not math.isfinite(target):
        return math.inf
    if len(pairs) == 1:
        return pairs[0][1] * target / pairs[0][0]
    xs, ts = [p[0] for p in pairs], [p[1] for p in pairs]
    if xs[0] <= target <= xs[-1]:
        return float(np.interp(target, xs, ts))
    (s0, t0), (s1, t1) = (pairs[-2], pairs[-1]) if target > xs[-1] else (pairs[0], pairs[1])
    per_sample = (t1 - t0) / (s1 - s0) if s1 != s0 else 0.0
    if per_sample <= 0:  # timing noise: fall back to the mean cost per sample at that end
        per_sample = (t1 / s1) if target > xs[-1] else (t0 / s0)
    base_s, base_t = (s1, t1) if target > xs[-1] else (s0, t0)
    return max(0.0, base_t + (target - base_s) * per_sample)


@dataclass(frozen=True)
class EqualQuality:
    """A denoised point against the raw render of the same error.

    ``raw_spp``: spp the raw render needs for that error; ``raw_s``: its render time;
    ``saving``: raw_s / the point's total time (> 1: the denoiser saves time);
    ``spp_ratio``: raw_spp / the point's spp.
    """

    raw_spp: float
    raw_s: float
    saving: float
    spp_ratio: float
    extrapolated: bool


def equal_quality(noisy_spp: Sequence[float], noisy_errors: Sequence[float],
                  noisy_seconds: Sequence[float], spp: float, total_s: float,
                  error: float) -> EqualQuality:
    """Equal-quality saving of one denoised point (``spp``, ``total_s``, ``error``)."""
    eq = spp_at_error(noisy_spp, noisy_errors, error)
    if math.isnan(eq.spp):
        return EqualQuality(math.nan, math.nan, math.nan, math.nan, True)
    raw_s = time_at_spp(noisy_spp, noisy_seconds, eq.spp)
    saving = raw_s / total_s if total_s > 0 else math.inf
    return EqualQuality(eq.spp, raw_s, saving, eq.spp / spp, eq.extrapolated)
