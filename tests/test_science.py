"""benchmarks/science.py: validation at equal CPU minutes."""
from __future__ import annotations

import pytest

from benchmarks.science import _at, table


def _point(minutes: float, psnr: float) -> dict:
    return {"step": int(minutes * 100), "cpu_min": minutes, "psnr": psnr, "per_spp": {"4": psnr - 1}}


def test_at_averages_the_last_quarter_and_counts_a_final_validation_just_past_the_budget() -> None:
    curve = [_point(10.0, 20.0), _point(14.1, 29.0), _point(18.8, 33.0), _point(20.008, 31.0), _point(21.0, 99.0)]
    at = _at(curve, 20.0)
    assert at["psnr"] == pytest.approx(32.0) and at["validations"] == 2 and at["step"] == 2000
    assert at["per_spp"]["4"] == pytest.approx(31.0)
    assert _at(curve, 5.0) is None


def _run(budget: float, points: list[tuple[float, float]]) -> dict:
    curve = [{**_point(m, p), "per_spp": {s: p for s in ("4", "16", "128")}, "noisy": {}, "oidn": {}}
             for m, p in points]
    return {"config": {"model": {"arch": "dense_unet"}}, "curve": curve, "budget_min": budget}


def test_a_run_continued_past_the_common_budget_gets_its_own_table() -> None:
    runs = {"short": _run(20.0, [(19.0, 30.0)]),
            "long": _run(60.0, [(19.5, 31.0), (39.0, 32.0), (59.9, 33.5)])}
    lines = table({"runs": runs, "date": "today"})
    assert lines[4].startswith("| short |") and lines[5].startswith("| long |")  # both at 5/10/20 min
    assert "| 31.00 |" in lines[5]
    at = lines.index(next(line for line in lines if line.startswith("Runs continued to 60")))
    assert lines[at + 2].startswith("| run | steps | 20 min | 40 min | 60 min |")
    assert lines[at + 4] == "| long | 5990 | 31.00 | 32.00 | 33.50 | 33.50 | 33.50 | 33.50 |"
    assert not any(line.startswith("| short | ") for line in lines[at:])
    assert not any(line.startswith("Runs continued") for line in table({"runs": {"short": runs["short"]},
                                                                       "date": "today"}))
