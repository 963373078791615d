"""``render-and-denoise``'s core: render a scene, denoise it, compare, write files and a report.

Outputs in ``out``: noisy.exr, denoised.exr (+ oidn.exr and oidn_aux.exr: OIDN colour-only and
OIDN + albedo + normal; reference.exr), a PNG preview of each, comparison.png, metrics.json
(written last: a run without it did not finish), report.html and config.json (the run's settings).
A folder already holding one of these files is refused before anything runs
(:func:`imaging.output_paths.check_output_folder`) unless ``overwrite``; a run with it deletes the
earlier run's metrics.json and report.html first, and replaces each file it writes.
Writing them, the metrics and the report go a block of rows at a time (:func:`output_bytes` of
the ``--max-memory-mb`` budget), so their scratch memory does not grow with the image.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from imaging.atomic_io import TMP_PREFIX, json_safe, write_json_atomic
from imaging.blocks import DEFAULT_BLOCK_BYTES
from imaging.errors import DenoiserError
from imaging.exr import write_exr
from imaging.metrics import percentile
from imaging.output_paths import check_output_folder
from imaging.peak_rss import PeakRSS
from console.progress import ProgressFactory, counted
from rendering.render import RenderResult
from pipeline.budget import BudgetPlan, Candidate, after_render, budget_candidates, plan_run, refit_spp
from pipeline.budget_costs import read_costs
from denoise.denoiser import DenoiseResult, Denoiser
from pipeline.evaluation import (OIDN, OIDN_AUX, RenderSettings, aovs_for, check_memory, check_reference,
                                 denoise_output, make_denoiser, oidn_output, quality_lines, read_reference,
                                 render_input, render_reference, score, with_aovs)
from denoise.noise_guard import DEFAULT_PIVOT_SPP, DEFAULT_RADIUS, strength_for
from denoise.oidn import oidn_available
from model.registry import AUTO
from pipeline.report import write_comparison, write_previews, write_report


@dataclass
class RunConfig:
    """Settings of one render-and-denoise run (filled by the CLI, saved as config.json).
    ``compare_oidn``: OIDN beside ours (None: whenever pyoidn is installed); ``time_budget``
    seconds: spp (and, with model "auto", the model) chosen to fit; ``curves``: a tradeoff.json
    guiding the model choice under a time budget."""

    render: RenderSettings
    out: str
    spp: int = 128
    model: str | None = None
    compare_oidn: bool | None = None
    time_budget: float | None = None
    curves: str | None = None


def image_stats(img: np.ndarray, max_bytes: float = DEFAULT_BLOCK_BYTES) -> dict[str, float]:
    """Summary statistics of an HxWx3 radiance image (used when there is no reference); p99 is
    ``np.percentile``'s value without its copy of the image (:func:`imaging.metrics.percentile`,
    blocks within ``max_bytes``)."""
    return {"mean": float(img.mean()), "min": float(img.min()), "max": float(img.max()),
            "p99": percentile(img, 99, max_bytes)}


def output_bytes(cfg: RenderSettings) -> float:
    """Temporaries of a block of rows in the output stages (writing, metrics, report): an eighth
    of the memory budget, at most :data:`imaging.blocks.DEFAULT_BLOCK_BYTES`."""
    return min(DEFAULT_BLOCK_BYTES, cfg.max_memory_mb * 2**20 / 8)


# every file of a run in its output folder; with the writability probe, every file run() writes into
# (or removes from) it
RESULT_NAMES = ("config.json", "metrics.json", "report.html", "comparison.png",
                *(f"{image}.{ext}" for image in ("noisy", "denoised", OIDN, OIDN_AUX, "reference")
                  for ext in ("exr", "png")))
OUTPUT_NAMES = (*RESULT_NAMES, ".write-test")


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
        # An earlier run's folder (--overwrite): its completion marker (and the report that goes
        # with it) must not sit beside new, possibly unfinished outputs; nor leftovers of a crash.
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
    return {"compared": True, "note": "OIDN: Intel Open Image Denoise (pyoidn), colour-only and with the "
            "render's albedo and normals (from an AOV pass with the render's camera rays)"}


@dataclass
class _Run:
    """What the stages of :func:`run` hand on: the settings, the models, the loaded scene and what
    has been made so far (images by name, timings in seconds)."""

    cfg: RunConfig
    log: Callable[[str], None]
    started: float
    denoiser: Denoiser | None  # under a time budget: None until the plan chooses
    candidates: dict[str, Candidate]
    reference: np.ndarray | None
    aovs: tuple[str, ...] = ()
    scene: Any = None
    spp: int = 0
    plan: BudgetPlan | None = None
    noisy: RenderResult | None = None
    result: DenoiseResult | None = None
    render_memory: PeakRSS | None = None
    images: dict[str, np.ndarray] = field(default_factory=dict)
    timings: dict[str, float] = field(default_factory=dict)
    oidn: dict[str, Any] = field(default_factory=dict)
    bars: ProgressFactory | None = None  # the renders' progress bars (None: none drawn)
    recorded: tuple[float, float] | None = None  # the recorded model costs' calibration times (budget mode)


def _start(cfg: RunConfig, log: Callable[[str], None], started: float | None) -> _Run:
    """Check the settings, load the model (under a time budget: those whose costs are not
    recorded), read the reference file and prepare the output folder (everything that can fail
    before the scene loads, but for loading the model a budget chooses)."""
    cfg.render.check()
    cfg.render.check_outputs(cfg.out, OUTPUT_NAMES)
    check_output_folder(cfg.out, RESULT_NAMES, cfg.render.overwrite)
    started = time.perf_counter() if started is None else started
    costs = read_costs() if cfg.time_budget is not None else None
    candidates = budget_candidates(cfg.model, cfg.render, costs) if cfg.time_budget is not None else {}
    denoiser = None if candidates else make_denoiser(cfg.model, cfg.render)
    reference = read_reference(cfg.render)
    _check_out(Path(cfg.out))
    aovs = aovs_for([denoiser] if denoiser else candidates.values())
    return _Run(cfg, log, started, denoiser, candidates, reference, aovs, spp=cfg.spp,
                recorded=(costs.calibration_s, costs.loading_s) if costs else None)


def _load_scene(run: _Run) -> None:
    t0 = time.perf_counter()
    run.scene = run.cfg.render.load(run.aovs)
    held = ["denoised", *(["oidn"] if _oidn_setting(run.cfg.compare_oidn)["compared"] else []),
            *(["reference"] if run.cfg.render.reference_spp else [])]  # a reference file is read already
    check_memory(run.scene, run.cfg.render, run.spp, run.aovs, held)
    run.timings["scene_load_s"] = time.perf_counter() - t0


def _use(run: _Run, name: str) -> None:
    """Denoise with candidate ``name``, loading it if it is not loaded yet (the time it takes goes
    into the timings' ``model_load_s``)."""
    candidate = run.candidates[name]
    if not isinstance(candidate, Denoiser):
        run.log(f"loading {name}")
        t0 = time.perf_counter()
        candidate = run.candidates[name] = make_denoiser(name, run.cfg.render)
        run.timings["model_load_s"] = run.timings.get("model_load_s", 0.0) + time.perf_counter() - t0
    run.denoiser = candidate


def _fit_budget(run: _Run) -> None:
    """Budget mode: calibrate, probe the scene (and the models loaded for it), choose the model and
    the spp; load the chosen model and fit the spp to the time then left."""
    if not run.candidates:
        return
    cfg = run.cfg
    run.plan = plan_run(cfg.time_budget, run.started, run.scene, cfg.render.seed, run.aovs, run.candidates,
                        cfg.curves, run.log, halves=cfg.render.noise_guard, max_memory_mb=cfg.render.max_memory_mb,
                        recorded=run.recorded)
    loaded = isinstance(run.candidates[run.plan.model], Denoiser)
    _use(run, run.plan.model)
    if not loaded:
        refit_spp(run.plan, time.perf_counter() - run.started)
    run.spp = run.plan.spp


def _render_and_denoise(run: _Run) -> None:
    """The evaluation path (:mod:`pipeline.evaluation`): the render a denoiser is given, then our
    model as it applies to it; the budget's clock stops here."""
    run.log(f"rendering {run.spp} spp")
    with PeakRSS() as run.render_memory:  # Mitsuba's render and its buffers, reported on their own
        run.noisy = render_input(run.scene, run.spp, run.cfg.render, run.aovs, counted(run.bars, "render"))
    if run.reference is not None:
        check_reference(run.cfg.render, run.reference, run.noisy)
    if run.plan:
        switch = after_render(run.plan, time.perf_counter() - run.started, run.noisy.seconds)
        if switch:
            _use(run, switch)
    chosen = f" -> {run.denoiser.choice(run.spp).name}" if run.denoiser.name == AUTO else ""
    run.log(f"denoising with {run.denoiser.name}{chosen}")
    denoised = denoise_output(run.noisy, run.denoiser)
    if run.plan:
        run.plan.actual_s = time.perf_counter() - run.started
    run.result = denoised.result
    run.images.update(noisy=run.noisy.rgb, denoised=denoised.image)
    run.timings.update(render_s=run.noisy.seconds, denoise_s=denoised.seconds)


def _compare(run: _Run) -> None:
    """OIDN on the same render (colour-only, then with the render's albedo and normals, rendered
    now unless the render has them), and the reference (read, or rendered now)."""
    run.oidn = _oidn_setting(run.cfg.compare_oidn)
    if run.oidn["compared"]:
        run.log("denoising with OIDN colour-only")
        oidn = oidn_output(run.noisy)
        run.images[OIDN], run.timings["oidn_s"] = oidn.image, oidn.seconds
        run.log("rendering albedo and normals; denoising with OIDN + albedo + normal")
        render, run.timings["aov_render_s"] = with_aovs(run.noisy, run.scene, run.cfg.render)
        aux = oidn_output(render, aux=True)
        run.images[OIDN_AUX], run.timings["oidn_aux_s"] = aux.image, aux.seconds
    if run.cfg.render.reference_spp:
        run.log(f"rendering the reference at {run.cfg.render.reference_spp} spp")
        ref = render_reference(run.cfg.render, run.scene, run.aovs, counted(run.bars, "reference"))
        run.reference, run.timings["reference_render_s"] = ref.rgb, ref.seconds
    if run.reference is not None:
        run.images["reference"] = run.reference


def _write_images(run: _Run) -> None:
    """Every image as EXR and PNG, and the comparison sheet, a block of rows at a time
    (:func:`output_bytes`)."""
    out, max_bytes = Path(run.cfg.out), output_bytes(run.cfg.render)
    meta = {"scene": Path(run.cfg.render.scene).stem, "spp": run.spp, "seed": run.cfg.render.seed}
    for name, img in run.images.items():
        write_exr(out / f"{name}.exr", img, metadata={**meta, "image": name}, max_bytes=max_bytes)
    write_previews(out, run.images, max_bytes)
    focus_against = ("denoised", "reference") if run.reference is not None else ("denoised", "noisy")
    write_comparison(out / "comparison.png", run.images, *focus_against, max_bytes=max_bytes)


def _metrics(run: _Run) -> dict[str, Any]:
    """metrics.json's dict: settings, model, timings, sanitised values, memory, guard, budget and
    the quality of every image against the reference (or their statistics)."""
    cfg, noisy, result, denoiser = run.cfg.render, run.noisy, run.result, run.denoiser
    h, w = noisy.rgb.shape[:2]
    metrics: dict[str, Any] = {
        "scene": str(cfg.scene), "spp": run.spp, "resolution": [w, h], "seed": cfg.seed,
        "model": {"name": denoiser.name, "sha256": denoiser.sha256, "precision": result.precision,
                  "flips": denoiser.flips, "config": denoiser.config.to_dict(), "ran": result.choice,
                  "models_run": list(result.models), **denoiser.ensemble_record()},
        "notes": list(result.notes),
        "noise": {"level": result.noise.level, "nyquist_ratio": result.noise.ratio} if result.noise else None,
        "mitsuba": metadata.version("mitsuba"), "variant": noisy.variant, "pixel_filter": noisy.pixel_filter,
        "timings": run.timings,
        "sanitized": {"render_nonfinite_pixels": noisy.nonfinite, "denoiser_nonfinite_values":
                      result.nonfinite, "denoiser_negative_values": result.negative},
        "oidn": run.oidn,
        "reference": ({"file": str(cfg.reference)} if cfg.reference else
                      {"spp": cfg.reference_spp} if cfg.reference_spp else None),
        "render_memory": {**run.render_memory.to_dict(), "budget_mb": cfg.max_memory_mb, "crops": noisy.crops},
    }
    metrics["noise_guard"] = ({"radius": DEFAULT_RADIUS, "pivot_spp": DEFAULT_PIVOT_SPP,
                               "strength": strength_for(run.spp), "mean_weight": result.guard_weight}
                              if result.guard_weight is not None else None)
    metrics["energy"] = result.energy_record()
    if run.plan:
        metrics["budget"] = run.plan.to_dict()
    if run.reference is not None:
        metrics["quality"] = {n: score(img, run.reference, full=True) for n, img in run.images.items()
                              if n != "reference"}
        metrics["note"] = "quality against the reference (PSNR/SSIM tonemapped x/(1+x), gamma 1/2.2)"
    else:
        metrics["stats"] = {n: image_stats(img, output_bytes(cfg)) for n, img in run.images.items()}
        metrics["note"] = "no reference given: timings and image statistics only"
    return json_safe(metrics)


def run(cfg: RunConfig, log: Callable[[str], None] = lambda s: None, started: float | None = None,
        bars: ProgressFactory | None = None) -> dict[str, Any]:
    """Render, denoise, compare; write every output; return the metrics dict. metrics.json is
    written last: a folder without it holds no finished run. ``started``: the
    ``time.perf_counter()`` at which the command started, where the time budget and ``total_s``
    count from (None: now). ``bars``: a progress bar per render (samples rendered)."""
    state = _start(cfg, log, started)
    state.bars = bars
    _load_scene(state)
    # written once the scene and its memory passed: a refused start leaves no file that would
    # make the corrected command's folder look like an earlier run's
    write_json_atomic(Path(cfg.out) / "config.json", asdict(cfg))
    _fit_budget(state)
    _render_and_denoise(state)
    _compare(state)
    _write_images(state)
    state.timings["total_s"] = time.perf_counter() - state.started
    metrics = _metrics(state)
    write_report(Path(cfg.out), metrics, state.images, state.result.guard_map, output_bytes(cfg.render))
    write_json_atomic(Path(cfg.out) / "metrics.json", metrics)
    return metrics


def model_words(model: dict[str, Any]) -> str:
    """The model of a record in words: the name given, for ``auto`` the entry it chose
    (``auto -> fast``), and the networks that ran."""
    chose = f" -> {model['ran']}" if model["name"] == AUTO and model.get("ran") else ""
    return f"{model['name']}{chose}, ran {' + '.join(model['models_run'])}"


def budget_lines(budget: dict[str, Any]) -> list[str]:
    """What a time budget assumed and what it came to: the choice, the host's measured speed, the
    prediction against the wall time, and the notes of the checks against the clock."""
    speed = budget["speed"]
    host = (f"host at {1 / speed['slowdown']:.2f}x (networks) and {1 / speed['loading_slowdown']:.2f}x (loading) "
            f"the speed the model costs were recorded at (calibrations {speed['calibration_s'] * 1e3:.1f} and "
            f"{speed['loading_s'] * 1e3:.1f} ms a call, recorded {speed['recorded_s'] * 1e3:.1f} and "
            f"{speed['recorded_loading_s'] * 1e3:.1f})" if speed.get("slowdown") and speed.get("loading_slowdown") else
            f"calibrations {speed['calibration_s'] * 1e3:.1f} and {speed['loading_s'] * 1e3:.1f} ms a call "
            "(no model costs recorded to compare)")
    ratio = budget["actual_s"] / budget["budget_s"]
    return [f"time budget {budget['budget_s']:g} s: chose {budget['model']} at {budget['spp']} spp ({budget['rule']})",
            f"  assumed: {host}; model costs {budget['costs']}",
            f"  predicted {budget['predicted_s']:.2f} s; the denoised image took {budget['actual_s']:.2f} s of wall "
            f"time ({ratio:.2f}x the budget)",
            *(f"  note: {note}" for note in budget["notes"])]


def summary_lines(metrics: dict[str, Any]) -> list[str]:
    """A one-screen summary of a run's metrics."""
    t = metrics["timings"]
    lines = [f"{metrics['scene']}: {metrics['resolution'][0]}x{metrics['resolution'][1]} at "
             f"{metrics['spp']} spp, model {model_words(metrics['model'])} ({metrics['variant']})",
             "timings: " + ", ".join(f"{k[:-2]} {v:.2f}s" for k, v in t.items())]
    guarded = metrics.get("noise_guard")
    if guarded:
        lines.append(f"noise guard: mean weight of the denoiser's output {guarded['mean_weight']:.3f} "
                     "(1: unchanged)")
    energy = metrics.get("energy")
    if energy:
        lines.append(f"energy correction: mean factor {energy['mean_factor']:.3f} (1: unchanged)")
    budget = metrics.get("budget")
    if budget:
        lines += budget_lines(budget)
    if metrics.get("quality"):
        lines += quality_lines(metrics["quality"])
    else:
        lines.append(metrics["note"])
    return lines
