"""``render-and-denoise --time-budget SECONDS``: choose spp (and with ``--model auto`` the model) so
that the denoised image is ready within the budget, on the host as it is during the run.

The budget is wall time from the start of the command (its interpreter and imports included; a
call of :func:`pipeline.run.run`: from its ``started``, by default the call) until the denoised
image exists: loading, the calibration and probes below, loading the chosen model, the render and
the denoise. The reference render, OIDN, metrics and files come after and are not counted.

* **Host speed** (:func:`pipeline.budget_costs.measure_speed`): two small fixed workloads timed
  now, under whatever load the host has, against their times recorded with the models' costs:
  the slowdowns that scale them.
* **Render cost** (:func:`probe_render`): renders at 1 and 3 spp compile both kernel variants
  (Mitsuba's power-of-two and other sample counts differ), then a clean 1-spp render and one at
  ``p`` spp (``p`` sized to ~5% of the budget) give ``seconds = fixed + per_spp * spp``.
* **Model cost**: a registry entry's recorded costs (:mod:`pipeline.budget_costs`: loading it,
  its first call, per tile call and per window pixel) times the slowdown, on the real image's
  tiles; any other model (or other settings) is loaded at the start and times two small images
  now (:func:`denoise_seconds`).
* **Choice** (:func:`plan_budget`): per candidate, the largest spp whose predicted total fits. With
  trade curves (``tradeoff.json`` of a ``tradeoff`` run) the candidate whose curve predicts the
  lowest error at its spp wins. Without curves the rule is: the best registry entry
  (:func:`quality_order`, by measured quality) whose loading and denoising take at most a third of
  the time left, else the fastest that fits — samples keep at least two thirds of the time.
* **Checks against the clock**: once the chosen model is loaded, the spp is fitted again to the
  time then left (:func:`refit_spp`); after the render, a model predicted to end past the budget
  gives way to the candidate predicted to end first (:func:`after_render`). Each change is a note
  in the plan.
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
from denoise.denoiser import DEFAULT_MAX_MEMORY_MB, Denoiser
from model.registry import AUTO, CARD_SPP, registry
from pipeline.budget_costs import EntryCost, RecordedCosts, Speed, calibrate, measure_speed
from pipeline.evaluation import RenderSettings, make_denoiser
from pipeline.pareto import error_at_spp, metric_error

DENOISE_SHARE = 1.0 / 3.0
PROBE_SHARE = 0.05
MAX_SPP = 1 << 16
Curves = dict[str, tuple[list[float], list[float]]]  # denoiser -> (spp, error)
Candidate = Denoiser | EntryCost  # a model loaded (timed now) or a registry entry's recorded costs


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
    """The choice: ``model`` at ``spp``; predicted seconds of each part (``predicted_load_s``:
    loading the model, where that was still to do); ``spent_s`` already used (imports, loading,
    calibration, probes) when the plan was made; ``options``: every candidate's best fit;
    ``speed``: the host's measured speed (:meth:`pipeline.budget_costs.Speed.to_dict`); ``costs``:
    where the models' costs came from; ``notes``: what the checks against the clock changed, and
    why; ``actual_s``: when the denoised image existed."""

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
    predicted_load_s: float = 0.0
    speed: dict[str, Any] = field(default_factory=dict)
    costs: str = ""
    notes: list[str] = field(default_factory=list)

    @property
    def predicted_s(self) -> float:
        return self.spent_s + self.predicted_load_s + self.predicted_render_s + self.predicted_denoise_s

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


def too_small(budget_s: float, spent_s: float, need_s: float, speed: Speed | None) -> BudgetError:
    """The error of a budget that cannot be met: ``spent_s`` gone, ``need_s`` more needed at least."""
    host = (f" (the host runs the networks at {1 / speed.slowdown:.2f}x and loads them at "
            f"{1 / speed.loading_slowdown:.2f}x the speed their costs were recorded at)"
            if speed and speed.recorded_s and speed.recorded_loading_s else "")
    return BudgetError(f"time budget {budget_s:.3g} s is too small: {spent_s:.2f} s went to starting, "
                       f"calibrating and probing, and loading a model, 1 spp and denoising need "
                       f"{need_s:.2f} s more{host}")


def plan_budget(budget_s: float, spent_s: float, render: RenderCost, denoise_s: Mapping[str, float],
                curves: Curves | None = None, max_spp: int = MAX_SPP, *,
                load_s: Mapping[str, float] | None = None, speed: Speed | None = None) -> BudgetPlan:
    """Choose a model (a key of ``denoise_s``: its predicted seconds on this image; ``load_s``: the
    seconds to load it, where that is still to do) and spp. ``speed``: what the predictions
    assumed of the host, for the record and the error.

    Raises :class:`BudgetError` when no candidate fits 1 spp in the time left.
    """
    left = budget_s - spent_s
    loads = {name: (load_s or {}).get(name, 0.0) for name in denoise_s}
    options = [{"model": name, "spp": fit_spp(left, render, secs + loads[name], max_spp), "denoise_s": secs,
                "load_s": loads[name]} for name, secs in denoise_s.items()]
    fitting = [o for o in options if o["spp"] >= 1]
    if not fitting:
        raise too_small(budget_s, spent_s, min(render.seconds(1) + s + loads[n] for n, s in denoise_s.items()),
                        speed)
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
                      best["denoise_s"], rule, options, asdict(render), predicted_load_s=best["load_s"],
                      speed=speed.to_dict() if speed else {})


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

    def cost(o: dict[str, Any]) -> float:
        return o["denoise_s"] + o["load_s"]

    cheap = [o for o in fitting if cost(o) <= DENOISE_SHARE * left]
    if cheap:
        return min(cheap, key=lambda o: (rank(o), cost(o))), \
            "no trade curves: best model whose loading and denoising take at most 1/3 of the time left"
    return min(fitting, key=cost), "no trade curves: fastest model that fits"


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


def tile_rates(denoiser: Denoiser, img: np.ndarray, spp: int) -> tuple[float, float]:
    """Seconds per tile call and per window pixel of ``denoiser`` at ``spp``: timed runs on the
    square ``img`` (side^2) and on its (side/2)^2 corner, after a warm-up on a 16x16 corner."""
    side, margin = img.shape[0], denoiser.margin
    half = side // 2
    px_half = window_pixels(half, half, denoiser.cores(half, half), margin)
    px_full = window_pixels(side, side, denoiser.cores(side, side), margin)
    denoiser.denoise_array(img[:16, :16], spp=spp)  # warm-up
    t_half = denoiser.denoise_array(img[:half, :half], spp=spp).seconds
    t_full = denoiser.denoise_array(img, spp=spp).seconds
    per_px = (t_full - t_half) / (px_full - px_half)
    per_call = t_half - per_px * px_half
    if per_px <= 0 or per_call < 0:  # timing noise: all of it per pixel
        per_px, per_call = t_full / px_full, 0.0
    return per_call, per_px


def probe_image(side: int) -> np.ndarray:
    """The seeded side x side image the denoise probes time."""
    return np.random.default_rng(0).random((side, side, 3), dtype=np.float32)


def denoise_seconds(denoiser: Denoiser, height: int, width: int, side: int = 128) -> float:
    """Predicted seconds to denoise an HxW image: :func:`tile_rates` on a side^2 image, applied to
    the real image's tiles. An ensemble is predicted so in every spp range where a different set of
    its members runs (:func:`probe_spps`; their formats differ too: the default's flat member is
    in bfloat16 up to 16 spp only) and the dearest prediction is taken, whatever spp the plan then
    chooses."""
    img = probe_image(max(16, min(side, max(height, width))))
    core = denoiser.cores(height, width)
    tiles = sum(1 for _ in plan_tiles(height, width, core, denoiser.margin))
    pixels = window_pixels(height, width, core, denoiser.margin)

    def predicted(spp: int) -> float:
        per_call, per_px = tile_rates(denoiser, img, spp)
        return per_call * tiles + per_px * pixels

    return max(predicted(spp) for spp in probe_spps(denoiser))


def budget_candidates(model: str | None, settings: RenderSettings,
                      costs: RecordedCosts | None = None) -> dict[str, Candidate]:
    """Models to choose from: for ``auto`` every registry entry (best first, :func:`quality_order`),
    else the one given (None: the registry's default). A registry entry whose costs ``costs``
    records for these settings on this CPU stays unloaded (its :class:`EntryCost`); any other
    model is loaded."""
    from denoise.precision import native_bfloat16

    usable = costs is not None and costs.usable(settings.device, settings.precision, settings.flips,
                                                native_bfloat16())

    def entry(name: str) -> Candidate:
        cost = costs.entry(name) if usable and costs else None
        return cost if cost is not None else make_denoiser(name, settings)

    if model == AUTO:
        return {name: entry(name) for name in quality_order()}
    name = registry().default if model is None else model
    if name in registry().entries:
        return {name: entry(name)}
    den = make_denoiser(model, settings)
    return {den.label: den}


def plan_run(budget_s: float, started: float, scene: Any, seed: int, aovs: Sequence[str],
             candidates: Mapping[str, Candidate], curves_path: str | Path | None,
             log: Callable[[str], None] = lambda s: None, halves: bool = False,
             max_memory_mb: float = DEFAULT_MAX_MEMORY_MB,
             recorded: tuple[float, float] | None = None) -> BudgetPlan:
    """Measure the host's speed (against ``recorded``, the recorded costs' calibration times:
    :func:`pipeline.budget_costs.measure_speed`), predict each candidate's cost (recorded costs
    times the slowdowns, or timed now for a loaded model; a budget that the cheapest recorded
    model alone overruns fails here), probe the scene, then :func:`plan_budget`; ``started`` is
    the ``time.perf_counter()`` at which the budget began; ``halves`` as in :func:`probe_render`;
    ``max_memory_mb`` plans the tiles of the recorded costs."""
    if not budget_s > 0:
        raise BudgetError(f"time budget must be positive, got {budget_s}")
    curves = load_curves(curves_path) if curves_path and len(candidates) > 1 else None
    log("calibrating the host's speed")
    speed = measure_speed(recorded, calibrate)
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    costs = {name: c for name, c in candidates.items() if isinstance(c, EntryCost)}
    denoise_s = {name: c.denoise_s(height, width, max_memory_mb, speed) for name, c in costs.items()}
    load_s = {name: c.load_s * speed.loading_slowdown for name, c in costs.items()}
    if len(costs) == len(candidates):  # known already: a budget the model alone overruns fails now
        need = min(denoise_s[name] + load_s[name] for name in costs)
        if need >= budget_s - (time.perf_counter() - started):
            raise too_small(budget_s, time.perf_counter() - started, need, speed)
    log("probing render cost")
    render = probe_render(scene, seed, aovs, budget_s, halves)
    for name, candidate in candidates.items():
        if name not in costs:
            denoise_s[name] = denoise_seconds(candidate, height, width)
    plan = plan_budget(budget_s, time.perf_counter() - started, render, denoise_s, curves, MAX_SPP,
                       load_s=load_s, speed=speed)
    for o in plan.options:
        o["costs"] = "recorded" if o["model"] in load_s else "timed"
    plan.costs = "recorded x the measured slowdowns" if plan.model in load_s else "timed now"
    log(f"budget {budget_s:g} s: {plan.model} at {plan.spp} spp, predicted {plan.predicted_s:.2f} s")
    return plan


def refit_spp(plan: BudgetPlan, elapsed_s: float, max_spp: int | None = None) -> None:
    """Once the chosen model is loaded (``elapsed_s`` into the budget): the largest spp (at most
    ``max_spp``, default :data:`MAX_SPP`) whose render and denoise fit the time then left (at least
    1), with a note when it differs from the plan's."""
    render = RenderCost(plan.render_cost["fixed_s"], plan.render_cost["per_spp_s"])
    left = plan.budget_s - elapsed_s
    fits = fit_spp(left, render, plan.predicted_denoise_s, MAX_SPP if max_spp is None else max_spp)
    spp = max(1, fits)
    if spp != plan.spp:
        over = "; not even 1 spp fits: the budget will be exceeded" if not fits else ""
        plan.notes.append(f"{plan.model} loaded at {elapsed_s:.1f} s ({plan.predicted_load_s:.1f} s predicted "
                          f"for it), {left:.1f} s left: {plan.spp} -> {spp} spp{over}")
        plan.spp, plan.predicted_render_s = spp, render.seconds(spp)


