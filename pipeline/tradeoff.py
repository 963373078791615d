"""``tradeoff``'s measurement loop: error against time for each spp and each denoiser.

For every spp the scene is rendered ``repeat`` times with the same seed (the same image; the
median wall time is kept), then each denoiser — ``none`` (the raw render), each model, OIDN if
asked — runs ``repeat`` times on it (median time). The image is compared with the reference
(PSNR, relMSE, FLIP: :mod:`imaging.metrics`). Kernels are compiled and the networks warmed up
before anything is timed. Outputs (:mod:`pipeline.tradeoff_report`): ``tradeoff.json``,
``tradeoff.csv``, ``tradeoff.png`` and ``config.json`` (this run's :class:`TradeoffConfig`).
"""
from __future__ import annotations

import json
import math
import statistics
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from imaging.atomic_io import write_text_atomic
from imaging.errors import DenoiserError
from imaging.exr import read_exr
from imaging.hashing import file_sha256
from imaging.metrics import flip, psnr, relmse
from imaging.render import RenderResult, load_scene, pass_seeds, prepare, render_loaded
from model.config import PRESETS
from pipeline.denoise import Denoiser, resolve_model
from pipeline.oidn import oidn_denoise
from pipeline.pareto import ERROR_OF_METRIC, equal_quality, metric_error, pareto_front

DEFAULT_SPP = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024)
DEFAULT_MODELS = ("fast", "balanced", "high")
METRICS = ("psnr", "relmse", "flip")


class ProgressBar(Protocol):
    """The part of ``tqdm`` the loop uses."""

    def update(self, n: int = 1) -> Any: ...
    def set_description(self, desc: str | None = None, refresh: bool = True) -> Any: ...
    def close(self) -> Any: ...


@dataclass
class TradeoffConfig:
    """Settings of one ``tradeoff`` run (filled by the CLI, saved as config.json).

    ``models``: preset names (weights in ``model/weights/<name>.ckpt``) or checkpoint paths.
    ``metric``: the error that the plot, the Pareto front and the printed saving table use.
    """

    scene: str
    out: str
    spp: list[int] = field(default_factory=lambda: list(DEFAULT_SPP))
    models: list[str] = field(default_factory=lambda: list(DEFAULT_MODELS))
    compare_oidn: bool = False
    reference: str | None = None
    reference_spp: int | None = None
    repeat: int = 3
    resolution: tuple[int, int] | None = None
    seed: int = 0
    params: dict[str, str] = field(default_factory=dict)
    metric: str = "relmse"
    max_memory_mb: float = 1024.0
    noise_guard: bool = True  # as render-and-denoise: renders in two halves, our models guarded

    def check(self) -> None:
        """Raise :class:`DenoiserError` for settings that cannot give a measurement."""
        if not self.spp or any(s < 1 for s in self.spp) or len(set(self.spp)) != len(self.spp):
            raise DenoiserError(f"spp levels must be distinct positive integers, got {self.spp}")
        if (self.reference is None) == (self.reference_spp is None):
            raise DenoiserError("give exactly one of --reference FILE or --reference-spp N "
                                "(errors are measured against it)")
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


def model_labels(models: list[str]) -> dict[str, Path]:
    """Label -> checkpoint for each ``--models`` entry (preset name, else file stem; made unique).

    Raises :class:`DenoiserError` naming the file when a preset's weights or a file are missing.
    """
    labels: dict[str, Path] = {}
    for name in models:
        path = resolve_model(name)
        if not path.is_file():
            raise DenoiserError(f"{path}: checkpoint not found")
        label = name if name in PRESETS else path.stem
        base, n = label, 2
        while label in labels or label in ("none", "oidn"):
            label, n = f"{base}-{n}", n + 1
        labels[label] = path
    return labels


def _median(values: list[float]) -> float:
    return float(statistics.median(values))


