"""The host-speed calibration and the recorded model costs: fakes for the arithmetic, a tiny
checkpoint for the tile plan, and the shipped file against the registry."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from denoise.tiling import plan_tiles
from model.architectures import alignment
from model.registry import registry
from pipeline.budget import window_pixels
from pipeline.budget_costs import (COSTS, SETTINGS, CostsError, EntryCost, RecordedCosts, Speed, calibrate,
                                   calibration_workload, entry_signature, loading_workload, measure_speed,
                                   read_costs)
from pipeline.evaluation import RenderSettings, make_denoiser
from tests.test_denoiser import write_tiny_checkpoint

COST = EntryCost(load_s=2.0, first_s=0.5, per_call_s=0.01, per_px_s=1e-6, bytes_per_pixel=100.0, core_margin=8,
                 margin=8, alignment=1, needs_aovs=False, signature=())


def test_calibrate_is_the_mean_call_after_a_warm_up() -> None:
    now = [0.0]
    calls = []

    def workload():
        def call() -> None:
            calls.append(now[0])
            now[0] += 0.01 if len(calls) > 1 else 1.0  # the warm-up is slow and not counted
        return call

    assert calibrate(min_s=0.1, clock=lambda: now[0], workload=workload) == pytest.approx(0.01)
    assert len(calls) == 1 + 10


def test_calibrate_times_at_least_two_calls() -> None:
    now = [0.0]

    def workload():
        def call() -> None:
            now[0] += 1.0
        return call

    assert calibrate(min_s=0.1, clock=lambda: now[0], workload=workload) == pytest.approx(1.0)


def test_calibration_workloads_run() -> None:
    assert 0 < calibrate(min_s=0.0) < 5.0
    assert 0 < calibrate(min_s=0.0, workload=loading_workload) < 5.0


def test_speed_slowdowns() -> None:
    speed = Speed(0.02, 0.005, 0.03, 0.01)
    assert speed.slowdown == pytest.approx(4.0) and speed.loading_slowdown == pytest.approx(3.0)
    assert speed.to_dict() == {"calibration_s": 0.02, "recorded_s": 0.005, "slowdown": 4.0, "loading_s": 0.03,
                               "recorded_loading_s": 0.01, "loading_slowdown": pytest.approx(3.0)}
    alone = Speed(0.02, None, 0.03, None)
    assert alone.slowdown == alone.loading_slowdown == 1.0
    assert alone.to_dict()["slowdown"] is None and alone.to_dict()["loading_slowdown"] is None


def test_measure_speed_times_both_workloads() -> None:
    seconds = {calibration_workload: 0.02, loading_workload: 0.03}
    speed = measure_speed((0.01, 0.01), lambda workload: seconds[workload])
    assert speed == Speed(0.02, 0.01, 0.03, 0.01)
    assert measure_speed(None, lambda workload: seconds[workload]).recorded_s is None


def test_entry_cost_scales_with_the_slowdowns() -> None:
    tiles, pixels = COST.tiles(100, 60, 1024)
    assert (tiles, pixels) == (1, 6000)
    assert COST.denoise_s(100, 60, 1024) == pytest.approx(0.5 + 0.01 + 0.006)
    # the first call's extra goes by the loading slowdown (2), the tiles by the networks' (3)
    assert COST.denoise_s(100, 60, 1024, Speed(0.03, 0.01, 0.02, 0.01)) == pytest.approx(2 * 0.5 + 3 * 0.016)


def test_entry_cost_plans_the_tiles_the_loaded_model_plans(tmp_path: Path) -> None:
    den = make_denoiser(str(write_tiny_checkpoint(tmp_path / "tiny.ckpt")),
                        RenderSettings(scene="unused.xml", max_memory_mb=33))  # 1 MiB over the fixed cost
    first = den.members[0]
    cost = EntryCost(0, 0, 0, 0, den.bytes_per_pixel(), first.margin, den.margin, alignment(first.config), False, ())
    core = den.cores(300, 200)
    expected = list(plan_tiles(300, 200, core, den.margin))
    assert len(expected) > 1
    assert cost.tiles(300, 200, 33) == (len(expected), window_pixels(300, 200, core, den.margin))


def test_read_costs_missing_and_bad(tmp_path: Path) -> None:
    assert read_costs(tmp_path / "none.json") is None
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"calibration_s": 0.001}))
    with pytest.raises(CostsError, match="bad.json: not a usable budget costs file"):
        read_costs(bad)


def test_costs_apply_to_the_recorded_settings_and_members() -> None:
    costs = RecordedCosts(0.001, 0.001, SETTINGS, True, {"fast": COST, "high": EntryCost(
        *[1.0] * 5, 8, 8, 1, False, entry_signature("high"))})
    assert costs.usable("cpu", "auto", 1, True)
    assert not costs.usable("cpu", "auto", 1, False)  # another CPU: bfloat16 runs otherwise
    assert not costs.usable("cpu", "float32", 1, True) and not costs.usable("cpu", "auto", 2, True)
    assert costs.entry("high") is not None
    assert costs.entry("fast") is None  # recorded for other members: timed instead
    assert costs.entry("balanced") is None


def test_shipped_costs_cover_every_registry_entry() -> None:
    """Budget mode loads only the model it chooses when the costs of every entry are recorded for
    its current checkpoints; after a change to the registry, `python -m benchmarks.budget_costs`."""
    costs = read_costs(COSTS)
    assert costs is not None and dict(costs.settings) == SETTINGS and costs.calibration_s > 0 < costs.loading_s
    for name in registry().entries:
        cost = costs.entry(name)
        assert cost is not None, f"{name}: costs not recorded for its checkpoints"
        assert cost.load_s > 0 and cost.per_px_s > 0 and cost.first_s >= 0 and cost.per_call_s >= 0
