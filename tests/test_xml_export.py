"""Dict -> XML serializer: value kinds, exact floats, errors, files written by write_scene."""
from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pytest

from rendering.backend import select_variant
from imaging.exr import read_exr
from rendering.render import render
from scenes.spec import GeneratedScene
from scenes.transforms import compose, rotate, scale, to_mitsuba, translate
from scenes.xml_export import format_float, plugin_tag, scene_to_xml, write_scene


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


def _scene(**extra) -> dict:
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4, "hide_emitters": False},
        "sensor": {"type": "perspective", "fov": 40.0,
                   "to_world": to_mitsuba(translate((0.0, 0.0, 3.0)) @ rotate((0, 1, 0), 180.0)),
                   "film": {"type": "hdrfilm", "width": 16, "height": 8},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "red": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.1, 0.1]}},
        "ball": {"type": "sphere", "center": [0.0, 0.0, 0.0], "radius": 0.5,
                 "bsdf": {"type": "ref", "id": "red"}},
        "lamp": {"type": "point", "position": [1.0, 2.0, 3.0],
                 "intensity": {"type": "rgb", "value": 5.0}},
    }
    scene.update(extra)
    return scene


def test_value_kinds_map_to_xml_elements():
    root = ET.fromstring(scene_to_xml(_scene()))
    assert root.tag == "scene"
    integrator = root.find("integrator")
    assert integrator.get("type") == "path" and integrator.get("id") == "integrator"
    assert integrator.find("integer").attrib == {"name": "max_depth", "value": "4"}
    assert integrator.find("boolean").attrib == {"name": "hide_emitters", "value": "false"}
    sensor = root.find("sensor")
    assert sensor.find("float").attrib == {"name": "fov", "value": "40.0"}
    assert len(sensor.find("transform[@name='to_world']/matrix").get("value").split()) == 16
    assert sensor.find("film").get("name") == "film"
    assert root.find("bsdf[@id='red']/rgb").get("value") == "0.7, 0.1, 0.1"
    assert root.find("shape[@id='ball']/ref").attrib == {"name": "bsdf", "id": "red"}
    assert root.find("shape[@id='ball']/point").attrib == {"name": "center", "value": "0.0, 0.0, 0.0"}
    assert root.find("emitter[@id='lamp']/rgb").get("value") == "5.0"


def test_resolution_and_spp_become_parameters_with_defaults():
    root = ET.fromstring(scene_to_xml(_scene()))
    defaults = {d.get("name"): d.get("value") for d in root.findall("default")}
    assert defaults == {"resx": "16", "resy": "8", "spp": "4"}
    assert root.find("sensor/film/integer[@name='width']").get("value") == "$resx"
    assert root.find("sensor/sampler/integer[@name='sample_count']").get("value") == "$spp"


def test_floats_parse_back_exactly(rng):
    for x in list(rng.normal(size=200) * 10.0 ** rng.integers(-8, 8, size=200)) + [0.1, 1 / 3, 1e-30]:
        assert float(format_float(x)) == float(x)
    with pytest.raises(ValueError, match="non-finite"):
        format_float(float("nan"))


def test_matrix_entries_are_written_exactly(rng):
    m = compose(translate(rng.normal(size=3)), rotate(rng.normal(size=3), 33.3), scale((0.3, 2.0, 1.1)))
    root = ET.fromstring(scene_to_xml({"type": "scene",
                                       "s": {"type": "cube", "to_world": to_mitsuba(m)}}))
    values = [float(v) for v in root.find("shape/transform/matrix").get("value").split()]
    assert np.array_equal(np.array(values).reshape(4, 4), m)


def test_scalar_transform_is_written_as_a_matrix_and_loads_back():
    select_variant()
    import mitsuba as mi

    t = mi.ScalarTransform4f().translate([1.0, 2.0, 3.0]) @ mi.ScalarTransform4f().scale(2.0)
    xml = scene_to_xml({"type": "scene", "s": {"type": "rectangle", "to_world": t}})
    loaded = mi.load_string(xml)
    bbox = loaded.shapes()[0].bbox()
    assert np.allclose(np.array(bbox.min), [-1.0, 0.0, 3.0])
    assert np.allclose(np.array(bbox.max), [3.0, 4.0, 3.0])


