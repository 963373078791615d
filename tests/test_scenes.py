"""Scene families: determinism, structure, cost limits, finite non-black renders, XML round trip."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from rendering.render import load_scene, prepare, render
from scenes.demo import DEMO_NAME, EXAMPLES_DIR, demo_scene
from scenes.families import media
from scenes.registry import DEFAULT_FAMILIES, FAMILIES, generate
from scenes.spec import GeneratedScene, referenced_files
from scenes.xml_export import scene_to_xml, write_scene

RENDER_SEEDS = (1, 2, 3, 4)  # plus seed 0 in the round-trip test
STRUCTURE_SEEDS = range(12)
# Integrator type and max_depth bounds per family (default: unidirectional path, depth 2..12).
INTEGRATORS = {"media": ("volpath", 16, 64)}
MEDIA_SEEDS = range(24)  # every media sub-kind occurs among these


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
        kind, lo, hi = INTEGRATORS.get(family, ("path", 2, 12))
        assert scene["integrator"]["type"] == kind
        depth = scene["integrator"]["max_depth"]
        assert lo <= depth <= hi
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


def test_default_families_are_the_original_nine_in_order():
    # generate-dataset's default; datasets made with it must stay reproducible as families are added
    assert DEFAULT_FAMILIES == ("cornell_box", "material_preview", "indoor_room", "env_objects",
                                "caustics", "small_emitters", "textured_surfaces", "terrain",
                                "veach_mis")
    assert set(DEFAULT_FAMILIES) < set(FAMILIES) and "media" not in DEFAULT_FAMILIES
    from dataset_gen.cli import build_parser

    assert build_parser().parse_args(["--scenes", "1", "--out", "x"]).families == DEFAULT_FAMILIES


def _media_kind_from_structure(scene: dict) -> str:
    """Which media sub-kind a scene dict is, read from where its media sit."""
    if "medium" in scene["sensor"]:
        return "fog_room"
    filled = [v for v in scene.values() if isinstance(v, dict) and "interior" in v]
    if any(v["bsdf"]["type"] == "null" for v in filled):
        return "smoke_box"
    assert filled and all(v["bsdf"]["type"] in ("dielectric", "roughdielectric") for v in filled)
    albedos = [v["interior"]["albedo"]["value"] for v in filled]
    if all(min(a) >= 0.7 for a in albedos):
        return "subsurface"
    assert all(max(a) <= 0.3 for a in albedos)
    return "absorbing"


def test_media_scenes_use_volpath_and_hold_valid_media():
    kinds = set()
    for seed in MEDIA_SEEDS:
        scene = generate("media", seed).scene
        integrator = scene["integrator"]
        assert integrator["type"] == "volpath"
        assert 16 <= integrator["max_depth"] <= 64 and 1 <= integrator["rr_depth"] <= 10
        found = [p for p in _iter_plugins(scene) if p.get("type") == "homogeneous"]
        assert found, f"media/{seed}: no medium"
        for m in found:
            albedo, sigma_t = m["albedo"]["value"], m["sigma_t"]
            sigma_t = sigma_t["value"] if isinstance(sigma_t, dict) else [sigma_t]
            assert all(0.0 <= a <= 1.0 for a in albedo)
            assert all(0.0 < s <= 1.0 for s in sigma_t), "RGB extinction must lie in (0, 1]"
            assert 0.0 < m["scale"] < np.inf
        kind = _media_kind_from_structure(scene)
        assert kind == media.kind_of(seed)
        kinds.add(kind)
    assert kinds == set(media.KINDS)


def _object_size(shape: dict) -> float:
    """Largest extent of a filled object: sphere, box (cube scaled by half extents) or blob
    mesh (1 unit across before its uniform scale)."""
    if shape["type"] == "sphere":
        return 2.0 * shape["radius"]
    norms = np.linalg.norm(np.array(shape["to_world"], dtype=np.float64)[:3, :3], axis=0)
    return float(2.0 * norms.max() if shape["type"] == "cube" else norms.max())


def _extinction(medium: dict) -> np.ndarray:
    sigma_t = medium["sigma_t"]
    values = sigma_t["value"] if isinstance(sigma_t, dict) else [sigma_t] * 3
    return np.array(values, dtype=np.float64) * medium["scale"]


def test_media_densities_fit_the_objects():
    """A subsurface medium's mean free path is 0.5%..20% of its object's size (each channel);
    an absorbing one is 0.3..3 optical depths across its object (the densest channel)."""
    checked = set()
    for seed in MEDIA_SEEDS:
        kind = media.kind_of(seed)
        if kind not in ("subsurface", "absorbing"):
            continue
        scene = generate("media", seed).scene
        for shape in (v for v in scene.values() if isinstance(v, dict) and "interior" in v):
            size, sigma_t = _object_size(shape), _extinction(shape["interior"])
            if kind == "subsurface":
                mfp = 1.0 / sigma_t / size
                assert 0.005 * (1 - 1e-9) <= mfp.min() and mfp.max() <= 0.2 * (1 + 1e-9), (seed, mfp)
            else:
                assert 0.3 * (1 - 1e-9) <= sigma_t.max() * size <= 3.0 * (1 + 1e-9), seed
            checked.add((kind, shape["type"]))
    assert {k for k, _ in checked} == {"subsurface", "absorbing"}
    assert {t for _, t in checked} == {"sphere", "cube", "ply"}


def test_media_load_from_xml_attached_where_they_belong(mi, tmp_path):
    """Mitsuba, loading the exported XML, finds each medium on the shape the generator put it
    in, with the same coefficients, and the fog of a fog room shared by camera and volume."""
    for seed in MEDIA_SEEDS:
        gen = generate("media", seed)
        scene = load_scene(prepare(write_scene(gen, tmp_path / str(seed))))
        expected = {k: v["interior"] for k, v in gen.scene.items()
                    if isinstance(v, dict) and "interior" in v}
        filled = {s.id(): s for s in scene.shapes() if s.interior_medium() is not None}
        assert set(filled) == set(expected) and all(s.is_medium_transition() for s in filled.values())
        sensor_medium = scene.sensors()[0].get_medium()
        assert (sensor_medium is not None) == (media.kind_of(seed) == "fog_room")
        for key, shape in filled.items():
            want = expected[key]
            if want["type"] == "ref":
                assert shape.interior_medium() == sensor_medium
                want = gen.scene[want["id"]]
            params = mi.traverse(shape.interior_medium())
            albedo = np.ravel(params["albedo.value.value"])
            sigma_t = np.ravel(params["sigma_t.value.value"]) * params["scale"]
            np.testing.assert_allclose(albedo, want["albedo"]["value"], rtol=1e-6)
            np.testing.assert_allclose(np.broadcast_to(sigma_t, (3,)), _extinction(want), rtol=1e-5)


def test_media_blob_mesh_is_closed_and_outward(rng):
    data = media.blob_mesh(rng)
    header, body = data.split(b"end_header\n", 1)
    n_v = int(header.decode().split("element vertex ")[1].split()[0])
    n_f = _ply_triangles(data)
    vertices = np.frombuffer(body[: n_v * 32], dtype="<f4").reshape(n_v, 8)
    faces = np.frombuffer(body[n_v * 32:], dtype=np.dtype([("n", "u1"), ("i", "<i4", (3,))]))["i"]
    assert len(faces) == n_f <= 20_000
    p = vertices[:, :3].astype(np.float64)
    assert p[:, 1].min() == pytest.approx(0.0, abs=1e-6)
    assert np.ptp(p, axis=0).max() == pytest.approx(1.0, abs=1e-6)
    # closed: every edge is shared by exactly two triangles, in opposite directions
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    assert len({tuple(e) for e in edges}) == len(edges)
    assert {tuple(e) for e in edges} == {tuple(e) for e in edges[:, ::-1]}
    # outward: the signed volume is positive, and normals point away from the centroid
    a, b, c = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
    assert np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0 > 0.0
    normals = vertices[:, 3:6]
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    assert (np.einsum("ij,ij->i", normals, p - p.mean(axis=0)) > 0).mean() > 0.95


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
