"""Scene preparation: includes inlined, every film forced to box/float32, clear one-line errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from imaging.errors import SceneError
from rendering.render import load_scene, prepare, render
from rendering.scene_io import pixel_filter_spec

FILM = """<scene version="3.0.0">
  <default name="res" value="24"/>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm" id="film">
      <integer name="width" value="$res"/><integer name="height" value="$res"/>
      <string name="component_format" value="float16"/>
      <rfilter type="gaussian"/>
    </film>
  </sensor>
</scene>"""

SCENE = """<scene version="3.0.0">
  <default name="light" value="1.0"/>
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <include filename="include/film.xml"/>
  <emitter type="constant"><rgb name="radiance" value="$light"/></emitter>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
  {extra}
</scene>"""


def _write_scene(folder: Path, extra: str = "") -> Path:
    (folder / "include").mkdir(parents=True, exist_ok=True)
    (folder / "include" / "film.xml").write_text(FILM)
    path = folder / "scene.xml"
    path.write_text(SCENE.format(extra=extra))
    return path


def test_included_film_gets_box_filter_and_float32(tmp_path: Path) -> None:
    prepared = prepare(_write_scene(tmp_path))
    assert "<include" not in prepared.xml and 'type="gaussian"' not in prepared.xml
    scene = load_scene(prepared)
    film = scene.sensors()[0].film()
    assert str(film.rfilter()).startswith("BoxFilter")
    assert tuple(film.crop_size()) == (24, 24)
    assert 'name="component_format" value="float32"' in prepared.xml


def test_a_named_pixel_filter_is_forced_instead_of_the_box(tmp_path: Path) -> None:
    prepared = prepare(_write_scene(tmp_path), pixel_filter="gaussian:stddev=0.3")
    assert prepared.pixel_filter == {"type": "gaussian", "stddev": 0.3}
    assert '<rfilter type="gaussian"><float name="stddev" value="0.3" /></rfilter>' in prepared.xml
    assert str(load_scene(prepared).sensors()[0].film().rfilter()).startswith("GaussianFilter")


@pytest.mark.parametrize("text, spec", [
    (None, {"type": "box"}), ("box", {"type": "box"}), ("gaussian", {"type": "gaussian", "stddev": 0.5}),
    ("gaussian:stddev=0.25", {"type": "gaussian", "stddev": 0.25}),
    ("lanczos", {"type": "lanczos", "lobes": 3}), ({"type": "tent"}, {"type": "tent"}),
    ("mitchell:B=0.5", {"type": "mitchell", "B": 0.5, "C": 1 / 3}),
])
def test_pixel_filter_spec_fills_in_the_defaults(text: object, spec: dict) -> None:
    assert pixel_filter_spec(text) == spec


@pytest.mark.parametrize("text, message", [
    ("blackman-harris", "unknown pixel filter 'blackman-harris' (valid: box, tent, gaussian, mitchell"),
    ("gaussian:radius=2", "pixel filter 'gaussian' has no parameter 'radius' (it takes: stddev)"),
    ("gaussian:stddev=-1", "stddev must be a number > 0"),
    ("gaussian:stddev", "expected NAME or NAME:PARAM=NUMBER"),
])
def test_a_bad_pixel_filter_is_one_line(text: str, message: str) -> None:
    with pytest.raises(SceneError) as exc:
        pixel_filter_spec(text)
    assert message in str(exc.value)


def test_params_and_resolution(tmp_path: Path) -> None:
    path = _write_scene(tmp_path)
    dim = render(path, spp=2, params={"light": 0.5}).rgb
    bright = render(path, spp=2, params={"light": 1.0}).rgb
    assert dim.shape == (24, 24, 3)
    np.testing.assert_allclose(bright.mean(), 2 * dim.mean(), rtol=1e-4)
    assert render(path, spp=1, params={"res": 10}).rgb.shape == (10, 10, 3)
    assert render(path, spp=1, resolution=(16, 8)).rgb.shape == (8, 16, 3)


def test_undeclared_param_is_refused(tmp_path: Path) -> None:
    with pytest.raises(SceneError, match=r"scene\.xml: --param 'nope' is not a parameter"):
        prepare(_write_scene(tmp_path), params={"nope": 3})


def _one_line_error(path: Path) -> str:
    with pytest.raises(SceneError) as info:
        load_scene(prepare(path))
    message = str(info.value)
    assert "\n" not in message and str(path) in message
    return message


def test_errors_name_file_and_problem(tmp_path: Path) -> None:
    assert "file not found" in _one_line_error(tmp_path / "missing.xml")
    assert "is a directory" in _one_line_error(tmp_path)
    bad = tmp_path / "bad.xml"
    bad.write_text("<scene version='3.0.0'><shape type='sphere'></scene>")
    assert "malformed XML" in _one_line_error(bad)
    mesh = _write_scene(tmp_path / "m", '<shape type="ply"><string name="filename" value="gone.ply"/></shape>')
    assert "gone.ply" in _one_line_error(mesh)
    plugin = _write_scene(tmp_path / "p", '<shape type="no_such_plugin"/>')
    assert "no_such_plugin" in _one_line_error(plugin)


def test_missing_include_is_named(tmp_path: Path) -> None:
    path = _write_scene(tmp_path)
    (tmp_path / "include" / "film.xml").unlink()
    message = _one_line_error(path)
    assert "film.xml" in message and "file not found" in message


def test_shared_eval_scene_matches_its_recorded_noise() -> None:
    """A real scene with an included gaussian film renders exactly like the stored box-filter data."""
    root = Path(__file__).resolve().parents[2] / "shared" / "eval-scenes" / "matpreview_gold"
    if not root.exists():
        pytest.skip("../shared/eval-scenes is not beside this checkout")
    import json

    from imaging.exr import read_exr
    from imaging.metrics import psnr

    recorded = json.loads((root / "reference.json").read_text())["spp16"]["noisy_psnr"]
    noisy = render(root / "scene.xml", spp=16, seed=7).rgb
    assert abs(psnr(noisy, read_exr(root / "reference.exr").rgb) - recorded) < 0.02
