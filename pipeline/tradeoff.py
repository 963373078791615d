"""``tradeoff``'s measurement loop: error against time for each spp and each denoiser.

For every spp the scene is rendered ``repeat`` times with the same seed (the same image; the
median wall time is kept), then each denoiser — ``none`` (the raw render), each model, OIDN if
asked — runs ``repeat`` times on it (median time). OIDN comes twice: colour-only (``oidn``) and
with the render's albedo and normals (``oidn_aux``), whose render time includes their AOV pass
(:func:`pipeline.evaluation.with_aovs`, ``repeat`` times with the render, median of the sums).
Renders, denoisers and scores are those of ``render-and-denoise`` (:mod:`pipeline.evaluation`: two
halves, noise input and guard unless ``--no-noise-guard``; PSNR, relMSE, FLIP). Kernels are
compiled and the networks warmed up before anything is timed. Outputs
(:mod:`pipeline.tradeoff_report`): ``tradeoff.json``, ``tradeoff.csv``, ``tradeoff.png``,
``report.html`` and ``config.json`` (this run's :class:`TradeoffConfig`). A folder already holding
one of them is refused before anything runs (:func:`imaging.output_paths.check_output_folder`)
unless ``overwrite``.
"""
from __future__ import annotations

import statistics
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from imaging.atomic_io import json_safe, write_json_atomic
from imaging.errors import DenoiserError
from imaging.output_paths import check_output_folder
from console.progress import ProgressBar, ProgressFactory
from rendering.render import RenderResult
from denoise.denoiser import Denoiser, select
from denoise.oidn import oidn_available
from model.registry import SEPARATOR, range_suffix, registry
from pipeline.evaluation import (OIDN, OIDN_AUX, Output, RenderSettings, aovs_for, check_memory, check_reference,
                                 denoise_output, make_denoiser, oidn_output, read_reference, render_input,
                                 render_reference, score, with_aovs)
from pipeline.pareto import ERROR_OF_METRIC, equal_quality, metric_error, pareto_front

DEFAULT_SPP = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024)
DEFAULT_MODELS = ("fast", "balanced", "high")  # the registry's entries
METRICS = ("psnr", "relmse", "flip")


@dataclass
class TradeoffConfig:
    """Settings of one ``tradeoff`` run (filled by the CLI, saved as config.json).

    ``models``: registry names (:mod:`model.registry`), checkpoint files or expert specs.
    ``compare_oidn``: also measure OIDN colour-only and OIDN + albedo + normal (None: whenever
    pyoidn is installed).
    ``metric``: the error that the plot, the Pareto front and the printed saving table use.
    """

    render: RenderSettings
    out: str
    spp: list[int] = field(default_factory=lambda: list(DEFAULT_SPP))
    models: list[str] = field(default_factory=lambda: list(DEFAULT_MODELS))
    compare_oidn: bool | None = None
    repeat: int = 3
    metric: str = "relmse"

    def check(self) -> None:
        """Raise :class:`DenoiserError` for settings that cannot give a measurement."""
        if not self.spp or any(s < 1 for s in self.spp) or len(set(self.spp)) != len(self.spp):
            raise DenoiserError(f"spp levels must be distinct positive integers, got {self.spp}")
        self.render.check(reference_required=True)
        if self.repeat < 1:
            raise DenoiserError(f"repeat must be >= 1, got {self.repeat}")
        if self.metric not in ERROR_OF_METRIC:
            raise DenoiserError(f"unknown metric {self.metric!r} (known: {', '.join(ERROR_OF_METRIC)})")


@dataclass
class Point:
    """One (denoiser, spp) measurement. Seconds are medians over the repeats."""

    denoiser: str
    spp: int
    render_s: float
    denoise_s: float
    psnr: float
    relmse: float
    flip: float
    render_times: list[float]
    denoise_times: list[float]

    @property
    def total_s(self) -> float:
        return self.render_s + self.denoise_s

    def error(self, metric: str) -> float:
        return metric_error(metric, getattr(self, metric))


def model_labels(models: list[str]) -> dict[str, str]:
    """Label -> ``--model`` value for each ``--models`` entry: a registry name is its own label; a
    file or spec is labelled by its members' file stems with their spp ranges (made unique).
    Raises :class:`DenoiserError` for an unknown name or a missing file."""
    labels: dict[str, str] = {}
    for name in models:
        selection = select(name)
        if selection.auto or selection.name in registry().entries:
            label = selection.name
        else:
            label = SEPARATOR.join(m.path.stem + range_suffix(m.lo, m.hi) for m in selection.choices[0].by_spp)
        base, n = label, 2
        while label in labels or label in ("none", OIDN, OIDN_AUX):
            label, n = f"{base}-{n}", n + 1
        labels[label] = name
    return labels


