"""render-and-denoise and denoise end to end on 32-px renders; bad input -> one line, exit 1."""
from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from imaging.exr import read_exr, write_exr
from pipeline.cli import denoise_main, main, tradeoff_main
from pipeline.evaluation import RenderSettings
from denoise.denoiser import Denoiser
from tests.test_denoiser import write_tiny_checkpoint

DEMO = Path(__file__).resolve().parents[1] / "scenes" / "examples" / "demo.xml"
OUTPUTS = ("noisy.exr", "denoised.exr", "oidn.exr", "oidn_aux.exr", "reference.exr", "noisy.png", "denoised.png",
           "oidn.png", "oidn_aux.png", "reference.png", "comparison.png", "metrics.json", "report.html", "config.json")


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.ckpt")


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory: pytest.TempPathFactory, ckpt: Path) -> Path:
    out = tmp_path_factory.mktemp("run") / "demo"
    old = os.umask(0o022)
    try:
        code = main([str(DEMO), "--spp", "4", "--res", "32", "24", "--reference-spp", "64",
                     "--model", str(ckpt), "--out", str(out), "--quiet"])
    finally:
        os.umask(old)
    assert code == 0
    return out


def test_render_and_denoise_writes_everything(demo_run: Path, ckpt: Path) -> None:
    """OIDN is compared by default (pyoidn is installed by make); every file readable by all
    (0644 under the umask 022 the fixture ran with)."""
    for name in OUTPUTS:
        assert (demo_run / name).stat().st_size > 0, name
        assert stat.S_IMODE((demo_run / name).stat().st_mode) == 0o644, name
    metrics = json.loads((demo_run / "metrics.json").read_text())
    assert metrics["resolution"] == [32, 24] and metrics["spp"] == 4
    assert set(metrics["quality"]) == {"noisy", "denoised", "oidn", "oidn_aux"} and metrics["oidn"]["compared"]
    assert metrics["quality"]["oidn_aux"]["psnr"] != metrics["quality"]["oidn"]["psnr"]
    assert metrics["timings"]["aov_render_s"] > 0 and metrics["timings"]["oidn_aux_s"] > 0
    for row in metrics["quality"].values():
        for key in ("psnr", "ssim", "relmse", "smape", "flip", "hdr_flip"):
            assert np.isfinite(row[key]), key
    assert metrics["model"]["name"] == str(ckpt) and len(metrics["model"]["sha256"]) == 64
    assert metrics["model"]["precision"] == Denoiser(ckpt).precision  # auto: what this CPU gets
    assert metrics["model"]["flips"] == 1
    assert all(v >= 0 for v in metrics["timings"].values())
    assert read_exr(demo_run / "denoised.exr").rgb.shape == (24, 32, 3)
    html = (demo_run / "report.html").read_text()
    assert "PSNR" in html and 'data-dtype="f16"' in html and "noise guard weight" in html
    assert "OIDN colour-only" in html and "OIDN + albedo + normal" in html
    assert "energy correction" in html and "mean factor" in html


def test_reference_file_and_no_reference(tmp_path: Path, demo_run: Path, ckpt: Path) -> None:
    out = tmp_path / "again"
    assert main([str(DEMO), "--spp", "4", "--res", "32", "24", "--model", str(ckpt), "--quiet",
                 "--reference", str(demo_run / "reference.exr"), "--out", str(out)]) == 0
    again = json.loads((out / "metrics.json").read_text())
    first = json.loads((demo_run / "metrics.json").read_text())
    assert again["quality"]["noisy"]["psnr"] == pytest.approx(first["quality"]["noisy"]["psnr"], rel=1e-6)
    bare = tmp_path / "bare"
    assert main([str(DEMO), "--spp", "2", "--res", "16", "16", "--model", str(ckpt), "--quiet",
                 "--no-compare", "--out", str(bare)]) == 0
    metrics = json.loads((bare / "metrics.json").read_text())
    assert "quality" not in metrics and "no reference" in metrics["note"]
    assert set(metrics["stats"]) == {"noisy", "denoised"} and not (bare / "oidn.exr").exists()
    assert metrics["oidn"] == {"compared": False, "note": "OIDN not compared (--no-compare)"}
    assert json.loads((bare / "config.json").read_text())["compare_oidn"] is False


