"""``render-and-denoise --time-budget SECONDS``: choose spp (and with ``--model auto`` the model) so
that the denoised image is ready within the budget.

The budget is wall time from the start of the run until the denoised image exists: loading,
the probes below, the render and the denoise. The reference render, OIDN, metrics and files come
after and are not counted.

* **Render cost** (:func:`probe_render`): renders at 1 and 3 spp compile both kernel variants
  (Mitsuba's power-of-two and other sample counts differ), then a clean 1-spp render and one at
  ``p`` spp (``p`` sized to ~5% of the budget) give ``seconds = fixed + per_spp * spp``.
* **Denoise cost** (:func:`denoise_seconds`): each candidate model times two small images, giving
  seconds per call and per pixel, applied to the real image's tiles (they overlap by the margin).
* **Choice** (:func:`plan_budget`): per candidate, the largest spp whose predicted total fits. With
  trade curves (``tradeoff.json`` of a ``tradeoff`` run) the candidate whose curve predicts the
  lowest error at its spp wins. Without curves the rule is: the best registry entry
  (:func:`quality_order`, by measured quality) whose denoising takes at most a third of the time
  left, else the fastest that fits — samples keep at least two thirds of the time.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from imaging.errors import DenoiserError
from imaging.json_read import parse_json
from rendering.render import render_loaded
from denoise.tiling import Core, plan_tiles
from denoise.denoiser import Denoiser
from model.registry import AUTO, CARD_SPP, registry
from pipeline.evaluation import RenderSettings, make_denoiser
from pipeline.pareto import error_at_spp, metric_error

DENOISE_SHARE = 1.0 / 3.0
PROBE_SHARE = 0.05
MAX_SPP = 1 << 16
Curves = dict[str, tuple[list[float], list[float]]]  # denoiser -> (spp, error)


class BudgetError(DenoiserError):
    """The budget cannot be met (too small) or its inputs are unusable (no models, bad curves)."""


@dataclass(frozen=True)
class RenderCost:
    """Render wall time model of one loaded scene: ``fixed_s + per_spp_s * spp``."""

    fixed_s: float
    per_spp_s: float
    probe_s: float = 0.0

    def seconds(self, spp: float) -> float:
        return self.fixed_s + self.per_spp_s * spp


@dataclass
class BudgetPlan:
    """The choice: ``model`` at ``spp``; predicted seconds of each part; ``spent_s`` already used
    (loading, probes) when the plan was made; ``options``: every candidate's best fit."""

    budget_s: float
    model: str
    spp: int
    spent_s: float
    predicted_render_s: float
    predicted_denoise_s: float
    rule: str
    options: list[dict[str, Any]] = field(default_factory=list)
    render_cost: dict[str, float] = field(default_factory=dict)
    actual_s: float | None = None

    @property
    def predicted_s(self) -> float:
        return self.spent_s + self.predicted_render_s + self.predicted_denoise_s

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "predicted_s": self.predicted_s}


def fit_spp(time_left_s: float, render: RenderCost, denoise_s: float, max_spp: int = MAX_SPP) -> int:
    """Largest spp (<= ``max_spp``) with render + denoise within ``time_left_s``; 0 if none."""
    room = time_left_s - denoise_s - render.fixed_s
    if room < render.per_spp_s:
        return 0
    if render.per_spp_s <= 0:
        return max_spp
    return int(min(max_spp, math.floor(room / render.per_spp_s * (1 + 1e-9))))  # 1e-9: float noise


def plan_budget(budget_s: float, spent_s: float, render: RenderCost, denoise_s: Mapping[str, float],
                curves: Curves | None = None, max_spp: int = MAX_SPP) -> BudgetPlan:
    """Choose a model (a key of ``denoise_s``: its predicted seconds on this image) and spp.

    Raises :class:`BudgetError` when no candidate fits 1 spp in the time left.
    """
    left = budget_s - spent_s
    options = [{"model": name, "spp": fit_spp(left, render, secs, max_spp), "denoise_s": secs}
               for name, secs in denoise_s.items()]
    fitting = [o for o in options if o["spp"] >= 1]
    if not fitting:
        need = min(render.seconds(1) + s for s in denoise_s.values())
        raise BudgetError(f"time budget {budget_s:.3g} s is too small: {spent_s:.2f} s went to loading "
                          f"and probing, and 1 spp + denoising needs {need:.2f} s more")
    scored = [o for o in fitting if curves and o["model"] in curves]
    for o in scored:
        o["predicted_error"] = error_at_spp(*curves[o["model"]], o["spp"])  # type: ignore[index]
    scored = [o for o in scored if math.isfinite(o["predicted_error"])]
    if len(fitting) == 1:
        best, rule = fitting[0], "the only model that fits; largest spp that fits"
    elif scored:
        best = min(scored, key=lambda o: o["predicted_error"])
        rule = "lowest error predicted by the trade curves at the largest spp that fits"
    else:
        best, rule = _rule_without_curves(fitting, left)
    return BudgetPlan(budget_s, best["model"], best["spp"], spent_s, render.seconds(best["spp"]),
                      best["denoise_s"], rule, options, asdict(render))


def quality_order() -> tuple[str, ...]:
    """The registry's entries, best first: by mean measured PSNR over the cards' spp, entries
    without figures after them in the manifest's reverse order (it lists the quickest first)."""
    entries = list(registry().entries.values())[::-1]

    def key(entry: Any) -> float:
        psnr = [entry.psnr(s) for s in CARD_SPP]
        return -sum(psnr) / len(psnr) if all(p is not None for p in psnr) else math.inf

    return tuple(e.name for e in sorted(entries, key=key))