def test_plugin_tags():
    assert plugin_tag("roughplastic") == "bsdf"
    assert plugin_tag("ply") == "shape"
    assert plugin_tag("envmap") == "emitter"
    assert plugin_tag("box") == "rfilter"
    with pytest.raises(ValueError, match="unknown Mitsuba plugin type 'nosuch'"):
        plugin_tag("nosuch")


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="expected a dict with type 'scene'"):
        scene_to_xml({"type": "shape"})
    with pytest.raises(TypeError, match=r"s\.weird: cannot write a value of type object"):
        scene_to_xml({"type": "scene", "s": {"type": "sphere", "weird": object()}})
    with pytest.raises(ValueError, match="without a string 'type'"):
        scene_to_xml({"type": "scene", "s": {"radius": 1.0}})


def test_write_scene_writes_assets_and_renders_like_the_dict(tmp_path, rng):
    env = rng.uniform(0.0, 2.0, size=(8, 16, 3)).astype(np.float32)
    scene = _scene(env={"type": "envmap", "filename": "textures/env.exr"})
    path = write_scene(GeneratedScene("test", 0, scene, {"textures/env.exr": env}), tmp_path / "out")
    assert path == tmp_path / "out" / "scene.xml"
    np.testing.assert_array_equal(read_exr(tmp_path / "out" / "textures" / "env.exr").rgb, env)
    a = render(scene, spp=2, seed=1, base_dir=tmp_path / "out").rgb
    b = render(path, spp=2, seed=1).rgb
    assert a.shape == (8, 16, 3) and a.mean() > 0.0
    np.testing.assert_array_equal(a, b)
    small = render(path, spp=1, params={"resx": "6", "resy": "4"}).rgb
    assert small.shape == (4, 6, 3)


def test_media_are_written_nested_and_by_reference_and_render_like_the_dict(tmp_path):
    fog = {"type": "homogeneous", "albedo": {"type": "rgb", "value": [0.9, 0.8, 0.7]},
           "sigma_t": 1.0, "scale": 0.2, "phase": {"type": "hg", "g": 0.5}}
    scene = _scene(integrator={"type": "volpath", "max_depth": 8, "rr_depth": 4})
    scene = {"type": "scene", "fog": fog, **{k: v for k, v in scene.items() if k != "type"}}
    scene["sensor"]["medium"] = {"type": "ref", "id": "fog"}
    inside = {"type": "homogeneous", "sigma_t": {"type": "rgb", "value": [1.0, 0.5, 0.2]},
              "scale": 8.0, "albedo": {"type": "rgb", "value": 0.95}, "sample_emitters": False}
    scene["ball"] = {"type": "sphere", "radius": 0.5, "bsdf": {"type": "dielectric"},
                     "interior": inside}
    root = ET.fromstring(scene_to_xml(scene))
    assert root.find("medium[@id='fog']").get("type") == "homogeneous"
    assert root.find("medium[@id='fog']/phase[@name='phase']").get("type") == "hg"
    assert root.find("sensor/ref").attrib == {"name": "medium", "id": "fog"}
    interior = root.find("shape[@id='ball']/medium[@name='interior']")
    assert interior.get("type") == "homogeneous"
    assert interior.find("rgb[@name='sigma_t']").get("value") == "1.0, 0.5, 0.2"
    assert interior.find("boolean").attrib == {"name": "sample_emitters", "value": "false"}
    path = write_scene(GeneratedScene("test", 0, scene), tmp_path)
    a = render(scene, spp=4, seed=2).rgb
    b = render(path, spp=4, seed=2).rgb
    assert a.mean() > 0.0
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-5)


def test_write_scene_writes_bytes_assets_verbatim(tmp_path):
    from scenes.meshes import heightfield

    data = heightfield(np.zeros((3, 3)))
    scene = {"type": "scene", "m": {"type": "ply", "filename": "meshes/m.ply"}}
    write_scene(GeneratedScene("test", 0, scene, {"meshes/m.ply": data}), tmp_path)
    assert (tmp_path / "meshes" / "m.ply").read_bytes() == data
    assert not list(tmp_path.rglob(".tmp-*"))
