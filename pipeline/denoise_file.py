"""``denoise``'s core: denoise an image rendered elsewhere and write it in the layout it came in.

Inputs: an EXR (single- or multi-part, any number of layers, float16 or float32), a PFM or a
Radiance HDR file; or two EXRs holding independent halves of one render (``halves``). The colour
layer is :func:`imaging.exr_layers.pick_color_layer`'s choice (or ``layer``); albedo and normal
layers beside it go to models that use them. The variance of the image's Monte Carlo estimate,
from the halves (:func:`rendering.render.half_variance`) or a variance layer, goes to the
denoiser, which applies the noise guard with it. The output replaces the colour layer's channels
and keeps every other layer, part and attribute (``rgb_only``: a plain RGB EXR); a ``.pfm``,
``.hdr`` or ``.png`` (tonemapped) output path writes that format instead, any other extension is
refused, and so is an output that is one of the inputs or, unless ``overwrite``, a file that exists
(:mod:`imaging.output_paths`). With a reference, the metrics cover OIDN on the same input too (when
pyoidn is installed): colour-only and, where the file has albedo and normal layers, OIDN + albedo + normal.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from imaging.atomic_io import json_safe
from imaging.bitmap_io import check_image_header, image_format, read_bitmap, write_bitmap
from imaging.errors import DenoiserError, ExrError
from imaging.exr import write_exr
from imaging.blocks import DEFAULT_BLOCK_BYTES, row_blocks
from imaging.exr_layers import (ALBEDO_WORDS, NORMAL_WORDS, VARIANCE_WORDS, ExrFile, Layer,
                                 describe_layers, find_aux_layer, pick_color_layer, read_exr_file,
                                 replace_layer, write_exr_file)
from imaging.memory_limit import require_memory
from imaging.metrics import all_metrics
from imaging.output_paths import check_new_file, check_not_inputs, output_format
from imaging.png import save_png
from rendering.render import half_variance
from denoise.denoiser import Denoiser
from denoise.energy import settings_if
from denoise.noise_guard import DEFAULT_STRENGTH, strength_for
from denoise.oidn import oidn_available, oidn_denoise
from model.registry import AUTO
from pipeline.evaluation import OIDN, OIDN_AUX, quality_lines

HALVES_BYTES_PER_PIXEL = 128  # combine_halves: float64 temporaries of the mean and the variance
OUTPUT_BYTES_PER_PIXEL = 12  # the denoised image, HxWx3 float32
GUARD_BYTES_PER_PIXEL = 4  # the noise guard's HxW float32 weights


@dataclass
class DenoiseFileConfig:
    """Settings of one ``denoise`` run (filled by the CLI).

    ``inputs``: one image, or the two halves of a render. ``spp``: samples per pixel of the
    (combined) input, for the noise guard's strength; None: the files' ``spp`` attribute, else
    strength 1. ``variance_layer``: None picks a layer named ``variance`` if there is one.
    """

    inputs: list[str]
    output: str
    model: str | None = None
    reference: str | None = None
    layer: str | None = None
    variance_layer: str | None = None
    rgb_only: bool = False
    spp: int | None = None
    noise_guard: bool = True
    max_memory_mb: float = 1024.0
    skip_below: float | None = None
    precision: str = "auto"
    device: str = "cpu"
    flips: int = 1
    energy: bool = True
    overwrite: bool = False


@dataclass
class InputImage:
    """An input read for denoising: HxWx3 float32 ``rgb`` and what came with it."""

    path: str
    rgb: np.ndarray
    exr: ExrFile | None = None  # the whole file, for writing back its layout (EXR inputs)
    layer: Layer | None = None
    albedo: np.ndarray | None = None
    normals: np.ndarray | None = None
    variance: np.ndarray | None = None
    variance_layer: str | None = None
    spp: int | None = None


def _spp_attribute(exr: ExrFile, part: int) -> int | None:
    value = exr.metadata(part).get("spp")
    try:
        spp = int(value) if value is not None else None
    except (TypeError, ValueError):
        return None
    return spp if spp and spp > 0 else None


def _variance(exr: ExrFile, color: Layer, name: str | None) -> tuple[np.ndarray | None, str | None]:
    if name is not None:
        layer = exr.layers.get(name)
        if layer is None or layer.kind == "xyz":
            raise ExrError(f"{exr.path}: no variance layer named {name!r} (layers: {describe_layers(exr)})")
    else:
        layer = find_aux_layer(exr, VARIANCE_WORDS, color, ("rgb", "scalar"))
        if layer is None:
            return None, None
    return exr.take_image(layer, 3), layer.name


def read_input(path: str | Path, layer: str | None = None, variance_layer: str | None = None,
               max_bytes: float = DEFAULT_BLOCK_BYTES) -> InputImage:
    """Read one input image (EXR, PFM or HDR) with its colour layer and what is beside it; the
    readers' temporaries within ``max_bytes`` where they go a block of rows at a time."""
    fmt = image_format(path)
    if fmt != "exr":
        if layer is not None or variance_layer is not None:
            raise DenoiserError(f"{path}: a {fmt.upper()} file has no layers (--layer and "
                                "--variance-layer are for EXR files)")
        return InputImage(str(path), read_bitmap(path, max_bytes))
    exr = read_exr_file(path)
    color = pick_color_layer(exr, layer)
    aux = {key: find_aux_layer(exr, words, color, ("rgb", "xyz"))
           for key, words in (("albedo", ALBEDO_WORDS), ("normals", NORMAL_WORDS))}
    # each layer's pixels held once: the file's channels become views of the arrays made here
    rgb = exr.take_image(color)
    albedo, normals = (exr.take_image(aux[k]) if aux[k] else None for k in ("albedo", "normals"))
    variance, var_name = _variance(exr, color, variance_layer)
    return InputImage(str(path), rgb, exr, color, albedo, normals, variance=variance, variance_layer=var_name,
                      spp=_spp_attribute(exr, color.part))