def _median(values: list[float]) -> float:
    return float(statistics.median(values))


def _timed(render: RenderResult, denoiser: Denoiser | None, repeat: int) -> tuple[Output, list[float]]:
    """:func:`denoise_output` ``repeat`` times, one output held at a time: the last output and
    every run's seconds."""
    seconds = []
    for _ in range(repeat):
        output = None
        output = denoise_output(render, denoiser)
        seconds.append(output.seconds)
    return output, seconds


def _warm_up(scene: Any, settings: RenderSettings, aovs: tuple[str, ...],
             denoisers: dict[str, Denoiser | None]) -> None:
    """Compile the render kernels (power-of-two and other spp differ; the AOV pass's too, with
    OIDN) and touch every denoiser."""
    first, third = render_input(scene, 1, settings, aovs), render_input(scene, 3, settings, aovs)
    for denoiser in denoisers.values():
        denoise_output(first, denoiser)
    if OIDN in denoisers:
        with_aovs(third, scene, settings)
        oidn_output(with_aovs(first, scene, settings)[0], aux=True)


def _oidn_aux_point(scene: Any, settings: RenderSettings, noisy: RenderResult, render_times: list[float],
                    repeat: int, reference: np.ndarray) -> Point:
    """OIDN + albedo + normal on ``noisy``: each of the ``repeat`` render times plus an AOV pass's."""
    passes = [with_aovs(noisy, scene, settings) for _ in range(repeat)]
    outputs = [oidn_output(passes[-1][0], aux=True) for _ in range(repeat)]
    times = [o.seconds for o in outputs]
    with_pass = [r + seconds for r, (_, seconds) in zip(render_times, passes)]
    return Point(OIDN_AUX, noisy.spp, _median(with_pass), _median(times), **score(outputs[-1].image, reference),
                 render_times=with_pass, denoise_times=times)


def measure(cfg: TradeoffConfig, progress: ProgressFactory | None = None) -> dict[str, Any]:
    """Run the measurements of ``cfg``; returns the JSON-ready result (see :func:`run_tradeoff`)."""
    cfg.check()
    settings = cfg.render
    labels = model_labels(cfg.models)
    models = {name: make_denoiser(path, settings) for name, path in labels.items()}
    reference = read_reference(settings)
    aovs = aovs_for(models.values())
    scene = settings.load(aovs)
    check_memory(scene, settings, max(cfg.spp), aovs,
                 ["denoised", *(["reference"] if settings.reference_spp else [])])  # a reference file is read already
    oidn = oidn_available() if cfg.compare_oidn is None else cfg.compare_oidn
    denoisers: dict[str, Denoiser | None] = {**models, **({OIDN: None} if oidn else {})}
    spps = sorted(cfg.spp)
    bar = progress(len(spps) * (1 + len(denoisers) + int(oidn)) + 1) if progress else None
    _warm_up(scene, settings, aovs, denoisers)
    ref_info: dict[str, Any] = {"file": settings.reference}
    if settings.reference_spp:
        _describe(bar, f"reference {settings.reference_spp} spp")
        ref = render_reference(settings, scene, aovs, _share(bar))
        reference, ref_info = ref.rgb, {"spp": settings.reference_spp, "seconds": ref.seconds}
    _advance(bar)
    assert reference is not None
    points: list[Point] = []
    for spp in spps:
        _describe(bar, f"{spp} spp: render")
        render_times = []
        for _ in range(cfg.repeat):  # one render held at a time: any --repeat takes the same memory
            noisy = None
            noisy = render_input(scene, spp, settings, aovs, _share(bar))
            render_times.append(noisy.seconds)
        check_reference(settings, reference, noisy)
        points.append(Point("none", spp, _median(render_times), 0.0, **score(noisy.rgb, reference),
                            render_times=render_times, denoise_times=[]))
        _advance(bar)
        for name, denoiser in denoisers.items():
            _describe(bar, f"{spp} spp: {name}")
            output, times = _timed(noisy, denoiser, cfg.repeat)
            points.append(Point(name, spp, _median(render_times), _median(times),
                                **score(output.image, reference), render_times=render_times,
                                denoise_times=times))
            _advance(bar)
        if oidn:
            _describe(bar, f"{spp} spp: {OIDN_AUX}")
            points.append(_oidn_aux_point(scene, settings, noisy, render_times, cfg.repeat, reference))
            _advance(bar)
    if bar:
        bar.close()
    h, w = reference.shape[:2]
    info = {
        "scene": str(settings.scene), "resolution": [w, h], "megapixels": w * h / 1e6, "seed": settings.seed,
        "reference": ref_info, "mitsuba": metadata.version("mitsuba"), "variant": noisy.variant,
        "models": {name: {"checkpoint": str(d.path), "sha256": d.sha256,
                          "precision": d.precision, "flips": d.flips, "config": d.config.to_dict(),
                          **d.ensemble_record()} for name, d in models.items()},
    }
    return analyse(points, info, cfg.metric)


