"""The rendering core: load a prepared scene, render at a given spp/seed, return linear radiance.

Every render goes through :mod:`pipeline.scene_io`, so it uses a box pixel filter and a float32
film. Large sample counts are split into passes (independent seeds) whose mean is returned, so
memory stays bounded by ``max_samples_per_pass`` samples in flight.
"""
from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.backend import select_variant
from pipeline.errors import RenderError, SceneError
from pipeline.scene_io import AOV_TYPES, PreparedScene, prepare_dict, prepare_xml

DEFAULT_MAX_SAMPLES_PER_PASS = 1 << 24
MAX_SEED = 2**32 - 1


@dataclass
class RenderResult:
    """A render: ``rgb`` is HxWx3 float32 linear radiance, finite.

    ``aovs`` maps each requested AOV name to an HxWx3 float32 array. ``nonfinite`` counts the
    pixels that had a NaN/Inf channel (replaced by 0). ``seconds`` is the render's wall time.
    ``variance`` (renders made of two halves, else None) may hold NaN/Inf where a sample did.
    """

    rgb: np.ndarray
    aovs: dict[str, np.ndarray] = field(default_factory=dict)
    spp: int = 0
    seed: int = 0
    nonfinite: int = 0
    seconds: float = 0.0
    variant: str = ""
    variance: np.ndarray | None = None  # HxWx3 variance of ``rgb``'s estimate (``halves`` renders)