def combine_halves(a: InputImage, b: InputImage, max_bytes: float = 64 * 2**20) -> InputImage:
    """The render whose two independent halves are ``a`` and ``b``: their spp-weighted mean (equal
    weights unless both files give their ``spp``) with its variance, in ``a``'s layout; computed
    in row blocks within ``max_bytes`` of scratch memory."""
    if a.rgb.shape != b.rgb.shape:
        raise DenoiserError(f"{b.path}: half is {b.rgb.shape[1]}x{b.rgb.shape[0]}, "
                            f"{a.path} is {a.rgb.shape[1]}x{a.rgb.shape[0]}")
    n_a, n_b = (a.spp, b.spp) if a.spp and b.spp else (1, 1)
    mean, variance = np.empty(a.rgb.shape, np.float32), np.empty(a.rgb.shape, np.float32)
    height, width = a.rgb.shape[:2]
    for rows in row_blocks(height, width, HALVES_BYTES_PER_PIXEL, max_bytes):
        mean[rows] = (n_a * a.rgb[rows].astype(np.float64) + n_b * b.rgb[rows]) / (n_a + n_b)
        variance[rows] = half_variance(a.rgb[rows], b.rgb[rows], n_a, n_b)
    spp = a.spp + b.spp if a.spp and b.spp else None
    return InputImage(a.path, mean, a.exr, a.layer, a.albedo, a.normals, variance, "halves", spp)


def oidn_quality(image: InputImage, reference: np.ndarray) -> dict[str, dict[str, float]]:
    """Every metric of OIDN on ``image`` against ``reference``: colour-only (``oidn``) and, where
    the file has albedo and normal layers, OIDN + albedo + normal (``oidn_aux``); nothing without
    pyoidn."""
    if not oidn_available():
        return {}
    quality = {OIDN: all_metrics(oidn_denoise(image.rgb)[0], reference)}
    if image.albedo is not None and image.normals is not None:
        quality[OIDN_AUX] = all_metrics(oidn_denoise(image.rgb, image.albedo, image.normals)[0], reference)
    return quality


def _write(cfg: DenoiseFileConfig, image: InputImage, result: np.ndarray, model: str, max_bytes: float) -> str:
    """Write the output in the format its extension names; return the layout written."""
    attributes = {"denoised_by": model, "source": Path(image.path).name}
    fmt = output_format(cfg.output)
    if fmt == "png":
        if not Path(cfg.output).parent.is_dir():
            raise DenoiserError(f"{cfg.output}: output folder does not exist")
        save_png(cfg.output, result, min(max_bytes, DEFAULT_BLOCK_BYTES))
        return "png (tonemapped 8-bit)"
    if fmt != "exr":
        write_bitmap(cfg.output, result)
        return fmt
    half = image.exr is not None and image.layer is not None and image.exr.is_half(image.layer)
    if cfg.rgb_only or image.exr is None or image.layer is None:
        write_exr(cfg.output, result, metadata=attributes, half=half)
        return "rgb"
    write_exr_file(cfg.output, replace_layer(image.exr, image.layer, result, attributes))
    parts = len(image.exr.parts)
    return f"as read: {len(image.exr.layers)} layers" + (f" in {parts} parts" if parts > 1 else "")


