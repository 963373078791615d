"""The rendering core: load a prepared scene, render at a given spp/seed, return linear radiance.

Every render goes through :mod:`rendering.scene_io`, so it uses a box pixel filter (or the filter
the prepared scene names) and a float32 film. Large sample counts are split into passes (independent seeds) of at most
``max_samples_per_pass`` samples, whose mean is returned. A film too large for the memory budget
is rendered in crops (:mod:`rendering.render_crops`), each written straight into the output images.
:func:`render_aovs` renders a loaded scene's AOVs alone (Mitsuba's aov integrator in place of the
scene's) on the camera rays of its render.
"""
from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rendering.backend import select_variant
from rendering.camera import sensor_rotation
from imaging.errors import RenderError, SceneError
from imaging.memory_limit import require_memory
from rendering.render_crops import (IMAGE_BYTES_PER_PIXEL, Crop, crop_layout, crop_seed, cropped, film_window,
                                    max_crop_pixels, render_bytes)
from rendering.scene_io import (AOV_TYPES, FILTER_CLASSES, PreparedScene, aov_spec, check_aovs, prepare_dict,
                                prepare_xml)

DEFAULT_MAX_SAMPLES_PER_PASS = 1 << 24
DEFAULT_MAX_MEMORY_MB = 1024.0  # the commands' --max-memory-mb default
MAX_SEED = 2**32 - 1
Progress = Callable[[int, int], None]  # (samples rendered so far, samples in all) after each pass


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
    crops: int = 1  # film crops rendered one after the other (rendering.render_crops)
    pixel_filter: str = "box"  # the film's reconstruction filter (a box unless the prepared scene named another)
    # 3x3 rotation taking world directions into the sensor's frame (rendering.camera; None: unknown)
    to_camera: np.ndarray | None = None


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
    _check_filter(scene, prepared.source, prepared.pixel_filter["type"])
    _check_renderable(scene, prepared.source)
    return scene


_FILTER_NAMES = {cls: name for name, cls in FILTER_CLASSES.items()}  # BoxFilter -> box


def _filter_class(sensor: Any) -> str:
    return str(sensor.film().rfilter()).split("[", 1)[0].strip()


def filter_class(scene: Any) -> str:
    """Class name of the first sensor's pixel filter (``BoxFilter``, ``GaussianFilter``...)."""
    return _filter_class(scene.sensors()[0])


def _check_filter(scene: Any, source: str, kind: str) -> None:
    expected = FILTER_CLASSES[kind]
    for sensor in scene.sensors():
        name = _filter_class(sensor)
        if name != expected:
            raise SceneError(f"{source}: film pixel filter is {name}, expected {expected}")


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
    pixel_filter: str | Mapping[str, Any] | None = None,
) -> PreparedScene:
    """Prepare a scene file path or scene dict (see :mod:`rendering.scene_io`).

    ``base_dir`` resolves a dict scene's relative asset paths (XML scenes use their own folder);
    ``pixel_filter``: the films' filter (a box unless named, :func:`rendering.scene_io.pixel_filter_spec`).
    """
    if resolution is not None:
        w, h = resolution
        if int(w) < 1 or int(h) < 1:
            raise RenderError(f"resolution must be positive, got {w}x{h}")
        resolution = (int(w), int(h))
    if isinstance(scene, Mapping):
        if params:
            raise SceneError("<dict scene>: $parameters apply to XML scene files only")
        return prepare_dict(scene, resolution, aovs, base_dir=base_dir, pixel_filter=pixel_filter)
    return prepare_xml(scene, resolution, aovs, params, pixel_filter)


def zero_nonfinite(img: np.ndarray) -> np.ndarray:
    """Set the NaN/Inf values of an HxWxC image to 0 in place; return the HxW mask of the pixels
    that had one."""
    finite = np.isfinite(img)
    img[~finite] = 0.0
    return ~finite.all(axis=2)


def pass_seed(seed: int, index: int) -> int:
    """Seed of pass ``index`` of one render: pass 0 uses ``seed``, later ones a 32-bit mix of it."""
    if index == 0:
        return seed
    x = (seed * 0x9E3779B1 + index * 0x85EBCA77) & 0xFFFFFFFF
    x ^= x >> 16
    x = (x * 0x7FEB352D) & 0xFFFFFFFF
    x ^= x >> 15
    return x