def _describe(bar: ProgressBar | None, text: str) -> None:
    if bar:
        bar.set_description(text)


def _share(bar: ProgressBar | None) -> Callable[[int, int], None] | None:
    """A render's progress shown as the share of its samples done, after the bar's step."""
    if bar is None:
        return None
    return lambda done, total: bar.set_postfix_str(f"{done / total:.0%} of the samples")


def _advance(bar: ProgressBar | None) -> None:
    if bar:
        bar.update(1)


def analyse(points: list[Point], info: dict[str, Any], metric: str) -> dict[str, Any]:
    """Pareto fronts (per metric) and equal-quality savings of every denoised point."""
    noisy = [p for p in points if p.denoiser == "none"]
    result: dict[str, Any] = {**info, "metric": metric, "points": [], "pareto": {}, "equal_quality": []}
    for m in METRICS:
        front = pareto_front([p.total_s for p in points], [p.error(m) for p in points])
        result["pareto"][m] = [[points[i].denoiser, points[i].spp] for i in front]
    for p in points:
        row = {"denoiser": p.denoiser, "spp": p.spp, "render_s": p.render_s, "denoise_s": p.denoise_s,
               "total_s": p.total_s, "psnr": p.psnr, "relmse": p.relmse, "flip": p.flip,
               "render_times": p.render_times, "denoise_times": p.denoise_times}
        result["points"].append(row)
        if p.denoiser == "none":
            continue
        for m in METRICS:
            eq = equal_quality([q.spp for q in noisy], [q.error(m) for q in noisy],
                               [q.render_s for q in noisy], p.spp, p.total_s, p.error(m))
            result["equal_quality"].append({"denoiser": p.denoiser, "spp": p.spp, "metric": m,
                                            "total_s": p.total_s, **asdict(eq)})
    return result


RESULT_NAMES = ("config.json", "tradeoff.json", "tradeoff.csv", "tradeoff.png", "report.html")
OUTPUT_NAMES = (*RESULT_NAMES, ".write-test")  # with the writability probe


def _prepare_out(out: Path) -> None:
    """Create ``out`` and check it is writable; drop an earlier run's ``tradeoff.json`` (the
    completion marker; there with ``overwrite``) so that it never sits beside new, unfinished outputs."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
        (out / "tradeoff.json").unlink(missing_ok=True)
    except OSError as exc:
        raise DenoiserError(f"{out}: output folder is not usable ({exc.strerror or exc})") from None


def run_tradeoff(cfg: TradeoffConfig, progress: ProgressFactory | None = None) -> dict[str, Any]:
    """Measure, then write ``tradeoff.json`` (written last), ``.csv``, ``.png``, ``report.html``
    and ``config.json`` into ``cfg.out``; returns the result dict (points, pareto, equal_quality, scene info)."""
    from pipeline.tradeoff_report import plot_tradeoff, write_csv, write_report

    out = Path(cfg.out)
    cfg.check()
    cfg.render.check_outputs(out, OUTPUT_NAMES)
    check_output_folder(out, RESULT_NAMES, cfg.render.overwrite)
    _prepare_out(out)
    write_json_atomic(out / "config.json", asdict(cfg))
    result = measure(cfg, progress)
    write_csv(out / "tradeoff.csv", result)
    plot_tradeoff(out / "tradeoff.png", result)
    write_report(out / "report.html", json_safe(result), out / "tradeoff.png")
    write_json_atomic(out / "tradeoff.json", result)
    return result
