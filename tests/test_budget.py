"""The time-budget planner on fake cost models (and on a host made slower), its probes and its
checks against the clock on fakes, and the CLI end to end."""
from __future__ import annotations

import json
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from denoise.tiling import plan_tiles
from model.registry import registry
from pipeline import budget
from pipeline.evaluation import RenderSettings
from pipeline.budget import (BudgetError, BudgetPlan, RenderCost, after_render, budget_candidates,
                             denoise_seconds, fit_spp, load_curves, plan_budget, plan_run, probe_render,
                             refit_spp, window_pixels)
from pipeline.budget_costs import COSTS, EntryCost, read_costs
from pipeline.cli import main
from tests.test_denoiser import write_tiny_checkpoint

DEMO = Path(__file__).resolve().parents[1] / "scenes" / "examples" / "demo.xml"
RENDER = RenderCost(fixed_s=0.5, per_spp_s=0.01)
PRESETS = {"high": 4.0, "balanced": 2.0, "fast": 0.5}  # predicted denoise seconds


def test_fit_spp() -> None:
    assert fit_spp(10.0, RENDER, 2.0) == 750  # (10 - 2 - 0.5) / 0.01
    assert fit_spp(2.505, RENDER, 2.0) == 0
    assert fit_spp(100.0, RENDER, 0.0, max_spp=64) == 64
    assert fit_spp(1.0, RenderCost(0.0, 0.0), 0.5) == budget.MAX_SPP


def test_single_model_gets_the_largest_spp_that_fits() -> None:
    plan = plan_budget(11.0, 1.0, RENDER, {"mine": 2.0})
    assert (plan.model, plan.spp) == ("mine", 750)
    assert plan.predicted_s == pytest.approx(1.0 + 0.5 + 7.5 + 2.0)
    assert plan.predicted_s <= 11.0


