"""`tradeoff` end to end on a 32-px scene with 2 spp levels; its analysis on synthetic points."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest

from imaging.errors import DenoiserError
from denoise import denoiser
from pipeline.cli import tradeoff_main
from pipeline.evaluation import RenderSettings
from denoise.oidn import oidn_available
from pipeline import tradeoff
from pipeline.tradeoff import Point, TradeoffConfig, analyse, model_labels
from pipeline.tradeoff_report import recommendation, recommendation_line
from tests.test_denoiser import write_tiny_checkpoint

DEMO = Path(__file__).resolve().parents[1] / "scenes" / "examples" / "demo.xml"


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory: pytest.TempPathFactory) -> list[Path]:
    root = tmp_path_factory.mktemp("ckpts")
    (root / "other").mkdir()
    return [write_tiny_checkpoint(root / "tiny.ckpt"),
            write_tiny_checkpoint(root / "other" / "tiny.ckpt", seed=1)]


def test_tradeoff_end_to_end(tmp_path: Path, ckpts: list[Path], capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "trade"
    oidn = ["--compare", "oidn"] if oidn_available() else []
    assert tradeoff_main([str(DEMO), "--res", "32", "32", "--spp", "2,8", "--reference-spp", "32",
                          "--repeat", "2", "--models", ",".join(map(str, ckpts)), *oidn,
                          "--out", str(out)]) == 0
    names = {"none", "tiny", "tiny-2"} | ({"oidn", "oidn_aux"} if oidn else set())
    result = json.loads((out / "tradeoff.json").read_text())
    assert result["resolution"] == [32, 32] and result["reference"]["spp"] == 32
    assert {p["denoiser"] for p in result["points"]} == names and len(result["points"]) == 2 * len(names)
    for p in result["points"]:
        assert len(p["render_times"]) == 2 and p["render_s"] > 0
        assert p["denoise_s"] == 0 if p["denoiser"] == "none" else p["denoise_s"] > 0
        assert p["total_s"] == pytest.approx(p["render_s"] + p["denoise_s"])
        for key in ("psnr", "relmse", "flip"):
            assert p[key] is not None and math.isfinite(p[key]), key
    for metric in ("psnr", "relmse", "flip"):
        assert result["pareto"][metric], metric
    assert len(result["equal_quality"]) == 3 * 2 * (len(names) - 1)
    by = {(p["denoiser"], p["spp"]): p for p in result["points"]}
    for spp in (2, 8) if oidn else ():  # the AOV pass counts in OIDN + albedo + normal's render time
        assert by[("oidn_aux", spp)]["render_s"] > by[("oidn", spp)]["render_s"] == by[("none", spp)]["render_s"]
        assert by[("oidn_aux", spp)]["psnr"] != by[("oidn", spp)]["psnr"]
    rows = list(csv.DictReader((out / "tradeoff.csv").open()))
    assert len(rows) == len(result["points"]) and any(r["pareto"] == "1" for r in rows)
    png = (out / "tradeoff.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    assert json.loads((out / "config.json").read_text())["spp"] == [2, 8]
    report = (out / "report.html").read_text()  # the plot embedded, the tables, nothing fetched
    assert "data:image/png;base64," in report and "Equal-quality saving" in report and "tiny-2" in report
    if oidn:
        assert "OIDN colour-only" in report and "OIDN + albedo + normal" in report
    assert report.count("<tr>") >= 1 + len(result["points"]) and "https://" not in report
    printed = capsys.readouterr().out
    assert "equal-quality saving" in printed and "tiny-2" in printed
    assert "recommended: " in printed and "Recommended" in report
    assert f"report: {out / 'report.html'}" in printed


def test_an_earlier_run_is_refused_before_rendering_unless_overwrite(tmp_path: Path, ckpts: list[Path],
                                                                    capsys: pytest.CaptureFixture,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A second run into a run's folder is refused in one line before any model or scene loads, every
    file kept; --overwrite measures again and replaces them. An --out that is a file is refused always."""
    out = tmp_path / "t"
    base = [str(DEMO), "--res", "8", "8", "--reference-spp", "2", "--repeat", "1", "--models", str(ckpts[0]),
            "--no-compare", "--quiet"]
    assert tradeoff_main([*base, "--spp", "1", "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    loads: list[str] = []
    monkeypatch.setattr(RenderSettings, "load", lambda self, aovs=(): loads.append(self.scene))
    monkeypatch.setattr(tradeoff, "model_labels", lambda models: loads.append("models"))
    assert tradeoff_main([*base, "--spp", "2", "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{out}: holds an earlier run's files (config.json, tradeoff.json, " in err
    assert "--overwrite" in err and not loads and {p.name: p.read_bytes() for p in out.iterdir()} == before
    monkeypatch.undo()

    def stop(*args: object) -> None:
        raise DenoiserError("stopped")

    monkeypatch.setattr(tradeoff, "measure", stop)  # with --overwrite the old completion marker goes first
    assert tradeoff_main([*base, "--spp", "2", "--out", str(out), "--overwrite"]) == 1
    assert "stopped" in capsys.readouterr().err and not (out / "tradeoff.json").exists()
    monkeypatch.undo()
    assert tradeoff_main([*base, "--spp", "2", "--out", str(out), "--overwrite"]) == 0
    assert {p["spp"] for p in json.loads((out / "tradeoff.json").read_text())["points"]} == {2}
    blocker = tmp_path / "a_file"
    blocker.write_text("mine")
    for extra in ([], ["--overwrite"]):
        assert tradeoff_main([*base, "--spp", "1", "--out", str(blocker), *extra]) == 1
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "a_file: exists and is not a folder" in err
    assert blocker.read_text() == "mine"


def test_analyse_synthetic_points() -> None:
    def point(name: str, spp: int, render_s: float, denoise_s: float, err: float) -> Point:
        return Point(name, spp, render_s, denoise_s, psnr=-10 * math.log10(err), relmse=err, flip=err,
                     render_times=[render_s], denoise_times=[denoise_s])

    points = [point("none", s, 0.01 * s, 0.0, 1.0 / s) for s in (1, 4, 16, 64)]
    points += [point("net", 1, 0.01, 0.05, 1.0 / 16), point("net", 4, 0.04, 0.05, 1.0 / 256)]
    result = analyse(points, {"scene": "x.xml", "resolution": [8, 8]}, "relmse")
    assert result["pareto"]["relmse"] == [["none", 1], ["none", 4], ["net", 1], ["net", 4]]
    eq = {(r["denoiser"], r["spp"]): r for r in result["equal_quality"] if r["metric"] == "relmse"}
    assert eq[("net", 1)]["raw_spp"] == pytest.approx(16) and not eq[("net", 1)]["extrapolated"]
    assert eq[("net", 1)]["saving"] == pytest.approx(0.16 / 0.06)
    assert eq[("net", 4)]["raw_spp"] == pytest.approx(256) and eq[("net", 4)]["extrapolated"]
    # recommended: of the front's denoised points, the largest equal-quality saving
    rec = recommendation(result)
    assert (rec["denoiser"], rec["spp"]) == ("net", 4) and rec["saving"] == pytest.approx(eq[("net", 4)]["saving"])
    assert recommendation_line(result).startswith("recommended: net at 4 spp")
    only_raw = analyse([p for p in points if p.denoiser == "none"], {"scene": "x.xml", "resolution": [8, 8]}, "relmse")
    assert recommendation(only_raw) is None and "raw render" in recommendation_line(only_raw)


def test_oidn_is_compared_by_default_when_installed(tmp_path: Path) -> None:
    settings = RenderSettings(str(DEMO), reference_spp=4)
    assert TradeoffConfig(settings, out="x").compare_oidn is None  # None: whenever pyoidn imports


def test_an_unknown_model_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(DenoiserError, match="registry names: fast, balanced, high, auto"):
        model_labels(["fsat"])
    code = tradeoff_main([str(DEMO), "--models", "fsat", "--reference-spp", "4", "--out",
                          str(tmp_path / "o"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 1 and len(err.splitlines()) == 1 and "'fsat'" in err


def test_labels_are_registry_names_or_the_members_files(tmp_path: Path) -> None:
    mine = write_tiny_checkpoint(tmp_path / "mine.ckpt")
    labels = model_labels(["fast", "high", f"flat-s-allspp+{mine}:-8", str(mine), str(mine)])
    assert labels == {"fast": "fast", "high": "high", "flat-s-allspp+mine:-8": f"flat-s-allspp+{mine}:-8",
                      "mine": str(mine), "mine-2": str(mine)}
    assert len(denoiser.Denoiser(labels["flat-s-allspp+mine:-8"]).members) == 2
    with pytest.raises(DenoiserError, match="nope.ckpt"):
        model_labels([f"flat-s-allspp+{tmp_path / 'nope.ckpt'}"])


def test_bad_settings(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(DenoiserError, match="distinct positive"):
        TradeoffConfig(RenderSettings("x", reference_spp=4), out="y", spp=[2, 2]).check()
    with pytest.raises(DenoiserError, match="give one of --reference FILE or --reference-spp N"):
        TradeoffConfig(RenderSettings("x"), out="y").check()
    with pytest.raises(DenoiserError, match="either --reference or --reference-spp"):
        TradeoffConfig(RenderSettings("x", reference="r.exr", reference_spp=4), out="y").check()
    with pytest.raises(SystemExit) as exc:
        tradeoff_main([str(DEMO), "--spp", "1,0", "--reference-spp", "4"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        tradeoff_main([str(DEMO)])  # no reference
    assert exc.value.code == 2 and "Traceback" not in capsys.readouterr().err


def test_registry_names_label_themselves_auto_included() -> None:
    assert model_labels(["auto", "balanced"]) == {"auto": "auto", "balanced": "balanced"}


def test_repeats_hold_one_output_at_a_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """``--repeat N`` times a denoiser N times keeping only the last image: any N, the same memory."""
    import gc
    import weakref

    import numpy as np

    from pipeline import tradeoff
    from pipeline.evaluation import Output

    alive: list[weakref.ref] = []
    most = [0]

    def fake_output(render: object, denoiser: object) -> Output:
        gc.collect()
        most[0] = max(most[0], sum(r() is not None for r in alive))
        image = np.zeros((4, 4, 3), np.float32)
        alive.append(weakref.ref(image))
        return Output(image, 0.5)

    monkeypatch.setattr(tradeoff, "denoise_output", fake_output)
    output, seconds = tradeoff._timed(None, None, 5)
    assert seconds == [0.5] * 5 and output.image is alive[-1]()
    assert most[0] == 0  # the previous output is let go before the next is made
