"""``render-and-denoise``'s core: render a scene, denoise it, compare, write files and a report.

Outputs in ``out``: noisy.exr, denoised.exr (+ oidn.exr, reference.exr), a PNG preview of each,
comparison.png, metrics.json (written last: a run without it did not finish; a re-run into the
same folder deletes the old one first), report.html and config.json (the run's settings).
"""
from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from imaging.atomic_io import TMP_PREFIX, write_text_atomic
from imaging.errors import DenoiserError
from imaging.exr import read_exr, write_exr
from imaging.metrics import all_metrics
from imaging.peak_rss import PeakRSS
from imaging.png import save_png
from imaging.render import load_scene, pass_seeds, prepare, render_loaded
from pipeline.budget import budget_candidates, plan_run
from pipeline.denoise import Denoiser
from pipeline.noise_guard import DEFAULT_PIVOT_SPP, DEFAULT_RADIUS, strength_for
from pipeline.oidn import oidn_available, oidn_denoise
from pipeline.report import comparison_image, write_previews, write_report


@dataclass
class RunConfig:
    """Settings of one render-and-denoise run (filled by the CLI, saved as config.json)."""

    scene: str
    out: str
    spp: int = 128
    resolution: tuple[int, int] | None = None
    seed: int = 0
    model: str | None = None
    reference: str | None = None
    reference_spp: int | None = None
    compare_oidn: bool | None = None  # OIDN beside ours; None: whenever pyoidn is installed
    params: dict[str, str] = field(default_factory=dict)
    max_memory_mb: float = 1024.0
    time_budget: float | None = None  # seconds: spp (and, with model "auto", the model) chosen to fit
    curves: str | None = None  # tradeoff.json guiding the model choice under a time budget
    noise_guard: bool = True  # render in two halves, blend by pipeline.noise_guard (off: one render)


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None  # JSON has no inf: identical images have PSNR null (= infinite)
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def image_stats(img: np.ndarray) -> dict[str, float]:
    """Summary statistics of an HxWx3 radiance image (used when there is no reference)."""
    return {"mean": float(img.mean()), "min": float(img.min()), "max": float(img.max()),
            "p99": float(np.percentile(img, 99))}


def _check_out(out: Path) -> None:
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise DenoiserError(f"{out}: cannot create output folder ({exc.strerror or exc})") from None
    if not out.is_dir():
        raise DenoiserError(f"{out}: is not a folder")
    probe = out / ".write-test"
    try:
        probe.write_bytes(b"")
        probe.unlink()
        # A re-run into the folder of an earlier run: its completion marker (and the report that
        # goes with it) must not sit beside new, possibly unfinished outputs; nor leftovers of a crash.
        for stale in [out / "metrics.json", out / "report.html", *out.glob(f"{TMP_PREFIX}*")]:
            stale.unlink(missing_ok=True)
    except OSError as exc:
        raise DenoiserError(f"{out}: output folder is not writable ({exc.strerror or exc})") from None


def _oidn_setting(compare: bool | None) -> dict[str, Any]:
    """Whether OIDN is compared, and why: asked for (True; fails later without pyoidn), declined
    (False), or by default (None) whenever pyoidn is installed."""
    if compare is False:
        return {"compared": False, "note": "OIDN not compared (--no-compare)"}
    if compare is None and not oidn_available():
        return {"compared": False, "note": "OIDN not compared: pyoidn is not installed "
                "(pip install '.[oidn]')"}
    return {"compared": True, "note": "OIDN: Intel Open Image Denoise, colour only (pyoidn)"}