def denoise_file(cfg: DenoiseFileConfig) -> dict[str, Any]:
    """Read, denoise, write; return what was done (and quality against ``cfg.reference``)."""
    if len(cfg.inputs) not in (1, 2):
        raise DenoiserError(f"expected one input or two halves, got {len(cfg.inputs)} files")
    if len(cfg.inputs) == 2 and cfg.variance_layer is not None:
        raise DenoiserError("two halves give the variance: --variance-layer is for a single input")
    output_format(cfg.output)
    check_not_inputs([cfg.output], [*cfg.inputs, cfg.reference], cfg.overwrite)
    check_new_file(cfg.output, cfg.overwrite)
    for path in [*cfg.inputs, *([cfg.reference] if cfg.reference else [])]:
        check_image_header(path)  # before the models load: a file that lies fails at once
    # one image a process: huge pages would only slow its one call (denoise.allocator)
    denoiser = Denoiser(cfg.model, max_memory_mb=cfg.max_memory_mb, skip_below=cfg.skip_below,
                        precision=cfg.precision, flips=cfg.flips,
                        energy=settings_if(cfg.energy), device=cfg.device, huge_pages=False)
    blocks = min(denoiser.max_bytes, DEFAULT_BLOCK_BYTES)  # the readers' temporaries
    images = [read_input(p, cfg.layer, cfg.variance_layer, blocks) for p in cfg.inputs]
    image = images[0] if len(images) == 1 else combine_halves(*images, max_bytes=denoiser.max_bytes)
    ref = read_input(cfg.reference, max_bytes=blocks).rgb if cfg.reference else None
    if ref is not None and ref.shape != image.rgb.shape:
        raise DenoiserError(f"{cfg.reference}: reference is {ref.shape[1]}x{ref.shape[0]}, "
                            f"input is {image.rgb.shape[1]}x{image.rgb.shape[0]}")
    spp = cfg.spp or image.spp
    variance = image.variance if cfg.noise_guard else None
    height, width = image.rgb.shape[:2]
    require_memory(height * width * (OUTPUT_BYTES_PER_PIXEL + GUARD_BYTES_PER_PIXEL * (variance is not None)),
                   f"{cfg.inputs[0]}: {width}x{height} pixels: the denoised image"
                   f"{' and its guard weights' if variance is not None else ''}", DenoiserError)
    strength = strength_for(spp) if spp else DEFAULT_STRENGTH
    result = denoiser.denoise_array(image.rgb, image.albedo, image.normals, variance=variance,
                                    strength=strength, spp=spp or None)
    layout = _write(cfg, image, result.image, denoiser.name, denoiser.max_bytes)
    out: dict[str, Any] = {
        "input": cfg.inputs[0] if len(cfg.inputs) == 1 else list(cfg.inputs), "output": cfg.output,
        "layer": image.layer.name if image.layer else None, "layout": layout,
        "denoise_s": result.seconds, "model": denoiser.name, "ran": result.choice,
        "models_run": list(result.models), "spp": spp or None, "notes": list(result.notes),
        "noise": {"level": result.noise.level, "nyquist_ratio": result.noise.ratio} if result.noise else None,
        "precision": result.precision,
        "flips": denoiser.flips, "nonfinite_values": result.nonfinite,
        "negative_values": result.negative,
        "noise_guard": None if variance is None else {
            "variance": image.variance_layer, "spp": spp, "strength": strength,
            "mean_weight": result.guard_weight},
        "energy": result.energy_record()}
    if ref is not None:
        out["quality"] = {"noisy": all_metrics(image.rgb, ref), "denoised": all_metrics(result.image, ref),
                          **oidn_quality(image, ref)}
    return json_safe(out)


def _ran(models: list[str], precision: str) -> str:
    """``a + b in bfloat16``, or each network with its own format where they differ."""
    formats = precision.split("+")
    if len(set(formats)) == 1:
        return f"{' + '.join(models)} in {formats[0]}"
    return " + ".join(f"{m} ({f})" for m, f in zip(models, formats))


def denoise_summary(record: dict[str, Any]) -> list[str]:
    """``denoise``'s table of one run's record (:func:`denoise_file`)."""
    inputs = record["input"] if isinstance(record["input"], str) else " + ".join(record["input"])
    spp = f"{record['spp']} spp" if record.get("spp") else "spp unknown"
    chosen = f" -> {record['ran']}" if record["model"] == AUTO and record.get("ran") else ""
    lines = [f"{inputs} -> {record['output']} ({record['layout']})",
             f"model {record['model']}{chosen} ({spp}): ran {_ran(record['models_run'], record['precision'])}, "
             f"{record['denoise_s']:.2f} s"]
    guard = record.get("noise_guard")
    if guard:
        lines.append(f"noise guard: mean weight of the denoiser's output {guard['mean_weight']:.3f} (1: unchanged)")
    if record.get("energy"):
        lines.append(f"energy correction: mean factor {record['energy']['mean_factor']:.3f} (1: unchanged)")
    if record.get("nonfinite_values") or record.get("negative_values"):
        lines.append(f"replaced by 0: {record['nonfinite_values']} non-finite, {record['negative_values']} negative values")
    if record.get("quality"):
        lines += quality_lines(record["quality"])
    return lines