def _one_line(exc: BaseException) -> str:
    """Mitsuba's messages span several lines with source locations; keep the informative one."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    for ln in reversed(lines):
        if "rror" in ln or "not found" in ln or "nknown" in ln:
            return ln.split("] ", 1)[-1]
    return lines[-1] if lines else type(exc).__name__


def load_scene(prepared: PreparedScene) -> Any:
    """Load a :class:`PreparedScene` into a ``mi.Scene``; raises :class:`SceneError` on failure."""
    select_variant()
    import mitsuba as mi

    resolver = mi.file_resolver()
    saved = [str(p) for p in resolver]
    try:
        for path in reversed(prepared.search_paths):
            resolver.prepend(str(path))
        if prepared.scene_dict is not None:
            scene = mi.load_dict(prepared.scene_dict)
        else:
            scene = mi.load_string(prepared.xml, **prepared.params)
    except Exception as exc:  # Mitsuba raises RuntimeError/ValueError/TypeError on bad scenes
        raise SceneError(f"{prepared.source}: {_one_line(exc)}") from None
    finally:
        resolver.clear()
        for p in saved:
            resolver.append(p)
    _check_box_filter(scene, prepared.source)
    _check_renderable(scene, prepared.source)
    return scene


def _check_box_filter(scene: Any, source: str) -> None:
    for sensor in scene.sensors():
        name = str(sensor.film().rfilter()).split("[", 1)[0].strip()
        if name != "BoxFilter":
            raise SceneError(f"{source}: film pixel filter is {name}, expected BoxFilter")


def _check_renderable(scene: Any, source: str) -> None:
    """What ``mi.render`` would otherwise fail on with a multi-line error or a bare ``Exception``."""
    if scene.integrator() is None:
        raise SceneError(f"{source}: the scene has no <integrator> (add e.g. <integrator type=\"path\"/>)")
    for sensor in scene.sensors():
        width, height = (int(v) for v in sensor.film().crop_size())
        if width < 1 or height < 1:
            raise SceneError(f"{source}: film size is {width}x{height}; it must be at least 1x1")


def prepare(
    scene: str | Path | Mapping[str, Any],
    resolution: tuple[int, int] | None = None,
    aovs: Sequence[str] = (),
    params: Mapping[str, Any] | None = None,
    base_dir: str | Path | None = None,
) -> PreparedScene:
    """Prepare a scene file path or scene dict (see :mod:`pipeline.scene_io`).

    ``base_dir`` resolves a dict scene's relative asset paths (XML scenes use their own folder).
    """
    if resolution is not None:
        w, h = resolution
        if int(w) < 1 or int(h) < 1:
            raise RenderError(f"resolution must be positive, got {w}x{h}")
        resolution = (int(w), int(h))
    if isinstance(scene, Mapping):
        if params:
            raise SceneError("<dict scene>: $parameters apply to XML scene files only")
        return prepare_dict(scene, resolution, aovs, base_dir=base_dir)
    return prepare_xml(scene, resolution, aovs, params)


def sanitize_nonfinite(img: np.ndarray) -> tuple[np.ndarray, int]:
    """Replace NaN/Inf values of an HxWxC image by 0; return it and the count of bad pixels."""
    img = np.array(img, dtype=np.float32, copy=True)
    bad = ~np.isfinite(img)
    img[bad] = 0.0
    return img, int(bad.any(axis=2).sum())


def pass_seeds(seed: int, passes: int) -> list[int]:
    """Seeds of the passes of one render: pass 0 uses ``seed``, later ones a 32-bit mix of it."""
    seeds = [seed]
    for i in range(1, passes):
        x = (seed * 0x9E3779B1 + i * 0x85EBCA77) & 0xFFFFFFFF
        x ^= x >> 16
        x = (x * 0x7FEB352D) & 0xFFFFFFFF
        x ^= x >> 15
        seeds.append(x)
    return seeds


def _accumulate(scene: Any, spp: int, seed: int, max_samples_per_pass: int) -> np.ndarray:
    """Mean of ``spp`` samples per pixel in passes of bounded size (independent seeds), float64."""
    import mitsuba as mi

    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    per_pass = max(1, min(spp, max_samples_per_pass // max(1, width * height)))
    passes = math.ceil(spp / per_pass)
    counts = [per_pass] * (passes - 1) + [spp - per_pass * (passes - 1)]
    acc: np.ndarray | None = None
    for n, s in zip(counts, pass_seeds(seed, passes)):
        img = np.array(mi.render(scene, spp=n, seed=s), dtype=np.float64) * (n / spp)
        acc = img if acc is None else acc + img
    assert acc is not None
    return acc


def render_loaded(
    scene: Any,
    spp: int,
    seed: int = 0,
    aovs: Sequence[str] = (),
    max_samples_per_pass: int = DEFAULT_MAX_SAMPLES_PER_PASS,
    halves: bool = False,
) -> RenderResult:
    """Render an already loaded scene (prepared with the same ``aovs``).

    ``halves`` (spp >= 2): render the samples as two independent halves (seeds ``seed`` and a mix
    of it) and also return ``variance``, the per-pixel variance estimate of the combined mean
    (:func:`pipeline.noise_guard.half_variance`); the image has the same expectation and spp.
    """
    if isinstance(spp, bool) or not isinstance(spp, int) or spp < 1:
        raise RenderError(f"spp must be a positive integer, got {spp!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise RenderError(f"seed must be an integer in [0, 2^32), got {seed!r}")
    import mitsuba as mi

    start = time.perf_counter()
    variance = None
    if halves and spp >= 2:
        from pipeline.noise_guard import half_variance

        n_a = spp // 2
        seed_b = pass_seeds(seed ^ 0x5A5A5A5A, 2)[1]
        a = _accumulate(scene, n_a, seed, max_samples_per_pass)
        b = _accumulate(scene, spp - n_a, seed_b, max_samples_per_pass)
        acc = a * (n_a / spp) + b * ((spp - n_a) / spp)
        with np.errstate(invalid="ignore", over="ignore"):
            variance = half_variance(a[:, :, :3], b[:, :, :3], n_a, spp - n_a)
    else:
        acc = _accumulate(scene, spp, seed, max_samples_per_pass)
    seconds = time.perf_counter() - start
    expected = 3 + 3 * len(aovs)
    if acc.shape[2] != expected:
        raise RenderError(f"render returned {acc.shape[2]} channels, expected {expected}")
    data, nonfinite = sanitize_nonfinite(acc.astype(np.float32))
    out_aovs = {name: data[:, :, 3 + 3 * i: 6 + 3 * i] for i, name in enumerate(aovs)}
    return RenderResult(rgb=np.ascontiguousarray(data[:, :, :3]), aovs=out_aovs, spp=spp, seed=seed,
                        nonfinite=nonfinite, seconds=seconds, variant=mi.variant(), variance=variance)


def render(
    scene: str | Path | Mapping[str, Any],
    spp: int,
    seed: int = 0,
    resolution: tuple[int, int] | None = None,
    aovs: Sequence[str] = (),
    params: Mapping[str, Any] | None = None,
    max_samples_per_pass: int = DEFAULT_MAX_SAMPLES_PER_PASS,
    base_dir: str | Path | None = None,
    halves: bool = False,
) -> RenderResult:
    """Load and render a scene file or dict with a box filter and a float32 film.

    ``resolution`` is (width, height); ``aovs`` names extra buffers from ``AOV_TYPES`` (rendered
    only when asked for); ``params`` fills an XML scene's ``$name`` parameters; ``base_dir``
    resolves a dict scene's relative asset paths; ``halves``: see :func:`render_loaded`.
    """
    loaded = load_scene(prepare(scene, resolution, aovs, params, base_dir))
    return render_loaded(loaded, spp, seed, aovs, max_samples_per_pass, halves)


__all__ = ["AOV_TYPES", "RenderResult", "load_scene", "prepare", "render", "render_loaded"]
