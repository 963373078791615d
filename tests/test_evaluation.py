"""The one evaluation path (render in halves -> denoise as render-and-denoise does -> score): what
each step gives, and that the scoreboard (benchmarks/evaluate.py) and ``render-and-denoise`` report
the same PSNR for the same scene, spp and seed."""
from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from benchmarks import evaluate as scoreboard
from imaging.errors import DenoiserError
from imaging.exr import write_exr
from imaging.metrics import flip, psnr, relmse
from pipeline.cli import main as render_main
from denoise.denoiser import Denoiser
from pipeline.evaluation import (AOVS, BARE, OIDN, OIDN_AUX, RenderSettings, denoise_outputs, evaluate, make_denoiser,
                                 render_input, score, with_aovs)
from denoise.oidn import oidn_available
from tests.test_denoiser import TINY, write_tiny_checkpoint

ROOT = Path(__file__).resolve().parents[1]
DEMO = ROOT / "scenes" / "examples" / "demo.xml"
SIZE = (32, 24)


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An untrained model that changes the image beyond the noise (a residual one is the identity)."""
    return write_tiny_checkpoint(tmp_path_factory.mktemp("model") / "tiny.ckpt", replace(TINY, output="direct"))


@pytest.fixture(scope="module")
def demo() -> tuple[RenderSettings, object]:
    settings = RenderSettings(str(DEMO), SIZE, seed=3)
    return settings, settings.load()


def test_render_input_is_two_halves_unless_the_guard_is_off(demo: tuple) -> None:
    settings, scene = demo
    halves = render_input(scene, 4, settings)
    assert halves.variance is not None and halves.variance.shape == halves.rgb.shape and halves.spp == 4
    plain = render_input(scene, 4, RenderSettings(str(DEMO), SIZE, seed=3, noise_guard=False))
    assert plain.variance is None and not np.array_equal(plain.rgb, halves.rgb)


def test_outputs_are_the_default_path_and_the_bare_network(demo: tuple, ckpt: Path) -> None:
    settings, scene = demo
    render = render_input(scene, 4, settings)
    den = Denoiser(ckpt)
    outputs = denoise_outputs(render, {"tiny": den}, oidn=oidn_available(), bare=True)
    assert set(outputs) == {"tiny", "tiny" + BARE} | ({OIDN} if oidn_available() else set())
    assert np.array_equal(outputs["tiny"].image, den.denoise_render(render).image)
    # A flat RGB model has no noise input: its bare output is the unguarded, uncorrected one.
    assert np.array_equal(outputs["tiny" + BARE].image, Denoiser(ckpt, energy=None).denoise_array(render.rgb).image)
    assert outputs["tiny"].result.guard_weight < 0.9
    assert not np.array_equal(outputs["tiny"].image, outputs["tiny" + BARE].image)


def test_with_aovs_adds_the_aovs_of_the_render_and_leaves_its_radiance(demo: tuple) -> None:
    """The AOV pass: the albedo and normals the same render with AOVs has, on the same rgb array;
    the scene renders our models' input as before; a render that has them is kept as it is."""
    settings, scene = demo
    render = render_input(scene, 4, settings)
    added, seconds = with_aovs(render, scene, settings)
    assert added.rgb is render.rgb and render.aovs == {} and seconds > 0
    wrapped = render_input(settings.load(AOVS), 4, settings, AOVS)
    for name in AOVS:
        assert np.array_equal(added.aovs[name], wrapped.aovs[name]), name
    assert np.array_equal(render_input(scene, 4, settings).rgb, render.rgb)
    assert with_aovs(wrapped, scene, settings) == (wrapped, 0.0)


@pytest.mark.skipif(not oidn_available(), reason="make installs pyoidn (the oidn extra)")
def test_oidn_colour_only_and_with_albedo_and_normals(demo: tuple, ckpt: Path) -> None:
    """With OIDN: colour-only and with the render's albedo and normals, both scored; our model's
    figures are those of the same evaluation without OIDN."""
    settings, scene = demo
    reference = render_input(scene, 64, RenderSettings(str(DEMO), SIZE, seed=99)).rgb
    ev = evaluate(scene, 4, settings, reference, {"tiny": Denoiser(ckpt)}, oidn=True)
    assert set(ev.scores) == {"noisy", "tiny", OIDN, OIDN_AUX} and ev.aov_seconds > 0
    assert ev.scores[OIDN_AUX] != ev.scores[OIDN]
    alone = evaluate(scene, 4, settings, reference, {"tiny": Denoiser(ckpt)}, oidn=False)
    assert alone.scores["tiny"] == ev.scores["tiny"] and alone.aov_seconds is None
    assert set(denoise_outputs(alone.render, {}, oidn=True)) == {OIDN}  # no AOVs, no OIDN + albedo + normal


def test_evaluate_scores_every_output_with_the_metrics(demo: tuple, ckpt: Path) -> None:
    settings, scene = demo
    reference = render_input(scene, 64, RenderSettings(str(DEMO), SIZE, seed=99)).rgb
    ev = evaluate(scene, 4, settings, reference, {"tiny": Denoiser(ckpt)}, oidn=False, bare=True)
    assert set(ev.scores) == {"noisy", "tiny", "tiny" + BARE}
    image = ev.outputs["tiny"].image
    assert ev.scores["tiny"] == {"psnr": psnr(image, reference), "relmse": relmse(image, reference),
                                 "flip": flip(image, reference)}
    assert score(image, reference, full=True)["psnr"] == ev.scores["tiny"]["psnr"]
    with pytest.raises(DenoiserError, match="reference is 8x8, render is 32x24"):
        evaluate(scene, 4, settings, reference[:8, :8], {}, oidn=False)