def after_render(plan: BudgetPlan, elapsed_s: float, render_s: float) -> str | None:
    """After the render (it took ``render_s``; ``elapsed_s`` into the budget): the candidate to
    denoise with instead of the chosen one, or None. Each candidate's predicted seconds (loading
    it, unless it is the chosen one, and denoising) are scaled by how much longer the render took
    than predicted (the host may have become busier since the probes); when the chosen model's
    prediction ends past the budget, the candidate predicted to end first takes its place if
    that is sooner. Either way the plan gets a note."""
    drift = max(1.0, render_s / plan.predicted_render_s) if plan.predicted_render_s > 0 else 1.0
    left = plan.budget_s - elapsed_s
    need = {o["model"]: drift * (o["denoise_s"] + (0.0 if o["model"] == plan.model else o["load_s"]))
            for o in plan.options}
    mine = need[plan.model]
    if mine <= left:
        return None
    best = min(need, key=lambda name: need[name])
    head = (f"render done at {elapsed_s:.1f} s ({render_s:.1f} s, {drift:.2f}x its prediction), {max(left, 0):.1f} s "
            f"left: {plan.model} predicted to need {mine:.1f} s")
    if need[best] >= mine:
        plan.notes.append(f"{head}; no other model ends sooner: the budget will be exceeded")
        return None
    plan.notes.append(f"{head}, {best} {need[best]:.1f} s: denoising with {best}")
    plan.model = best
    return best
