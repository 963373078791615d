"""The time-budget planner on fake cost models, its probes on fakes, and the CLI end to end."""
from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from denoise.tiling import plan_tiles
from model.registry import registry
from pipeline import budget
from pipeline.evaluation import RenderSettings
from pipeline.budget import (BudgetError, RenderCost, budget_candidates, denoise_seconds, fit_spp,
                             load_curves, plan_budget, probe_render, window_pixels)
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
    with pytest.raises(BudgetError, match=r"time budget 1 s is too small: 0.80 s went to loading"):
        plan_budget(1.0, 0.8, RENDER, PRESETS)


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
    first (entries without figures by the manifest's order, the quickest last); any other model alone."""
    order = budget.quality_order()
    assert set(order) == set(registry().entries) and order[-1] == "fast"
    found = budget_candidates("auto", RenderSettings(scene="unused.xml", max_memory_mb=64))
    assert list(found) == list(order) and all(found[name].name == name for name in order)
    assert list(budget_candidates("balanced", RenderSettings(scene="unused.xml", max_memory_mb=64))) == ["balanced"]


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
    assert "time budget 120 s: chose tiny at 8 spp" in capsys.readouterr().out