@pytest.mark.parametrize("left, expected", [
    (20.0, "high"),      # 1/3 of 20 = 6.7: high's 4 s is cheap enough
    (9.0, "balanced"),   # 1/3 of 9 = 3: high (4 s) too slow, balanced (2 s) fits
    (3.0, "fast"),       # 1/3 of 3 = 1: only fast is cheap enough
    (2.6, "fast"),       # nothing within 1/3: the fastest that fits
])
def test_auto_rule_without_curves(left: float, expected: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(budget, "quality_order", lambda: ("high", "balanced", "fast"))  # best first, here
    plan = plan_budget(left, 0.0, RENDER, PRESETS)
    assert plan.model == expected
    assert plan.spp == fit_spp(left, RENDER, PRESETS[expected])
    assert "no trade curves" in plan.rule


def test_auto_with_curves_picks_the_lowest_predicted_error() -> None:
    # error = a / spp per model; at a 9 s budget: high 450 spp, balanced 650, fast 800
    curves = {"high": ([1, 1000], [0.02, 0.00002]), "balanced": ([1, 1000], [0.03, 0.00003]),
              "fast": ([1, 1000], [0.1, 0.0001])}
    plan = plan_budget(9.0, 0.0, RENDER, PRESETS, curves)
    errors = {o["model"]: o["predicted_error"] for o in plan.options}
    assert errors["high"] == pytest.approx(0.02 / 450) and errors["balanced"] == pytest.approx(0.03 / 650)
    assert plan.model == "high" and "trade curves" in plan.rule
    # a tight budget: high fits only a few spp and loses to balanced
    tight = plan_budget(4.6, 0.0, RENDER, PRESETS, curves)
    assert tight.model == "balanced" and tight.spp == fit_spp(4.6, RENDER, 2.0) == 210


def test_budget_too_small_is_a_clear_error() -> None:
    with pytest.raises(BudgetError, match=r"time budget 1 s is too small: 0.80 s went to starting"):
        plan_budget(1.0, 0.8, RENDER, PRESETS)


def test_loading_a_model_counts_against_the_budget(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(budget, "quality_order", lambda: ("high", "balanced", "fast"))
    plan = plan_budget(20.0, 0.0, RENDER, PRESETS, load_s={"high": 4.0, "balanced": 1.0, "fast": 0.5})
    assert plan.model == "balanced"  # high's 4 + 4 s is over a third of 20 s, balanced's 3 s is not
    assert plan.predicted_load_s == 1.0 and plan.spp == fit_spp(20.0, RENDER, 3.0)
    assert plan.predicted_s == pytest.approx(1.0 + 0.5 + 0.01 * plan.spp + 2.0)


SLOW_SCENE = SimpleNamespace(sensors=lambda: [SimpleNamespace(film=lambda: SimpleNamespace(crop_size=lambda: (64, 64)))])
RECORDED = {"high": EntryCost(1.0, 0.0, 0.0, 4.0 / 64**2, 1e3, 8, 8, 1, False, ()),  # 1 s to load, 4 s a 64x64
            "fast": EntryCost(0.2, 0.0, 0.0, 0.5 / 64**2, 1e3, 8, 8, 1, False, ())}


def slow_host_plan(monkeypatch: pytest.MonkeyPatch, slowdown: float, budget_s: float = 40.0) -> BudgetPlan:
    """plan_run on a host whose calibrations take ``slowdown`` times the recorded 1 ms; the render
    probe measures 0.05 s a sample under the same load."""
    monkeypatch.setattr(budget, "quality_order", lambda: ("high", "fast"))
    monkeypatch.setattr(budget, "calibrate", lambda workload: 0.001 * slowdown)  # both calibrations
    monkeypatch.setattr(budget, "probe_render", lambda *a, **k: RenderCost(0.0, 0.05 * slowdown))
    return plan_run(budget_s, time.perf_counter(), SLOW_SCENE, 0, (), RECORDED, None, recorded=(0.001, 0.001))


def test_a_slower_host_gets_a_plan_that_fits_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """The recorded costs are scaled by the calibrations' slowdowns: a host at a quarter of the
    recorded speed (busy) gets fewer samples and the cheaper model, predicted within the budget."""
    idle = slow_host_plan(monkeypatch, 1.0)
    busy = slow_host_plan(monkeypatch, 4.0)
    assert idle.model == "high" and busy.model == "fast"
    assert busy.spp < idle.spp
    assert busy.speed["slowdown"] == busy.speed["loading_slowdown"] == pytest.approx(4.0)
    assert busy.speed["calibration_s"] == busy.speed["loading_s"] == 0.004 and busy.speed["recorded_s"] == 0.001
    assert busy.predicted_load_s == pytest.approx(4 * 0.2) and busy.predicted_denoise_s == pytest.approx(4 * 0.5)
    assert busy.predicted_s <= 40.0 < busy.predicted_s + busy.render_cost["per_spp_s"]
    assert busy.costs == "recorded x the measured slowdowns" and {o["costs"] for o in busy.options} == {"recorded"}
    with pytest.raises(BudgetError, match=r"the host runs the networks at 0.05x and loads them at 0.05x the speed"):
        slow_host_plan(monkeypatch, 20.0, budget_s=10.0)


def test_a_budget_the_model_alone_overruns_fails_before_the_render_probe(monkeypatch: pytest.MonkeyPatch) -> None:
    # at 4x slower fast needs 0.8 s to load and 2 s to denoise: 2.5 s cannot hold it, whatever the render costs
    def no_probe(*args: Any, **kwargs: Any) -> RenderCost:
        raise AssertionError("the render was probed")

    monkeypatch.setattr(budget, "probe_render", no_probe)
    monkeypatch.setattr(budget, "calibrate", lambda workload: 0.004)
    with pytest.raises(BudgetError, match=r"time budget 2.5 s is too small: .* need 2.80 s more .*0.25x"):
        plan_run(2.5, time.perf_counter(), SLOW_SCENE, 0, (), RECORDED, None, recorded=(0.001, 0.001))


def chosen(spp: int = 100, load_s: float = 1.0) -> BudgetPlan:
    """A plan of ``high`` at ``spp`` (render 0.01 s a sample, 4 s to denoise) with ``fast`` beside it."""
    options = [{"model": "high", "spp": spp, "denoise_s": 4.0, "load_s": load_s},
               {"model": "fast", "spp": spp, "denoise_s": 0.5, "load_s": 0.2}]
    return BudgetPlan(20.0, "high", spp, 5.0, 0.01 * spp, 4.0, "rule", options,
                      {"fixed_s": 0.0, "per_spp_s": 0.01, "probe_s": 0.0}, predicted_load_s=load_s)


def test_refit_spp_to_the_time_left_once_loaded() -> None:
    plan = chosen()
    refit_spp(plan, 10.0)  # 10 s left: 4 s denoising, 6 s of samples
    assert plan.spp == 600 and plan.predicted_render_s == pytest.approx(6.0)
    assert plan.notes == ["high loaded at 10.0 s (1.0 s predicted for it), 10.0 s left: 100 -> 600 spp"]
    late = chosen()
    refit_spp(late, 17.0)
    assert late.spp == 1 and "not even 1 spp fits: the budget will be exceeded" in late.notes[0]
    same = chosen(spp=600)
    refit_spp(same, 10.0)
    assert same.spp == 600 and not same.notes


def test_after_render_gives_way_to_a_model_that_ends_sooner() -> None:
    plan = chosen()
    assert after_render(plan, 10.0, 1.0) is None and not plan.notes  # 4 s of 10 left
    assert after_render(plan, 17.0, 1.0) == "fast"  # 3 s left: high needs 4, fast 0.2 + 0.5
    assert plan.model == "fast" and "denoising with fast" in plan.notes[0]
    slower = chosen()
    assert after_render(slower, 13.0, 2.0) == "fast"  # the render took 2x its prediction: high needs 8 s of 7
    assert "2.00x its prediction" in slower.notes[0]
    hopeless = chosen()
    hopeless.options[1].update(denoise_s=9.0)
    assert after_render(hopeless, 19.0, 1.0) is None and hopeless.model == "high"
    assert "no other model ends sooner: the budget will be exceeded" in hopeless.notes[0]


def test_load_curves(tmp_path: Path) -> None:
    path = tmp_path / "tradeoff.json"
    path.write_text(json.dumps({"points": [
        {"denoiser": "none", "spp": 1, "relmse": 0.5, "psnr": 20.0},
        {"denoiser": "fast", "spp": 1, "relmse": 0.1, "psnr": 30.0},
        {"denoiser": "fast", "spp": 4, "relmse": 0.05, "psnr": None}]}))
    assert load_curves(path) == {"none": ([1.0], [0.5]), "fast": ([1.0, 4.0], [0.1, 0.05])}
    assert load_curves(path, "psnr")["fast"] == ([1.0, 4.0], [pytest.approx(1e-3), 0.0])
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    with pytest.raises(BudgetError, match="bad.json: not a usable tradeoff.json"):
        load_curves(bad)


def test_probe_render_fits_fixed_and_per_sample_cost(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[int] = []

    def fake_render(scene: Any, spp: int, seed: int, aovs: Any) -> SimpleNamespace:
        calls.append(spp)
        return SimpleNamespace(seconds=0.1 + 0.02 * spp)

    monkeypatch.setattr(budget, "render_loaded", fake_render)
    cost = probe_render(None, 0, (), budget_s=10.0)
    assert cost.fixed_s == pytest.approx(0.1) and cost.per_spp_s == pytest.approx(0.02)
    assert calls[:3] == [1, 3, 1] and 4 <= calls[3] <= 256


@pytest.mark.parametrize("member_ranges, dearest", [([(0, 0)], 1), ([(9, 0), (0, 8), (0, 16), (17, 0)], 9)])
def test_denoise_seconds_scales_by_tile_windows(member_ranges: list[tuple[int, int]], dearest: int) -> None:
    # The cost per call and per window pixel of the dearest spp range: a single model is timed at
    # 1 spp; the default's shape at 1, 9 and 17 spp, where (as since its flat low-spp member went to
    # bfloat16) 9-16 spp cost the most.
    asked: set[int] = set()

    class FakeDenoiser:
        margin = 8
        members = [SimpleNamespace(min_spp=lo, max_spp=hi) for lo, hi in member_ranges]

        def cores(self, height: int, width: int) -> tuple[int, int]:
            return 64, 64

        def denoise_array(self, img: np.ndarray, spp: int | None = None) -> SimpleNamespace:
            asked.add(spp)
            h, w = img.shape[:2]
            scale = 2.0 if spp == dearest else 1.0
            return SimpleNamespace(seconds=scale * (0.01 + 1e-6 * window_pixels(h, w, 64, 8)))  # one tile

    tiles = len(list(plan_tiles(300, 200, 64, 8)))
    assert tiles > 1
    assert denoise_seconds(FakeDenoiser(), 300, 200) == pytest.approx(
        2.0 * (0.01 * tiles + 1e-6 * window_pixels(300, 200, 64, 8)))
    assert asked == ({1} if len(member_ranges) == 1 else {1, 9, 17})
    assert window_pixels(300, 200, 64, 8) > 300 * 200  # overlapping windows cost extra


def test_auto_candidates_are_the_registry_entries_best_first() -> None:
    """``--model auto`` under a budget chooses among the registry's entries, best measured quality
    first (entries without figures by the manifest's order, the quickest last); any other model
    alone. Without recorded costs each is loaded; with them none is."""
    order = budget.quality_order()
    settings = RenderSettings(scene="unused.xml", max_memory_mb=64)
    assert set(order) == set(registry().entries) and order[-1] == "fast"
    found = budget_candidates("auto", settings)
    assert list(found) == list(order) and all(found[name].name == name for name in order)
    assert list(budget_candidates("balanced", settings)) == ["balanced"]
    recorded = budget_candidates("auto", settings, read_costs(COSTS))
    assert list(recorded) == list(order) and all(isinstance(c, EntryCost) for c in recorded.values())
    assert isinstance(budget_candidates(None, settings, read_costs(COSTS))[registry().default], EntryCost)


@pytest.mark.parametrize("args", [["--time-budget", "5", "--spp", "4"],
                                  ["--time-budget", "0"], ["--curves", "x.json"]])
def test_cli_budget_argument_errors_exit_2(args: list[str], capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        main([str(DEMO), *args])
    assert exc.value.code == 2 and "Traceback" not in capsys.readouterr().err


def test_cli_time_budget_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture,
                                    monkeypatch: pytest.MonkeyPatch) -> None:
    # A generous budget with spp capped at 8: the wiring is tested, not this machine's load.
    monkeypatch.setattr(budget, "MAX_SPP", 8)
    ckpt = write_tiny_checkpoint(tmp_path / "tiny.ckpt")
    out = tmp_path / "run"
    assert main([str(DEMO), "--res", "32", "32", "--model", str(ckpt), "--time-budget", "120",
                 "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    plan = metrics["budget"]
    assert plan["model"] == "tiny" and plan["spp"] == metrics["spp"] == 8
    assert 0 < plan["spent_s"] < plan["predicted_s"] <= 120.0
    assert plan["actual_s"] > 0 and plan["render_cost"]["per_spp_s"] > 0
    assert plan["speed"]["calibration_s"] > 0 and plan["costs"] == "timed now"
    recorded, speed = read_costs(COSTS), plan["speed"]
    assert (speed["recorded_s"], speed["recorded_loading_s"]) == (recorded.calibration_s, recorded.loading_s)
    assert speed["slowdown"] == pytest.approx(speed["calibration_s"] / speed["recorded_s"])
    assert speed["loading_slowdown"] == pytest.approx(speed["loading_s"] / speed["recorded_loading_s"])
    out = capsys.readouterr().out
    assert "time budget 120 s: chose tiny at 8 spp" in out
    assert "the speed the model costs were recorded at (calibrations" in out and "of wall time (" in out


def test_cli_time_budget_loads_only_the_chosen_model(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A candidate with recorded costs is loaded once chosen, its loading timed, and the spp
    fitted to the time then left; a host 3x slower than recorded is in the record."""
    ckpt = write_tiny_checkpoint(tmp_path / "tiny.ckpt")
    loaded: list[str] = []

    def make(name: str, settings: RenderSettings) -> Any:
        loaded.append(name)
        return real_make(str(ckpt), settings)

    from pipeline import run as run_module
    real_make = run_module.make_denoiser
    cost = EntryCost(0.5, 0.0, 0.0, 1e-6, 1e3, 8, 8, 1, False, ())
    monkeypatch.setattr(run_module, "make_denoiser", make)
    monkeypatch.setattr(run_module, "budget_candidates", lambda *a: {"mine": cost})
    monkeypatch.setattr(run_module, "read_costs", lambda: SimpleNamespace(calibration_s=0.001, loading_s=0.001))
    monkeypatch.setattr(budget, "calibrate", lambda workload: 0.003)
    monkeypatch.setattr(budget, "MAX_SPP", 8)
    out = tmp_path / "run"
    assert main([str(DEMO), "--res", "32", "32", "--model", "mine", "--time-budget", "120", "--out", str(out),
                 "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    plan = metrics["budget"]
    assert loaded == ["mine"] and metrics["timings"]["model_load_s"] > 0
    assert plan["speed"]["slowdown"] == pytest.approx(3.0) and plan["predicted_load_s"] == pytest.approx(1.5)
    assert plan["costs"] == "recorded x the measured slowdowns" and plan["spp"] == metrics["spp"] == 8
