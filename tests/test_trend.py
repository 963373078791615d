"""benchmarks/trend.py: the slope of validation PSNR against log CPU time, and its projection to OIDN."""
from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from benchmarks.trend import fit, main, trend
from training.run_log import RunLog, validation_curve


def _log(path: Path, minutes: list[float], psnr: list[float], oidn: float = 40.0) -> Path:
    log = RunLog(path)
    for i, (m, db) in enumerate(zip(minutes, psnr)):
        step = 100 * (i + 1)
        log.append({"type": "train", "step": step, "loss": 0.01, "cpu_s": 60.0 * m})
        log.append({"type": "val", "step": step, "psnr": db, "per_spp": {
            "4": {"psnr": {"ours": db - 3, "noisy": 20.0, "oidn": oidn - 3}},
            "128": {"psnr": {"ours": db + 3, "noisy": 30.0, "oidn": None}}}})
    log.append({"type": "val", "step": 1, "psnr": 1.0, "per_spp": {}})  # no CPU time at step 1: left out
    return path


def test_fit_recovers_an_exact_log_linear_curve_and_where_it_reaches_the_target() -> None:
    points = [(m, 30.0 + 0.5 * math.log2(m)) for m in (8, 16, 32, 64)]
    f = fit(points, target=33.0)
    assert f["db_per_doubling"] == pytest.approx(0.5) and f["scatter_db"] == pytest.approx(0, abs=1e-9)
    assert f["end_db"] == pytest.approx(33.0 - 0.0) and f["points"] == 4 and f["minutes"] == [8, 64]
    assert f["hours_to_target"] == pytest.approx(64 / 60)  # 30 + 0.5 log2(m) = 33 at m = 64
    assert fit(points, target=34.0)["hours_to_target"] == pytest.approx(256 / 60)


def test_no_fit_from_too_few_points_and_no_projection_when_flat_or_falling() -> None:
    assert fit([(1.0, 30.0), (2.0, 31.0)], target=35.0) is None
    assert fit([(4.0, 30.0)] * 3, target=35.0) is None  # one CPU time: no slope
    falling = fit([(m, 35.0 - math.log2(m)) for m in (2, 4, 8)], target=40.0)
    assert falling["db_per_doubling"] == pytest.approx(-1.0) and falling["hours_to_target"] is None
    assert fit([(m, 30.0 + math.log2(m)) for m in (2, 4, 8)], target=None)["hours_to_target"] is None


def test_trend_fits_the_later_part_of_the_run_overall_and_per_spp(tmp_path: Path) -> None:
    minutes = [1, 2, 4, 8, 16, 32]
    curve = validation_curve(RunLog(_log(tmp_path / "log.jsonl", minutes, [30 + math.log2(m) for m in minutes])).read())
    result = trend(curve, [4, 16, 128], start=0.2)
    assert result["validations"] == 6 and result["last_cpu_min"] == 32
    assert result["overall"]["points"] == 3  # 8, 16, 32 minutes are >= 0.2 x 32
    assert result["overall"]["db_per_doubling"] == pytest.approx(1.0)
    assert result["overall"]["target_db"] is None  # OIDN's 128-spp figure is missing: no mean to aim at
    assert set(result["per_spp"]) == {"4", "128"}  # 16 spp was not validated
    assert result["per_spp"]["4"]["hours_to_target"] == pytest.approx(2 ** 10 / 60)
    assert result["per_spp"]["128"]["target_db"] is None
    shifted = trend(curve, [4], start=0.0, offset_min=32.0)
    assert shifted["last_cpu_min"] == 64 and shifted["overall"]["minutes"] == [33, 64]


def test_the_command_writes_json_and_table_and_fails_in_one_line(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    run = tmp_path / "run"
    run.mkdir()
    _log(run / "log.jsonl", [1, 2, 4, 8], [30, 31, 32, 33])
    assert main([str(run), "--from", "0", "--out", str(tmp_path / "r")]) == 0
    result = json.loads((tmp_path / "r" / "trend.json").read_text())
    assert result["runs"][str(run)]["overall"]["db_per_doubling"] == pytest.approx(1.0)
    table = (tmp_path / "r" / "trend.md").read_text().splitlines()
    assert table[2].startswith("| run | spp |") and any("| 4 | 4 | 1-8 |" in line for line in table)
    capsys.readouterr()
    assert main([str(tmp_path / "missing")]) == 1
    with pytest.raises(SystemExit) as usage:
        main([str(run), "--from", "1.5"])
    assert usage.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "missing" in err[0] and "--from must be in [0, 1)" in err[1]
