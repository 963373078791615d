"""The scoreboard page of ``benchmarks/evaluate.py``: one viewer set per scene, flipped with n / p
in a real browser, and the tables of the run (synthetic figures, tiny images)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks import evaluate
from tests.cdp import Browser
from tests.test_viewer import chromium  # noqa: F401  (fixture)


def fake_run(rng: np.random.Generator, scenes: list[str], spps: list[int]) -> tuple[dict, dict]:
    scores = lambda: {"psnr": float(rng.uniform(20, 40)), "relmse": float(rng.uniform(0, 1)),  # noqa: E731
                      "flip": float(rng.uniform(0, 1))}
    rows = {}
    for i, name in enumerate(scenes):
        rows[name] = {"ceiling_db": 35.0 if i == 0 else 50.0, "resolution": [16, 12]}
        for spp in spps:
            ours = scores()
            bare = scores()
            rows[name][str(spp)] = {"render_s": 0.1, "aov_render_s": 0.01, "ours_s": 0.2, "oidn_s": 0.05,
                                    "oidn_aux_s": 0.06, "noisy": scores(), "ours": ours, "ours_bare": bare,
                                    "oidn": scores(), "oidn_aux": scores(),
                                    "models": {"fast": {**ours, "s": 0.2}}, "bare": {"fast": bare}}
    result = {"model": {"path": "model/weights/fast.ckpt"}, "models": {"fast": {}}, "spp": spps, "seed": 7,
              "ceiling_db": 40.0, "summary": evaluate.summarize(rows, spps, 40.0), "scenes": rows,
              "wall_s": 12.0, "machine": {"cores": 2}, "path": "halves"}
    images = {name: {k: rng.random((12, 16, 3)).astype(np.float32)
                     for k in ("noisy", "ours", "ours_bare", "oidn", "oidn_aux", "reference")} for name in scenes}
    return result, images


def test_scoreboard_page_sets_and_tables(rng: np.random.Generator) -> None:
    result, images = fake_run(rng, ["alpha", "beta", "gamma"], [4, 16])
    page = evaluate.scoreboard_page(result, images, 4)
    assert [s.name for s in page.sets] == ["alpha", "beta", "gamma"]
    assert [r.label for r in page.sets[0].rows] == ["noisy", "ours", "bare", "OIDN colour-only",
                                                    "OIDN + albedo + normal", "reference"]
    assert all(r.flip for r in page.sets[0].rows[:5]) and page.sets[0].reference == page.sets[0].rows[5].image
    text = page.html()
    assert "Scored means (2 scenes" in text and "alpha*" in text and text.count("<tr>") > 3 * 2
    assert "OIDN + albedo + normal PSNR" in text and "AOV pass s" in text
    table = evaluate.markdown(result["scenes"], result["summary"], [4, 16], 40.0, "fast")
    assert "| OIDN colour-only PSNR | OIDN + albedo + normal PSNR |" in table


def test_scoreboard_flips_scenes_in_a_browser(chromium: str, rng: np.random.Generator,  # noqa: F811
                                              tmp_path: Path) -> None:
    result, images = fake_run(rng, ["alpha", "beta"], [4])
    path = evaluate.scoreboard_page(result, images, 4).write(tmp_path / "evaluate.html")
    with Browser(chromium, 900, 700) as browser:
        browser.open(path)
        browser.wait_for("Number(document.body.dataset.draws) >= 1 && !document.body.dataset.busy")
        for key, shown in (("2", "0/ours/image"), ("n", "1/ours/image"), ("f", "1/ours/flip"),
                           ("p", "0/ours/flip")):
            draws = int(browser.eval("document.body.dataset.draws"))
            browser.press(key)
            browser.wait_for(f"Number(document.body.dataset.draws) > {draws} && !document.body.dataset.busy")
            assert browser.eval("document.body.dataset.shown") == shown
        assert browser.eval("document.querySelector('.set-select').value") == "0"
