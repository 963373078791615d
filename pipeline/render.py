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
    """

    rgb: np.ndarray
    aovs: dict[str, np.ndarray] = field(default_factory=dict)
    spp: int = 0
    seed: int = 0
    nonfinite: int = 0
    seconds: float = 0.0
    variant: str = ""


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


def render_loaded(
    scene: Any,
    spp: int,
    seed: int = 0,
    aovs: Sequence[str] = (),
    max_samples_per_pass: int = DEFAULT_MAX_SAMPLES_PER_PASS,
) -> RenderResult:
    """Render an already loaded scene (prepared with the same ``aovs``)."""
    if isinstance(spp, bool) or not isinstance(spp, int) or spp < 1:
        raise RenderError(f"spp must be a positive integer, got {spp!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise RenderError(f"seed must be an integer in [0, 2^32), got {seed!r}")
    import mitsuba as mi

    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    per_pass = max(1, min(spp, max_samples_per_pass // max(1, width * height)))
    passes = math.ceil(spp / per_pass)
    counts = [per_pass] * (passes - 1) + [spp - per_pass * (passes - 1)]
    start = time.perf_counter()
    acc: np.ndarray | None = None
    for n, s in zip(counts, pass_seeds(seed, passes)):
        img = np.array(mi.render(scene, spp=n, seed=s), dtype=np.float64) * (n / spp)
        acc = img if acc is None else acc + img
    seconds = time.perf_counter() - start
    assert acc is not None
    expected = 3 + 3 * len(aovs)
    if acc.shape[2] != expected:
        raise RenderError(f"render returned {acc.shape[2]} channels, expected {expected}")
    data, nonfinite = sanitize_nonfinite(acc.astype(np.float32))
    out_aovs = {name: data[:, :, 3 + 3 * i: 6 + 3 * i] for i, name in enumerate(aovs)}
    return RenderResult(rgb=np.ascontiguousarray(data[:, :, :3]), aovs=out_aovs, spp=spp, seed=seed,
                        nonfinite=nonfinite, seconds=seconds, variant=mi.variant())


def render(
    scene: str | Path | Mapping[str, Any],
    spp: int,
    seed: int = 0,
    resolution: tuple[int, int] | None = None,
    aovs: Sequence[str] = (),
    params: Mapping[str, Any] | None = None,
    max_samples_per_pass: int = DEFAULT_MAX_SAMPLES_PER_PASS,
    base_dir: str | Path | None = None,
) -> RenderResult:
    """Load and render a scene file or dict with a box filter and a float32 film.

    ``resolution`` is (width, height); ``aovs`` names extra buffers from ``AOV_TYPES`` (rendered
    only when asked for); ``params`` fills an XML scene's ``$name`` parameters; ``base_dir``
    resolves a dict scene's relative asset paths.
    """
    loaded = load_scene(prepare(scene, resolution, aovs, params, base_dir))
    return render_loaded(loaded, spp, seed, aovs, max_samples_per_pass)


__all__ = ["AOV_TYPES", "RenderResult", "load_scene", "prepare", "render", "render_loaded"]
