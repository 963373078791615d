"""Scene families: determinism, structure, cost limits, finite non-black renders, XML round trip."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from imaging.render import render
from scenes.demo import DEMO_NAME, EXAMPLES_DIR, demo_scene
from scenes.registry import FAMILIES, generate
from scenes.spec import GeneratedScene, referenced_files
from scenes.xml_export import scene_to_xml, write_scene

RENDER_SEEDS = (1, 2, 3, 4)  # plus seed 0 in the round-trip test
STRUCTURE_SEEDS = range(12)


def _iter_plugins(node: dict):
    yield node
    for value in node.values():
        if isinstance(value, dict):
            yield from _iter_plugins(value)


def _ply_triangles(data: bytes) -> int:
    header = data[: data.index(b"end_header\n")].decode("ascii")
    line = next(ln for ln in header.splitlines() if ln.startswith("element face"))
    return int(line.split()[2])


def _same_assets(a: GeneratedScene, b: GeneratedScene) -> bool:
    if a.assets.keys() != b.assets.keys():
        return False
    for name, x in a.assets.items():
        y = b.assets[name]
        same = np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y
        if not same:
            return False
    return True


def test_there_are_at_least_eight_families():
    assert len(FAMILIES) >= 8


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_same_seed_same_scene_other_seed_other_scene(family):
    a, b, c = generate(family, 11), generate(family, 11), generate(family, 12)
    assert (a.family, a.seed) == (family, 11)
    assert scene_to_xml(a.scene) == scene_to_xml(b.scene)
    assert _same_assets(a, b)
    assert scene_to_xml(a.scene) != scene_to_xml(c.scene)


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_scene_structure_and_cost_limits(family):
    depths = set()
    for seed in STRUCTURE_SEEDS:
        gen = generate(family, seed)
        scene = gen.scene
        assert scene["type"] == "scene"
        assert scene["integrator"]["type"] == "path"
        depth = scene["integrator"]["max_depth"]
        assert 2 <= depth <= 12
        depths.add(depth)
        sensors = [v for v in scene.values() if isinstance(v, dict) and v["type"] == "perspective"]
        assert len(sensors) == 1
        film, sampler = sensors[0]["film"], sensors[0]["sampler"]
        assert (film["type"], film["width"], film["height"]) == ("hdrfilm", 128, 128)
        assert sampler["type"] == "independent"
        assert all(p["type"] != "aov" for p in _iter_plugins(scene))
        assert set(referenced_files(scene)) == set(gen.assets)
        for name, asset in gen.assets.items():
            if isinstance(asset, np.ndarray):
                limit = (256, 512) if "env" in name or "sky" in name else (256, 256)
                assert asset.shape[0] <= limit[0] and asset.shape[1] <= limit[1], name
                assert np.isfinite(asset).all() and asset.min() >= 0.0
            else:
                assert name.endswith(".ply") and _ply_triangles(asset) <= 20_000
    assert len(depths) > 1, "max_depth should vary with the seed"


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_family_renders_finite_and_not_black(family, tmp_path):
    for seed in RENDER_SEEDS:
        gen = generate(family, seed)
        folder = tmp_path / str(seed)
        write_scene(gen, folder)
        result = render(gen.scene, spp=4, seed=0, resolution=(32, 32), base_dir=folder)
        assert result.rgb.shape == (32, 32, 3)
        assert result.nonfinite == 0, f"{family}/{seed}: NaN/Inf pixels"
        assert np.isfinite(result.rgb).all()
        assert result.rgb.mean() > 0.0, f"{family}/{seed}: black image"


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_xml_export_renders_the_same_image(family, tmp_path):
    gen = generate(family, 0)
    xml_path = write_scene(gen, tmp_path)
    from_dict = render(gen.scene, spp=2, seed=3, resolution=(32, 32), base_dir=tmp_path).rgb
    from_xml = render(xml_path, spp=2, seed=3, resolution=(32, 32)).rgb
    assert from_dict.mean() > 0.0
    np.testing.assert_allclose(from_xml, from_dict, rtol=0, atol=1e-5)


def test_unknown_family_is_rejected_with_the_known_names():
    with pytest.raises(ValueError, match=r"unknown scene family 'nope' \(known: .*cornell_box"):
        generate("nope", 0)


@pytest.mark.parametrize("seed", [-1, 1.5, True, 2**63])
def test_bad_seed_is_rejected(seed):
    with pytest.raises(ValueError, match="seed must be an integer"):
        generate("cornell_box", seed)


def test_generated_scene_checks_its_assets():
    scene = {"type": "scene", "env": {"type": "envmap", "filename": "textures/env.exr"}}
    img = np.zeros((4, 8, 3), dtype=np.float32)
    GeneratedScene("x", 0, scene, {"textures/env.exr": img})
    with pytest.raises(ValueError, match="without an asset: textures/env.exr"):
        GeneratedScene("x", 0, scene, {})
    with pytest.raises(ValueError, match="not referenced by the scene: extra.exr"):
        GeneratedScene("x", 0, scene, {"textures/env.exr": img, "extra.exr": img})
    with pytest.raises(ValueError, match="must be a relative path"):
        GeneratedScene("x", 0, {"type": "scene"}, {"../evil.exr": img})
    with pytest.raises(ValueError, match="HxWx3 float32"):
        GeneratedScene("x", 0, scene, {"textures/env.exr": img.astype(np.float64)})


def test_heightfield_ply_header_and_size():
    gen = generate("terrain", 0)
    data = gen.assets["meshes/terrain.ply"]
    header, body = data.split(b"end_header\n", 1)
    assert b"format binary_little_endian 1.0" in header
    faces = _ply_triangles(data)
    vertices = int(header.decode().split("element vertex ")[1].split()[0])
    assert len(body) == vertices * 8 * 4 + faces * (1 + 3 * 4)
    assert struct.unpack_from("<B", body, vertices * 32)[0] == 3


def test_demo_scene_renders_and_is_up_to_date():
    path = EXAMPLES_DIR / DEMO_NAME
    assert path.read_text() == scene_to_xml(demo_scene().scene), \
        "scenes/examples/demo.xml is stale: run python -m scenes.demo"
    for name in demo_scene().assets:
        assert (EXAMPLES_DIR / name).is_file()
    result = render(Path("scenes/examples/demo.xml").resolve(), spp=4, resolution=(32, 32))
    assert result.nonfinite == 0 and np.isfinite(result.rgb).all()
    assert result.rgb.mean() > 0.0