def run(cfg: RunConfig, log: Callable[[str], None] = lambda s: None) -> dict[str, Any]:
    """Render, denoise, compare; write every output; return the metrics dict."""
    if cfg.reference and cfg.reference_spp:
        raise DenoiserError("give either --reference or --reference-spp, not both")
    out = Path(cfg.out)
    t_start = time.perf_counter()
    candidates = budget_candidates(cfg.model, cfg.max_memory_mb) if cfg.time_budget is not None else {}
    denoiser = (next(iter(candidates.values())) if candidates
                else Denoiser(cfg.model, max_memory_mb=cfg.max_memory_mb))
    reference = read_exr(cfg.reference).rgb if cfg.reference else None
    _check_out(out)
    write_text_atomic(out / "config.json", json.dumps(asdict(cfg), indent=1) + "\n")

    aovs = ("albedo", "sh_normal") if any(d.needs_aovs for d in (denoiser, *candidates.values())) else ()
    t0 = time.perf_counter()
    scene = load_scene(prepare(cfg.scene, cfg.resolution, aovs, cfg.params))
    t_load = time.perf_counter() - t0
    spp, plan = cfg.spp, None
    if candidates:
        plan = plan_run(cfg.time_budget, t_start, scene, cfg.seed, aovs, candidates, cfg.curves, log,
                        halves=cfg.noise_guard)
        denoiser, spp = candidates[plan.model], plan.spp
    log(f"rendering {spp} spp")
    with PeakRSS() as render_memory:  # Mitsuba's render and its buffers, reported on their own
        noisy = render_loaded(scene, spp, cfg.seed, aovs, halves=cfg.noise_guard,
                              max_memory_mb=cfg.max_memory_mb)
    if reference is not None and reference.shape != noisy.rgb.shape:
        raise DenoiserError(f"{cfg.reference}: reference is {reference.shape[1]}x{reference.shape[0]}"
                            f", render is {noisy.rgb.shape[1]}x{noisy.rgb.shape[0]}")
    log(f"denoising with {denoiser.name}")
    result = denoiser.denoise_render(noisy)
    if plan:
        plan.actual_s = time.perf_counter() - t_start
    images = {"noisy": noisy.rgb, "denoised": result.image}
    timings = {"scene_load_s": t_load, "render_s": noisy.seconds, "denoise_s": result.seconds}
    oidn = _oidn_setting(cfg.compare_oidn)
    if oidn["compared"]:
        log("denoising with OIDN")
        images["oidn"], timings["oidn_s"] = oidn_denoise(noisy.rgb)
    if cfg.reference_spp:
        log(f"rendering the reference at {cfg.reference_spp} spp")
        plain = load_scene(prepare(cfg.scene, cfg.resolution, (), cfg.params)) if aovs else scene
        ref = render_loaded(plain, cfg.reference_spp, pass_seeds(cfg.seed, 2)[1],
                            max_memory_mb=cfg.max_memory_mb)
        reference, timings["reference_render_s"] = ref.rgb, ref.seconds
    if reference is not None:
        images["reference"] = reference

    meta = {"scene": Path(cfg.scene).stem, "spp": spp, "seed": cfg.seed}
    for name, img in images.items():
        write_exr(out / f"{name}.exr", img, metadata={**meta, "image": name})
    write_previews(out, images)
    focus_against = ("denoised", "reference") if reference is not None else ("denoised", "noisy")
    save_png(out / "comparison.png", comparison_image(images, *focus_against))

    timings["total_s"] = time.perf_counter() - t_start
    h, w = noisy.rgb.shape[:2]
    metrics: dict[str, Any] = {
        "scene": str(cfg.scene), "spp": spp, "resolution": [w, h], "seed": cfg.seed,
        "model": {"name": denoiser.name, "sha256": denoiser.sha256, "config": denoiser.config.to_dict()},
        "mitsuba": metadata.version("mitsuba"), "variant": noisy.variant, "timings": timings,
        "sanitized": {"render_nonfinite_pixels": noisy.nonfinite, "denoiser_nonfinite_values":
                      result.nonfinite, "denoiser_negative_values": result.negative},
        "oidn": oidn,
        "reference": ({"file": str(cfg.reference)} if cfg.reference else
                      {"spp": cfg.reference_spp} if cfg.reference_spp else None),
        "render_memory": {**render_memory.to_dict(), "budget_mb": cfg.max_memory_mb, "crops": noisy.crops},
    }
    metrics["noise_guard"] = ({"radius": DEFAULT_RADIUS, "pivot_spp": DEFAULT_PIVOT_SPP,
                               "strength": strength_for(spp), "mean_weight": result.guard_weight}
                              if result.guard_weight is not None else None)
    if plan:
        metrics["budget"] = plan.to_dict()
    if reference is not None:
        metrics["quality"] = {n: all_metrics(img, reference) for n, img in images.items()
                              if n != "reference"}
        metrics["note"] = "quality against the reference (PSNR/SSIM tonemapped x/(1+x), gamma 1/2.2)"
    else:
        metrics["stats"] = {n: image_stats(img) for n, img in images.items()}
        metrics["note"] = "no reference given: timings and image statistics only"
    metrics = _json_safe(metrics)
    write_report(out, metrics, images, result.guard_map)
    write_text_atomic(out / "metrics.json", json.dumps(metrics, indent=1) + "\n")
    return metrics


def summary_lines(metrics: dict[str, Any]) -> list[str]:
    """A one-screen summary of a run's metrics."""
    t = metrics["timings"]
    lines = [f"{metrics['scene']}: {metrics['resolution'][0]}x{metrics['resolution'][1]} at "
             f"{metrics['spp']} spp, model {metrics['model']['name']} ({metrics['variant']})",
             "timings: " + ", ".join(f"{k[:-2]} {v:.2f}s" for k, v in t.items())]
    guarded = metrics.get("noise_guard")
    if guarded:
        lines.append(f"noise guard: mean weight of the denoiser's output {guarded['mean_weight']:.3f} "
                     "(1: unchanged)")
    budget = metrics.get("budget")
    if budget:
        lines.append(f"time budget {budget['budget_s']:g} s: chose {budget['model']} at {budget['spp']} spp "
                     f"({budget['rule']}); predicted {budget['predicted_s']:.2f} s, actual "
                     f"{budget['actual_s']:.2f} s")
    quality = metrics.get("quality")
    if quality:
        lines.append(f"{'':10}{'PSNR dB':>9}{'SSIM':>8}{'relMSE':>10}{'FLIP':>8}")
        for name, m in quality.items():
            psnr = "inf" if m["psnr"] is None else f"{m['psnr']:.2f}"
            lines.append(f"{name:10}{psnr:>9}{m['ssim']:>8.4f}{m['relmse']:>10.5f}{m['flip']:>8.4f}")
    else:
        lines.append(metrics["note"])
    return lines
