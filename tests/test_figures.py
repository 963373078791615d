"""The README's quality-time figure: its points come from the result files as they are."""
from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.figures import OIDN_AUX_LABEL, plot_tradeoff, tradeoff_points
from model.registry import CARD_SPP, registry


def _results(aux: bool) -> tuple[dict, dict]:
    names = list(registry().entries)
    scored = {}
    for i, s in enumerate(CARD_SPP):
        scored[str(s)] = {"oidn_psnr": 30.0 + i, "models": {n: {"psnr": 29.0 + i + 0.1 * k} for k, n in enumerate(names)}}
        if aux:
            scored[str(s)]["oidn_aux_psnr"] = 31.0 + i
    ratios = {n: {str(s): 0.5 + k for s in CARD_SPP} for k, n in enumerate(names)}
    return {"summary": {"scored": scored}}, {"ratios": {"1280x720": ratios}}


def test_oidn_with_albedo_and_normals_is_a_quality_line_beside_the_points(tmp_path: Path) -> None:
    """Every entry and OIDN colour-only are points (PSNR, time over OIDN's); OIDN + albedo + normal,
    whose time the inference benchmark does not measure, carries its PSNR alone, and the plot draws it."""
    points = tradeoff_points(*_results(aux=True))
    first = str(CARD_SPP[0])
    assert points["OIDN"] == {"psnr": {str(s): 30.0 + i for i, s in enumerate(CARD_SPP)},
                              "time_ratio": {str(s): 1.0 for s in CARD_SPP}}
    assert points[OIDN_AUX_LABEL] == {"psnr": {str(s): 31.0 + i for i, s in enumerate(CARD_SPP)}}
    name = next(iter(registry().entries))
    assert points[name]["psnr"][first] == pytest.approx(29.0) and points[name]["time_ratio"][first] == 0.5
    out = tmp_path / "quality_time.png"
    plot_tradeoff(points, out)
    assert out.stat().st_size > 1000


def test_a_scoreboard_without_oidn_aux_gives_no_line() -> None:
    assert OIDN_AUX_LABEL not in tradeoff_points(*_results(aux=False))