def test_an_earlier_run_is_refused_before_rendering_unless_overwrite(tmp_path: Path, ckpt: Path,
                                                                    capsys: pytest.CaptureFixture,
                                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    """A second run into a run's folder is refused in one line before the scene loads, every file
    kept; --overwrite runs and replaces them. A folder of other files is used; a file is refused always."""
    out = tmp_path / "o"
    base = [str(DEMO), "--res", "16", "16", "--model", str(ckpt), "--no-compare", "--quiet"]
    assert main([*base, "--spp", "1", "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    loads: list[str] = []
    monkeypatch.setattr(RenderSettings, "load", lambda self, aovs=(): loads.append(self.scene))
    _one_line_error(capsys, main([*base, "--spp", "2", "--out", str(out)]),
                    f"{out}: holds an earlier run's files (config.json, metrics.json, report.html and", "--overwrite")
    assert not loads and {p.name: p.read_bytes() for p in out.iterdir()} == before
    monkeypatch.undo()
    assert main([*base, "--spp", "2", "--out", str(out), "--overwrite"]) == 0
    assert json.loads((out / "metrics.json").read_text())["spp"] == 2
    assert read_exr(out / "noisy.exr").metadata["spp"] == 2
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    assert main([*base, "--spp", "1", "--out", str(mine)]) == 0
    assert (mine / "notes.txt").read_text() == "mine" and (mine / "metrics.json").exists()
    blocker = tmp_path / "a_file"
    blocker.write_text("mine")
    for extra in ([], ["--overwrite"]):
        _one_line_error(capsys, main([*base, "--spp", "1", "--out", str(blocker), *extra]),
                        "a_file: exists and is not a folder")
    assert blocker.read_text() == "mine"


def test_an_ensemble_runs_its_low_spp_member_only_at_low_spp(tmp_path: Path, ckpt: Path) -> None:
    """render-and-denoise --model A+B with B trained for <= 8 spp: both run at 2 spp, A alone at
    32; metrics.json and the report say which ran."""
    low = write_tiny_checkpoint(tmp_path / "low.ckpt", seed=2, max_spp=8)
    for spp, ran in ((2, ["tiny", "low"]), (32, ["tiny"])):
        out = tmp_path / f"s{spp}"
        assert main([str(DEMO), "--spp", str(spp), "--res", "16", "16", "--model", f"{ckpt}+{low}", "--quiet",
                     "--no-compare", "--out", str(out)]) == 0
        model = json.loads((out / "metrics.json").read_text())["model"]
        assert model["models_run"] == ran and [m["max_spp"] for m in model["members"]] == [0, 8]
        assert f"ran: {' + '.join(ran)}" in (out / "report.html").read_text()


def test_noise_guard_on_by_default_and_off_on_request(tmp_path: Path, demo_run: Path, ckpt: Path) -> None:
    guarded = json.loads((demo_run / "metrics.json").read_text())["noise_guard"]
    assert 0.0 <= guarded["mean_weight"] <= 1.0 and guarded["strength"] >= 1.0
    assert 0.5 < json.loads((demo_run / "metrics.json").read_text())["energy"]["mean_factor"] < 1.5
    unmatched = tmp_path / "unmatched"
    assert main([str(DEMO), "--spp", "4", "--res", "32", "24", "--model", str(ckpt), "--quiet",
                 "--no-energy", "--no-compare", "--out", str(unmatched)]) == 0
    assert json.loads((unmatched / "metrics.json").read_text())["energy"] is None
    assert json.loads((unmatched / "config.json").read_text())["render"]["energy"] is False
    out = tmp_path / "plain"
    assert main([str(DEMO), "--spp", "4", "--res", "32", "24", "--model", str(ckpt), "--quiet",
                 "--no-noise-guard", "--out", str(out)]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["noise_guard"] is None
    assert json.loads((out / "config.json").read_text())["render"]["noise_guard"] is False
    # Unguarded, one-piece render: another noise realisation than the guarded two-halves render.
    assert not np.array_equal(read_exr(out / "noisy.exr").rgb, read_exr(demo_run / "noisy.exr").rgb)


def test_oidn_with_albedo_and_normals_leaves_our_input_as_it_was(tmp_path: Path, demo_run: Path, ckpt: Path) -> None:
    """The AOV pass for OIDN + albedo + normal renders apart: without OIDN the render and our output
    are the same images, bit for bit."""
    out = tmp_path / "alone"
    assert main([str(DEMO), "--spp", "4", "--res", "32", "24", "--model", str(ckpt), "--no-compare", "--quiet",
                 "--out", str(out)]) == 0
    for name in ("noisy.exr", "denoised.exr"):
        assert np.array_equal(read_exr(out / name).rgb, read_exr(demo_run / name).rgb), name
    assert not (out / "oidn_aux.exr").exists()


def test_denoise_command(tmp_path: Path, demo_run: Path, ckpt: Path, capsys: pytest.CaptureFixture) -> None:
    half = tmp_path / "noisy16.exr"
    write_exr(half, read_exr(demo_run / "noisy.exr").rgb, half=True)
    out = tmp_path / "out.exr"
    assert denoise_main([str(half), str(out), "--model", str(ckpt),
                         "--reference", str(demo_run / "reference.exr"), "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert set(printed["quality"]) == {"noisy", "denoised", "oidn"}  # no albedo or normal layers in the file
    assert read_exr(out).rgb.shape == (24, 32, 3)


def _one_line_error(capsys: pytest.CaptureFixture, code: int, *needles: str) -> None:
    err = capsys.readouterr().err.strip()
    assert code != 0
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, err


def test_render_bad_input(tmp_path: Path, ckpt: Path, demo_run: Path, capsys: pytest.CaptureFixture) -> None:
    base = ["--model", str(ckpt), "--quiet", "--spp", "2", "--res", "16", "16"]
    _one_line_error(capsys, main([str(tmp_path / "nope.xml"), *base, "--out", str(tmp_path / "a")]), "nope.xml")
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene version='3.0.0'><shape type='sphere'>")
    _one_line_error(capsys, main([str(bad), *base, "--out", str(tmp_path / "b")]), "bad.xml")
    _one_line_error(capsys, main([str(DEMO), *base, "--param", "nosuch=1", "--out", str(tmp_path / "c")]),
                    "nosuch")
    _one_line_error(capsys, main([str(DEMO), *base, "--reference", str(demo_run / "reference.exr"),
                                  "--out", str(tmp_path / "d")]), "reference.exr")
    _one_line_error(capsys, main([str(DEMO), "--model", str(tmp_path / "no.ckpt"), "--quiet",
                                  "--out", str(tmp_path / "e")]), "no.ckpt")
    assert not (tmp_path / "d" / "metrics.json").exists()


@pytest.mark.parametrize("args", [["--spp", "0"], ["--spp", "x"], ["--res", "0", "16"], ["--param", "novalue"]])
def test_render_bad_arguments_exit_2(args: list[str], capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        main([str(DEMO), *args])
    assert exc.value.code == 2 and "Traceback" not in capsys.readouterr().err


def test_denoise_bad_input(tmp_path: Path, ckpt: Path, demo_run: Path, capsys: pytest.CaptureFixture) -> None:
    notexr = tmp_path / "not.exr"
    notexr.write_text("hello")
    _one_line_error(capsys, denoise_main([str(notexr), str(tmp_path / "o.exr"), "--model", str(ckpt)]), "not.exr")
    _one_line_error(capsys, denoise_main([str(tmp_path), str(tmp_path / "o.exr"), "--model", str(ckpt)]))
    small = tmp_path / "small.exr"
    write_exr(small, np.ones((8, 8, 3), np.float32))
    _one_line_error(capsys, denoise_main([str(small), str(tmp_path / "o.exr"), "--model", str(ckpt),
                                          "--reference", str(demo_run / "reference.exr")]), "reference.exr")
    assert not (tmp_path / "o.exr").exists()


def test_shipped_model_beats_noisy_input_on_demo_scene(tmp_path: Path) -> None:
    """The default model (the registry's ``high``) on our own 32-px demo scene at 16 spp."""
    out = tmp_path / "shipped"
    assert main([str(DEMO), "--spp", "16", "--res", "32", "32", "--reference-spp", "512",
                 "--out", str(out), "--quiet"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["model"]["name"] == "high" and metrics["model"]["ran"] == "high"
    # unet-l-allspp and flat-s-allspp in float32: above 16 spp only
    assert metrics["model"]["models_run"] == ["flat-s-allspp", "unet-m-k5-lowspp", "unet-m-k5-lowspp-b"]
    assert metrics["notes"] == [] and metrics["pixel_filter"] == "box"
    quality = metrics["quality"]
    assert quality["denoised"]["psnr"] > quality["noisy"]["psnr"] + 1.0
    assert quality["denoised"]["relmse"] < quality["noisy"]["relmse"]


def test_oidn_compared_by_default_only_when_installed(monkeypatch: pytest.MonkeyPatch) -> None:
    import pipeline.run as run_module

    monkeypatch.setattr(run_module, "oidn_available", lambda: False)
    missing = run_module._oidn_setting(None)
    assert not missing["compared"] and "pyoidn is not installed" in missing["note"]
    assert run_module._oidn_setting(True)["compared"]  # asked for: oidn_denoise then names pyoidn
    monkeypatch.setattr(run_module, "oidn_available", lambda: True)
    assert run_module._oidn_setting(None)["compared"] and not run_module._oidn_setting(False)["compared"]


@pytest.mark.parametrize("command", [main, denoise_main])
def test_help_lists_the_registry_names_and_list_models_prints_the_cards(command, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        command(["--help"])
    out = capsys.readouterr().out
    assert exc.value.code == 0
    for name in ("fast", "balanced", "high", "auto"):
        assert f"\n  {name}: " in out  # one line each
    with pytest.raises(SystemExit) as exc:
        command(["--list-models"])  # no scene or file needed
    out = capsys.readouterr().out
    assert exc.value.code == 0 and out.startswith("fast: ") and "runs, spp unknown: " in out and "recipe" in out
    # which networks run at which spp, as a person reads it, not the spec string
    assert "\n    1-16 spp: unet-m-k5-lowspp\n    17+ spp: unet-l-allspp\n" in out
    assert "\n    9-16 spp: unet-m-k5-lowspp + flat-s-allspp\n" in out and ":-16+" not in out


def test_a_wrong_model_name_lists_the_valid_ones(tmp_path: Path, demo_run: Path, capsys: pytest.CaptureFixture) -> None:
    assert denoise_main([str(demo_run / "noisy.exr"), str(tmp_path / "o.exr"), "--model", "hihg"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "unknown model 'hihg' (registry names: fast, balanced, high, auto" in err
    assert not (tmp_path / "o.exr").exists()


def test_denoise_without_spp_says_what_it_ran_and_the_name_it_prints_works(
        tmp_path: Path, demo_run: Path, capsys: pytest.CaptureFixture) -> None:
    plain = tmp_path / "plain.exr"
    write_exr(plain, read_exr(demo_run / "noisy.exr").rgb)  # no spp attribute
    assert denoise_main([str(plain), str(tmp_path / "a.exr"), "--model", "fast"]) == 0
    captured = capsys.readouterr()
    assert "denoise: note: spp unknown: ran" in captured.err
    assert "model fast (spp unknown)" in captured.out  # the table, not JSON
    assert denoise_main([str(plain), str(tmp_path / "b.exr"), "--model", "fast", "--spp", "16", "--json"]) == 0
    record = json.loads(capsys.readouterr().out)
    assert record["model"] == "fast" and record["notes"] == [] and record["spp"] == 16
    assert denoise_main([str(plain), str(tmp_path / "c.exr"), "--model", record["model"], "--quiet"]) == 0
    assert denoise_main([str(plain), str(tmp_path / "d.exr"), "--model", "auto", "--spp", "16"]) == 0
    from model.registry import registry

    assert f"model auto -> {registry().auto_entry(16)} (16 spp): ran " in capsys.readouterr().out


def test_render_and_denoise_takes_auto_without_a_budget(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``--model auto``: the registry picks an entry for the render's spp; the record and the
    summary name both, and the networks that ran; the render draws a progress bar of its samples."""
    from model.registry import registry

    out = tmp_path / "auto"
    assert main([str(DEMO), "--spp", "4", "--res", "24", "24", "--model", "auto", "--no-compare",
                 "--out", str(out)]) == 0
    model = json.loads((out / "metrics.json").read_text())["model"]
    assert model["name"] == "auto" and model["ran"] == registry().auto_entry(4)
    captured = capsys.readouterr()
    assert f"model auto -> {model['ran']}, ran {' + '.join(model['models_run'])} (" in captured.out
    assert "render: 100%" in captured.err and "2.30k/2.30k" in captured.err  # 4 x 24 x 24 samples
    assert f"... denoising with auto -> {model['ran']}\n" in captured.err


def test_quiet_and_json_draw_no_progress(tmp_path: Path, ckpt: Path, capsys: pytest.CaptureFixture) -> None:
    for flag in ("--quiet", "--json"):
        assert main([str(DEMO), "--spp", "2", "--res", "16", "16", "--model", str(ckpt), "--no-compare",
                     "--out", str(tmp_path / flag), flag]) == 0
        assert capsys.readouterr().err == ""


def test_a_film_too_large_for_the_memory_is_refused_in_one_line_before_rendering(
        tmp_path: Path, ckpt: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--res 100000 100000``: the images it would hold, in bytes, against the memory left (set
    to 64 GiB here), before any render; ``tradeoff`` the same."""
    import imaging.memory_limit

    monkeypatch.setattr(imaging.memory_limit, "available_bytes", lambda: 64 * 2**30)
    args = [str(DEMO), "--res", "100000", "100000", "--model", str(ckpt), "--no-compare"]
    _one_line_error(capsys, main([*args, "--spp", "4", "--out", str(tmp_path / "r")]),
                    "demo.xml: 100000x100000 pixels: 3 float32 images (rgb, variance, denoised) and the "
                    "render's scratch need 343,", "more than the 65,536 MB of memory available")
    assert not (tmp_path / "r" / "noisy.exr").exists()
    assert not (tmp_path / "r" / "config.json").exists()  # the corrected command may use the folder
    assert main([str(DEMO), "--res", "16", "16", "--model", str(ckpt), "--no-compare", "--spp", "2", "--quiet",
                 "--out", str(tmp_path / "r")]) == 0
    _one_line_error(capsys, tradeoff_main([*args, "--spp", "4", "--reference-spp", "8", "--quiet",
                                           "--out", str(tmp_path / "t")]),
                    "100000x100000 pixels: 4 float32 images (rgb, variance, denoised, reference)",
                    "65,536 MB of memory available")
