"""benchmarks/aov_cost.py: the three ways of rendering, timed, with their agreement recorded."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks import aov_cost
from tests.test_evaluation import eval_folder


def test_aov_cost_times_the_plain_render_the_pass_and_the_wrapped_render(tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture) -> None:
    """On the demo scene (a path tracer): the wrapped render's radiance is the plain render's and
    the pass's AOVs are the wrapped render's, bit for bit; the pass adds to the plain render's time."""
    eval_folder(tmp_path)
    assert aov_cost.main(["--eval-dir", str(tmp_path / "eval"), "--scenes", "demo", "--spp", "2,4",
                          "--res", "16", "--repeat", "2", "--out", str(tmp_path / "out")]) == 0
    result = json.loads((tmp_path / "out" / "aov_cost.json").read_text())
    assert result["spp"] == [2, 4] and result["resolution"] == [16, 16]
    assert result["command"].startswith("python -m benchmarks.aov_cost") and result["machine"]["cores"] >= 1
    for spp in ("2", "4"):
        e = result["scenes"]["demo"][spp]
        assert e["rgb_identical"] and e["rgb_max_diff"] == 0 and e["aov_max_diff"] == 0
        assert all(len(e["times"][way]) == 2 for way in aov_cost.WAYS)
        assert e["pass_ratio"] == pytest.approx((e["seconds"]["plain"] + e["seconds"]["pass"]) / e["seconds"]["plain"])
        assert e["pass_ratio"] > 1 and e["wrapped_ratio"] > 0
        assert result["summary"][spp]["pass_ratio"]["geomean"] == pytest.approx(e["pass_ratio"])
    table = (tmp_path / "out" / "aov_cost.md").read_text()
    assert "| demo | 4 |" in table and table in capsys.readouterr().out