def _rule_without_curves(fitting: list[dict[str, Any]], left: float) -> tuple[dict[str, Any], str]:
    order = quality_order()

    def rank(o: dict[str, Any]) -> int:
        return order.index(o["model"]) if o["model"] in order else len(order)

    cheap = [o for o in fitting if o["denoise_s"] <= DENOISE_SHARE * left]
    if cheap:
        return min(cheap, key=lambda o: (rank(o), o["denoise_s"])), \
            "no trade curves: best model whose denoising takes at most 1/3 of the time left"
    return min(fitting, key=lambda o: o["denoise_s"]), "no trade curves: fastest model that fits"


def load_curves(path: str | Path, metric: str = "relmse") -> Curves:
    """Error against spp of each denoiser in a ``tradeoff.json``; raises :class:`BudgetError`."""
    try:
        data = parse_json(Path(path).read_text())
        curves: Curves = {}
        for p in data["points"]:
            spp, err = curves.setdefault(p["denoiser"], ([], []))
            spp.append(float(p["spp"]))
            err.append(metric_error(metric, p[metric]))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise BudgetError(f"{path}: not a usable tradeoff.json ({exc})") from None
    return curves


def probe_render(scene: Any, seed: int, aovs: Sequence[str], budget_s: float,
                 halves: bool = False) -> RenderCost:
    """Measure ``fixed + per_spp * spp`` for a loaded scene (see the module docstring).

    ``halves``: the render will be made in two halves (the noise guard), two calls of the
    measured fixed cost."""
    start = time.perf_counter()
    render_loaded(scene, 1, seed, aovs)
    rough = render_loaded(scene, 3, seed, aovs).seconds / 3
    t1 = render_loaded(scene, 1, seed, aovs).seconds
    p = int(min(256, max(4, PROBE_SHARE * budget_s / max(rough, 1e-6))))
    tp = render_loaded(scene, p, seed, aovs).seconds
    per = (tp - t1) / (p - 1)
    fixed = t1 - per
    if per <= 0 or fixed < 0:  # timing noise: no fixed cost, the mean cost per sample
        per, fixed = tp / p, 0.0
    return RenderCost(2 * fixed if halves else fixed, per, time.perf_counter() - start)


def window_pixels(height: int, width: int, core: Core, margin: int) -> int:
    """Pixels the network processes for an image: the sum of its tile windows."""
    return sum((t.wy1 - t.wy0) * (t.wx1 - t.wx0) for t in plan_tiles(height, width, core, margin))


def probe_spps(denoiser: Denoiser) -> list[int]:
    """One spp in each range where a different set of an ensemble's members runs: 1 and every
    member's lowest spp (a single model: just 1)."""
    return sorted({1} | {m.min_spp for m in denoiser.members if m.min_spp})


def denoise_seconds(denoiser: Denoiser, height: int, width: int, side: int = 128) -> float:
    """Predicted seconds to denoise an HxW image: timed runs on (side/2)^2 and side^2 images give
    a cost per call and per window pixel, applied to the real image's tiles. An ensemble is
    predicted so in every spp range where a different set of its members runs (:func:`probe_spps`;
    their formats differ too: the default's flat member is in bfloat16 up to 16 spp only) and the
    dearest prediction is taken, whatever spp the plan then chooses."""
    side = max(16, min(side, max(height, width)))
    img = np.random.default_rng(0).random((side, side, 3), dtype=np.float32)
    margin = denoiser.margin
    half = side // 2
    px_half = window_pixels(half, half, denoiser.cores(half, half), margin)
    px_full = window_pixels(side, side, denoiser.cores(side, side), margin)
    core = denoiser.cores(height, width)
    tiles = sum(1 for _ in plan_tiles(height, width, core, margin))
    pixels = window_pixels(height, width, core, margin)

    def predicted(spp: int) -> float:
        denoiser.denoise_array(img[:16, :16], spp=spp)  # warm-up
        t_half = denoiser.denoise_array(img[:half, :half], spp=spp).seconds
        t_full = denoiser.denoise_array(img, spp=spp).seconds
        per_px = (t_full - t_half) / (px_full - px_half)
        per_call = t_half - per_px * px_half
        if per_px <= 0 or per_call < 0:  # timing noise: all of it per pixel
            per_px, per_call = t_full / px_full, 0.0
        return per_call * tiles + per_px * pixels

    return max(predicted(spp) for spp in probe_spps(denoiser))


def budget_candidates(model: str | None, settings: RenderSettings) -> dict[str, Denoiser]:
    """Models to choose from: for ``auto`` every registry entry (best first, :func:`quality_order`),
    else the one given."""
    if model != AUTO:
        den = make_denoiser(model, settings)
        return {den.label: den}
    return {name: make_denoiser(name, settings) for name in quality_order()}


def plan_run(budget_s: float, started: float, scene: Any, seed: int, aovs: Sequence[str],
             candidates: Mapping[str, Denoiser], curves_path: str | Path | None,
             log: Callable[[str], None] = lambda s: None, halves: bool = False) -> BudgetPlan:
    """Probe the scene and the candidates, then :func:`plan_budget`; ``started`` is the
    ``time.perf_counter()`` at which the budget began; ``halves`` as in :func:`probe_render`."""
    if not budget_s > 0:
        raise BudgetError(f"time budget must be positive, got {budget_s}")
    curves = load_curves(curves_path) if curves_path and len(candidates) > 1 else None
    log("probing render cost")
    render = probe_render(scene, seed, aovs, budget_s, halves)
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    denoise_s = {name: denoise_seconds(den, height, width) for name, den in candidates.items()}
    plan = plan_budget(budget_s, time.perf_counter() - started, render, denoise_s, curves, MAX_SPP)
    log(f"budget {budget_s:g} s: {plan.model} at {plan.spp} spp, predicted {plan.predicted_s:.2f} s")
    return plan
