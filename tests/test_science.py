"""benchmarks/science.py: validation at equal CPU minutes."""
from __future__ import annotations

import pytest

from benchmarks.science import _at


def _point(minutes: float, psnr: float) -> dict:
    return {"step": int(minutes * 100), "cpu_min": minutes, "psnr": psnr, "per_spp": {"4": psnr - 1}}


def test_at_averages_the_last_quarter_and_counts_a_final_validation_just_past_the_budget() -> None:
    curve = [_point(10.0, 20.0), _point(14.1, 29.0), _point(18.8, 33.0), _point(20.008, 31.0), _point(21.0, 99.0)]
    at = _at(curve, 20.0)
    assert at["psnr"] == pytest.approx(32.0) and at["validations"] == 2 and at["step"] == 2000
    assert at["per_spp"]["4"] == pytest.approx(31.0)
    assert _at(curve, 5.0) is None