def _quality(img: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    return {"psnr": psnr(img, ref), "relmse": relmse(img, ref), "flip": flip(img, ref)}


def _timed(fn: Callable[[], tuple[np.ndarray, float]], repeat: int) -> tuple[np.ndarray, list[float]]:
    times = []
    for _ in range(repeat):
        image, seconds = fn()
        times.append(seconds)
    return image, times


def _denoise_fns(denoisers: dict[str, Denoiser], oidn: bool
                 ) -> dict[str, Callable[[RenderResult], tuple[np.ndarray, float]]]:
    def ours(den: Denoiser) -> Callable[[RenderResult], tuple[np.ndarray, float]]:
        def run(r: RenderResult) -> tuple[np.ndarray, float]:
            res = den.denoise_render(r)
            return res.image, res.seconds
        return run

    fns = {name: ours(den) for name, den in denoisers.items()}
    if oidn:
        fns["oidn"] = lambda r: oidn_denoise(r.rgb)
    return fns


def _warm_up(scene: Any, seed: int, aovs: tuple[str, ...],
             fns: dict[str, Callable[[RenderResult], tuple[np.ndarray, float]]]) -> None:
    """Compile the render kernels (power-of-two and other spp differ) and touch every denoiser."""
    first = render_loaded(scene, 1, seed, aovs)
    render_loaded(scene, 3, seed, aovs)
    for fn in fns.values():
        fn(first)


def measure(cfg: TradeoffConfig, progress: Callable[[int], ProgressBar] | None = None
            ) -> dict[str, Any]:
    """Run the measurements of ``cfg``; returns the JSON-ready result (see :func:`run_tradeoff`)."""
    cfg.check()
    labels = model_labels(cfg.models)
    denoisers = {name: Denoiser(path, max_memory_mb=cfg.max_memory_mb) for name, path in labels.items()}
    reference = read_exr(cfg.reference).rgb if cfg.reference else None
    aovs = ("albedo", "sh_normal") if any(d.needs_aovs for d in denoisers.values()) else ()
    scene = load_scene(prepare(cfg.scene, cfg.resolution, aovs, cfg.params))
    fns = _denoise_fns(denoisers, cfg.compare_oidn)
    spps = sorted(cfg.spp)
    bar = progress(len(spps) * (1 + len(fns)) + 1) if progress else None
    _warm_up(scene, cfg.seed, aovs, fns)
    ref_info: dict[str, Any] = {"file": cfg.reference}
    if cfg.reference_spp:
        if bar:
            bar.set_description(f"reference {cfg.reference_spp} spp")
        ref = render_loaded(scene, cfg.reference_spp, pass_seeds(cfg.seed, 2)[1], aovs)
        reference, ref_info = ref.rgb, {"spp": cfg.reference_spp, "seconds": ref.seconds}
    if bar:
        bar.update(1)
    assert reference is not None
    points: list[Point] = []
    for spp in spps:
        if bar:
            bar.set_description(f"{spp} spp: render")
        renders = [render_loaded(scene, spp, cfg.seed, aovs, halves=cfg.noise_guard)
                   for _ in range(cfg.repeat)]
        noisy = renders[-1]
        if reference.shape != noisy.rgb.shape:
            raise DenoiserError(f"{cfg.reference}: reference is {reference.shape[1]}x{reference.shape[0]}"
                                f", render is {noisy.rgb.shape[1]}x{noisy.rgb.shape[0]}")
        render_times = [r.seconds for r in renders]
        points.append(Point("none", spp, _median(render_times), 0.0, **_quality(noisy.rgb, reference),
                            render_times=render_times, denoise_times=[]))
        if bar:
            bar.update(1)
        for name, fn in fns.items():
            if bar:
                bar.set_description(f"{spp} spp: {name}")
            image, times = _timed(lambda: fn(noisy), cfg.repeat)
            points.append(Point(name, spp, _median(render_times), _median(times),
                                **_quality(image, reference), render_times=render_times,
                                denoise_times=times))
            if bar:
                bar.update(1)
    if bar:
        bar.close()
    h, w = reference.shape[:2]
    info = {
        "scene": str(cfg.scene), "resolution": [w, h], "megapixels": w * h / 1e6, "seed": cfg.seed,
        "reference": ref_info, "mitsuba": metadata.version("mitsuba"), "variant": noisy.variant,
        "models": {name: {"checkpoint": str(d.path), "sha256": file_sha256(d.path),
                          "config": d.config.to_dict()} for name, d in denoisers.items()},
    }
    return analyse(points, info, cfg.metric)


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


def json_safe(value: Any) -> Any:
    """Non-finite floats -> None (JSON has no inf/NaN); containers converted recursively."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def _prepare_out(out: Path) -> None:
    """Create ``out`` and check it is writable; drop an earlier run's ``tradeoff.json`` (the
    completion marker) so that it never sits beside new, unfinished outputs."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
        (out / "tradeoff.json").unlink(missing_ok=True)
    except OSError as exc:
        raise DenoiserError(f"{out}: output folder is not usable ({exc.strerror or exc})") from None


def run_tradeoff(cfg: TradeoffConfig, progress: Callable[[int], ProgressBar] | None = None
                 ) -> dict[str, Any]:
    """Measure, then write ``tradeoff.json`` (written last), ``.csv``, ``.png``, ``report.html``
    and ``config.json`` into ``cfg.out``; returns the result dict (points, pareto, equal_quality, scene info)."""
    from pipeline.tradeoff_report import plot_tradeoff, write_csv, write_report

    out = Path(cfg.out)
    cfg.check()
    _prepare_out(out)
    write_text_atomic(out / "config.json", json.dumps(asdict(cfg), indent=1) + "\n")
    result = measure(cfg, progress)
    write_csv(out / "tradeoff.csv", result)
    plot_tradeoff(out / "tradeoff.png", result)
    write_report(out / "report.html", json_safe(result), out / "tradeoff.png")
    write_text_atomic(out / "tradeoff.json", json.dumps(json_safe(result), indent=1) + "\n")
    return result