def test_settings_refuse_two_references_or_none_when_needed() -> None:
    with pytest.raises(DenoiserError, match="not both"):
        RenderSettings("s.xml", reference="r.exr", reference_spp=4).check()
    with pytest.raises(DenoiserError, match="give one of --reference"):
        RenderSettings("s.xml").check(reference_required=True)
    RenderSettings("s.xml").check()


def eval_folder(tmp_path: Path) -> Path:
    """``tmp_path/eval/demo``: the demo scene as an eval scene, its 64-spp reference beside it."""
    folder = tmp_path / "eval" / "demo"
    shutil.copytree(DEMO.parent, folder)
    (folder / "demo.xml").rename(folder / "scene.xml")
    settings = RenderSettings(str(folder / "scene.xml"), SIZE, seed=123)
    reference = render_input(settings.load(), 64, settings).rgb
    write_exr(folder / "reference.exr", reference)
    (folder / "reference.json").write_text(json.dumps({"reference_psnr_ceiling_db": 45.0,
                                                       "shape": [SIZE[1], SIZE[0], 3]}))
    return folder


@pytest.mark.skipif(not oidn_available(), reason="make installs pyoidn (the oidn extra)")
def test_scoreboard_has_oidn_colour_only_and_with_albedo_and_normals(tmp_path: Path, ckpt: Path) -> None:
    eval_folder(tmp_path)
    assert scoreboard.main(["--eval-dir", str(tmp_path / "eval"), "--model", str(ckpt), "--spp", "2",
                            "--out", str(tmp_path / "board"), "--quiet"]) == 0
    board = json.loads((tmp_path / "board" / "evaluate.json").read_text())
    entry, mean = board["scenes"]["demo"]["2"], board["summary"]["scored"]["2"]
    assert entry["oidn_aux"] != entry["oidn"] and entry["aov_render_s"] > 0 and entry["oidn_aux_s"] > 0
    assert mean["oidn_aux_psnr"] == entry["oidn_aux"]["psnr"] and mean["oidn_psnr"] == entry["oidn"]["psnr"]
    table = (tmp_path / "board" / "evaluate.md").read_text()
    assert "OIDN colour-only PSNR" in table and "OIDN + albedo + normal PSNR" in table
    assert "OIDN + albedo + normal" in (tmp_path / "board" / "evaluate.html").read_text()


@pytest.mark.slow
@pytest.mark.parametrize("energy, energy_flag", [("on", []), ("off", ["--no-energy"])])
def test_scoreboard_and_render_and_denoise_give_the_same_psnr(tmp_path: Path, ckpt: Path, energy: str,
                                                              energy_flag: list[str]) -> None:
    """The same scene, spp and seed through ``python -m benchmarks.evaluate`` and through
    ``render-and-denoise``: the same noisy, denoised and OIDN figures, with and without the
    energy correction (``--energy off`` / ``--no-energy``)."""
    folder = eval_folder(tmp_path)
    spp = 4
    assert scoreboard.main(["--eval-dir", str(tmp_path / "eval"), "--model", str(ckpt), "--spp", str(spp),
                            "--out", str(tmp_path / "board"), "--quiet", "--energy", energy]) == 0
    board = json.loads((tmp_path / "board" / "evaluate.json").read_text())["scenes"]["demo"][str(spp)]
    assert render_main([str(folder / "scene.xml"), "--res", *map(str, SIZE), "--spp", str(spp), "--seed",
                        str(scoreboard.SEED), "--reference", str(folder / "reference.exr"), "--model", str(ckpt),
                        "--out", str(tmp_path / "run"), "--quiet", *energy_flag]) == 0
    quality = json.loads((tmp_path / "run" / "metrics.json").read_text())["quality"]
    assert quality["denoised"]["psnr"] == board["ours"]["psnr"]
    assert quality["noisy"]["psnr"] == board["noisy"]["psnr"]
    assert quality["denoised"]["relmse"] == board["ours"]["relmse"]
    if oidn_available():
        assert quality["oidn"]["psnr"] == board["oidn"]["psnr"]
        assert quality["oidn_aux"]["psnr"] == board["oidn_aux"]["psnr"]
    assert board["ours_bare"]["psnr"] != board["ours"]["psnr"]


def test_skip_below_reaches_the_denoiser_only_with_the_halves(demo: tuple, ckpt: Path) -> None:
    """--skip-below: a converged render (noise below any threshold here) comes back as itself, the
    network skipped; without the halves there is no noise estimate and nothing is skipped."""
    settings, scene = demo
    skipping = make_denoiser(ckpt, replace(settings, skip_below=1.0))
    assert skipping.skip_below == 1.0
    assert make_denoiser(ckpt, replace(settings, skip_below=1.0, noise_guard=False)).skip_below is None
    render = render_input(scene, 4, settings)
    out = skipping.denoise_render(render)
    assert out.tiles == 0 and np.array_equal(out.image, np.clip(render.rgb, 0, None))


def test_skip_below_flag_goes_into_the_settings(tmp_path: Path, ckpt: Path) -> None:
    out = tmp_path / "run"
    assert render_main([str(DEMO), "--res", "16", "16", "--spp", "2", "--model", str(ckpt), "--no-compare",
                        "--skip-below", "1", "--out", str(out)]) == 0
    assert json.loads((out / "config.json").read_text())["render"]["skip_below"] == 1.0


def test_scoreboard_refuses_an_unknown_energy_choice(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    (tmp_path / "eval" / "demo").mkdir(parents=True)
    with pytest.raises(SystemExit) as exit_info:
        scoreboard.main(["--eval-dir", str(tmp_path / "eval"), "--energy", "on,maybe", "--quiet"])
    assert exit_info.value.code != 0
    err = capsys.readouterr().err.strip()
    assert "--energy: maybe is not one of on, off" in err and "\n" not in err