def pass_seeds(seed: int, passes: int) -> list[int]:
    """Seeds of the first ``passes`` passes of one render (:func:`pass_seed`)."""
    return [pass_seed(seed, i) for i in range(passes)]


def _accumulate(scene: Any, spp: int, seed: int, max_samples_per_pass: int,
                advance: Callable[[int], None], integrator: Any = None) -> np.ndarray:
    """Mean of ``spp`` samples per pixel of the film's current crop window in passes of at most
    ``max_samples_per_pass`` samples (independent seeds), float64 HxWxC; ``advance(samples)``
    after each pass; ``integrator``: another than the scene's. Nothing is kept per pass: any spp
    takes the same memory."""
    import mitsuba as mi

    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    per_pass = max(1, min(spp, max_samples_per_pass // max(1, width * height)))
    passes = math.ceil(spp / per_pass)
    acc: np.ndarray | None = None
    for index in range(passes):
        n = per_pass if index < passes - 1 else spp - per_pass * (passes - 1)
        # np.asarray views Mitsuba's image (no float32 copy); the product is float64(x) * (n/spp)
        img = np.multiply(np.asarray(mi.render(scene, spp=n, seed=pass_seed(seed, index), integrator=integrator)),
                          n / spp,
                          dtype=np.float64)
        if acc is None:
            acc = img
        else:
            acc += img
        del img
        advance(n * width * height)
    assert acc is not None
    return acc


def _render_crop(scene: Any, spp: int, seed: int, max_samples_per_pass: int,
                 halves: bool, advance: Callable[[int], None],
                 integrator: Any = None) -> tuple[np.ndarray, np.ndarray | None]:
    """The film's current crop window: float64 HxWxC mean and, for ``halves``, the variance of
    its radiance (None with another ``integrator`` than the scene's: it renders AOVs alone)."""
    if not halves:
        return _accumulate(scene, spp, seed, max_samples_per_pass, advance, integrator), None
    n_a = spp // 2
    seed_b = pass_seed(seed ^ 0x5A5A5A5A, 1)
    a = _accumulate(scene, n_a, seed, max_samples_per_pass, advance, integrator)
    b = _accumulate(scene, spp - n_a, seed_b, max_samples_per_pass, advance, integrator)
    variance = None
    if integrator is None:
        with np.errstate(invalid="ignore", over="ignore"):
            variance = half_variance(a[:, :, :3], b[:, :, :3], n_a, spp - n_a)
    a *= n_a / spp  # in place, the same values as a * (n_a / spp) + b * (n_b / spp)
    b *= (spp - n_a) / spp
    a += b
    return a, variance


def half_variance(half_a: np.ndarray, half_b: np.ndarray, spp_a: int, spp_b: int) -> np.ndarray:
    """Per-pixel, per-channel variance estimate of the combined mean of two independent halves."""
    if half_a.shape != half_b.shape:
        raise ValueError(f"halves differ in shape: {half_a.shape} vs {half_b.shape}")
    if spp_a < 1 or spp_b < 1:
        raise ValueError(f"each half needs at least one sample, got {spp_a} and {spp_b}")
    n = spp_a + spp_b
    diff = np.asarray(half_a, np.float64) - np.asarray(half_b, np.float64)
    return (diff * diff * (spp_a * spp_b / (n * n))).astype(np.float32)


def _store(acc: np.ndarray, outputs: list[np.ndarray], crop: Crop) -> int:
    """Write a crop's float64 channels into the float32 outputs (3 channels each), NaN/Inf
    replaced by 0; return the count of pixels that had one."""
    x, y, w, h = crop
    bad = np.zeros((h, w), bool)
    for i, out in enumerate(outputs):
        view = out[y:y + h, x:x + w]
        view[...] = acc[:, :, 3 * i: 3 * i + 3]
        bad |= zero_nonfinite(view)
    return int(bad.sum())


def check_render_memory(width: int, height: int, aovs: Sequence[str] = (), halves: bool = False,
                        max_memory_mb: float | None = DEFAULT_MAX_MEMORY_MB, held: Sequence[str] = (),
                        source: str = "") -> None:
    """Raise :class:`RenderError` naming the size, the bytes and the memory left when a ``width`` x
    ``height`` render with ``aovs`` (and its variance with ``halves``; the scratch of its crops
    under ``max_memory_mb``, :func:`rendering.render_crops.render_bytes`) does not fit in the
    memory left (:mod:`imaging.memory_limit`), or the float32 images of that size that the caller
    holds beside them at once do not: ``held`` names them ("denoised", "reference"). Called before
    anything is allocated or rendered; ``source`` (the scene file) begins the message."""
    images = ["rgb", *aovs, *(["variance"] if halves else []), *held]
    channels = 3 + 3 * len(aovs)
    need = max(render_bytes(width, height, channels, halves, max_memory_mb),
               len(images) * width * height * IMAGE_BYTES_PER_PIXEL)
    plural = "s" if len(images) > 1 else ""
    require_memory(need, f"{source + ': ' if source else ''}{width}x{height} pixels: {len(images)} float32 "
                   f"image{plural} ({', '.join(images)}) and the render's scratch", RenderError)


def _check_spp_seed(spp: int, seed: int) -> None:
    if isinstance(spp, bool) or not isinstance(spp, int) or spp < 1:
        raise RenderError(f"spp must be a positive integer, got {spp!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= MAX_SEED:
        raise RenderError(f"seed must be an integer in [0, 2^32), got {seed!r}")


@dataclass
class _Film:
    """What :func:`_render_film` gives: the film's images (3 channels each, in the film's order),
    the radiance's variance (``halves`` with radiance) and how it went."""

    images: list[np.ndarray]
    variance: np.ndarray | None
    nonfinite: int
    crops: int


def _render_film(scene: Any, spp: int, seed: int, images: int, max_samples_per_pass: int, halves: bool,
                 max_memory_mb: float | None, integrator: Any = None, progress: Progress | None = None) -> _Film:
    """Render the film's ``images`` 3-channel images (the scene's integrator: the radiance, then
    its AOVs; another ``integrator``: what it gives), in crops within ``max_memory_mb``;
    ``progress(done, total)`` after each pass."""
    import drjit as dr

    channels = 3 * images
    _, _, width, height = film_window(scene)
    crops = crop_layout(width, height, max_crop_pixels(channels, halves, max_memory_mb))
    if len(crops) > 1 and filter_class(scene) != FILTER_CLASSES["box"]:  # its samples spill over crop edges
        raise RenderError(f"a {width}x{height} film with a {filter_class(scene)} pixel filter does not fit the "
                          f"memory budget ({max_memory_mb} MB) in one piece, and only a box filter renders in crops")
    outputs = [np.empty((height, width, 3), np.float32) for _ in range(images)]
    variance = np.empty((height, width, 3), np.float32) if halves and integrator is None else None
    nonfinite = 0
    done, total = [0], spp * width * height

    def advance(samples: int) -> None:
        done[0] += samples
        if progress is not None:
            progress(done[0], total)

    with contextlib.ExitStack() as stack:
        set_crop = stack.enter_context(cropped(scene)) if len(crops) > 1 else None
        for index, crop in enumerate(crops):
            if set_crop is not None:
                set_crop(crop)
            acc, var = _render_crop(scene, spp, crop_seed(seed, index), max_samples_per_pass, halves, advance,
                                     integrator)
            if acc.shape != (crop[3], crop[2], channels):
                raise RenderError(f"render returned {acc.shape[2]} channels, expected {channels}")
            nonfinite += _store(acc, outputs, crop)
            if variance is not None and var is not None:
                x, y, w, h = crop
                variance[y:y + h, x:x + w] = var
            del acc, var
    dr.flush_malloc_cache()  # hand Dr.Jit's cached film buffers back before the caller goes on
    return _Film(outputs, variance, nonfinite, len(crops))


def render_loaded(
    scene: Any,
    spp: int,
    seed: int = 0,
    aovs: Sequence[str] = (),
    max_samples_per_pass: int = DEFAULT_MAX_SAMPLES_PER_PASS,
    halves: bool = False,
    max_memory_mb: float | None = DEFAULT_MAX_MEMORY_MB,
    progress: Progress | None = None,
) -> RenderResult:
    """Render an already loaded scene (prepared with the same ``aovs``).

    ``halves`` (spp >= 2): render the samples as two independent halves (seeds ``seed`` and a mix
    of it) and also return ``variance``, the per-pixel variance estimate of the combined mean
    (:func:`half_variance`); the image has the same expectation and spp.

    ``max_memory_mb`` bounds the render's scratch memory beyond the returned images: a film whose
    pixels do not fit is rendered in crops with seeds of their own (:mod:`rendering.render_crops`;
    None: one piece). The image is a deterministic function of (scene, spp, seed, aovs, halves,
    crop layout); a render in one crop (any film that fits) is the same whatever the budget; other
    layouts draw other samples from the same distribution.

    A film whose images and scratch do not fit in the memory left is refused before anything is
    allocated (:func:`check_render_memory`). ``progress(done, total)`` is called after each pass
    with the samples rendered so far and in all (``spp`` x the film's pixels).
    """
    _check_spp_seed(spp, seed)
    import mitsuba as mi

    start = time.perf_counter()
    halves = halves and spp >= 2
    _, _, width, height = film_window(scene)
    check_render_memory(width, height, aovs, halves, max_memory_mb)
    film = _render_film(scene, spp, seed, 1 + len(aovs), max_samples_per_pass, halves, max_memory_mb,
                        progress=progress)
    seconds = time.perf_counter() - start
    return RenderResult(rgb=film.images[0], aovs=dict(zip(aovs, film.images[1:])), spp=spp, seed=seed,
                        nonfinite=film.nonfinite, seconds=seconds, variant=mi.variant(), variance=film.variance,
                        crops=film.crops, pixel_filter=_FILTER_NAMES.get(filter_class(scene), filter_class(scene)),
                        to_camera=_to_camera(scene))


def _to_camera(scene: Any) -> np.ndarray | None:
    """The scene's :func:`rendering.camera.sensor_rotation`, None for a degenerate sensor transform."""
    try:
        return sensor_rotation(scene)
    except SceneError:
        return None


@dataclass
class AovRender:
    """A render of AOVs alone (:func:`render_aovs`): each AOV's HxWx3 float32 image (NaN/Inf set
    to 0; ``nonfinite`` pixels had one), the wall time and the film crops."""

    aovs: dict[str, np.ndarray]
    seconds: float
    nonfinite: int = 0
    crops: int = 1


def render_aovs(
    scene: Any,
    spp: int,
    seed: int,
    aovs: Sequence[str],
    max_samples_per_pass: int = DEFAULT_MAX_SAMPLES_PER_PASS,
    halves: bool = False,
    max_memory_mb: float | None = DEFAULT_MAX_MEMORY_MB,
) -> AovRender:
    """The ``aovs`` of a loaded scene, rendered by Mitsuba's aov integrator alone (no light
    transport) instead of the scene's integrator. Its camera rays are those :func:`render_loaded`
    draws for the same spp, seed, ``halves`` and crop layout, so the AOVs (which depend on the
    camera ray alone) are those of that render of the scene prepared with ``aovs``, to float
    rounding (Mitsuba compiles each integrator into a kernel of its own)."""
    _check_spp_seed(spp, seed)
    if not aovs:
        raise RenderError("render_aovs needs at least one AOV")
    check_aovs(aovs)
    import mitsuba as mi

    start = time.perf_counter()
    integrator = mi.load_dict({"type": "aov", "aovs": aov_spec(aovs)})
    film = _render_film(scene, spp, seed, len(aovs), max_samples_per_pass, halves and spp >= 2, max_memory_mb,
                        integrator)
    return AovRender(dict(zip(aovs, film.images)), time.perf_counter() - start, film.nonfinite, film.crops)


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
    max_memory_mb: float | None = DEFAULT_MAX_MEMORY_MB,
    progress: Progress | None = None,
) -> RenderResult:
    """Load and render a scene file or dict with a box filter and a float32 film.

    ``resolution`` is (width, height); ``aovs`` names extra buffers from ``AOV_TYPES`` (rendered
    only when asked for); ``params`` fills an XML scene's ``$name`` parameters; ``base_dir``
    resolves a dict scene's relative asset paths; ``halves``, ``max_memory_mb`` and ``progress``:
    see :func:`render_loaded`.
    """
    loaded = load_scene(prepare(scene, resolution, aovs, params, base_dir))
    return render_loaded(loaded, spp, seed, aovs, max_samples_per_pass, halves, max_memory_mb, progress)


__all__ = ["AOV_TYPES", "AovRender", "RenderResult", "check_render_memory", "load_scene", "prepare", "render",
           "render_aovs", "render_loaded"]
