"""Normals in the sensor's frame (rendering.camera): analytic rotations of known cameras, and
Mitsuba's own normals of a rendered sphere seen from an oblique camera. Tolerance 1e-6 (float32
matrices), 0.05 for the rendered normals' averages."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from imaging.errors import SceneError
from rendering.camera import rotate_normals, scene_file_rotation, sensor_rotation, world_to_camera
from rendering.render import load_scene, prepare, render_loaded


def look_at(origin: list[float], target: list[float], up: list[float]) -> np.ndarray:
    """Mitsuba's ``look_at`` written out: columns left = up x dir, up' = dir x left, dir, origin."""
    o, t = np.array(origin, float), np.array(target, float)
    d = (t - o) / np.linalg.norm(t - o)
    left = np.cross(up, d)
    left /= np.linalg.norm(left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, np.cross(d, left), d, o
    return m


def test_a_camera_on_the_x_axis_sees_its_facing_normal_along_minus_z() -> None:
    """From (5, 0, 0) looking at the origin (up +y): the camera's left is world +z, so world normals
    +x (facing it) -> (0, 0, -1), +z -> (1, 0, 0) (the image's left), +y -> (0, 1, 0)."""
    r = world_to_camera(look_at([5, 0, 0], [0, 0, 0], [0, 1, 0]))
    normals = np.array([[[1, 0, 0], [0, 0, 1], [0, 1, 0]]], np.float32)
    np.testing.assert_allclose(rotate_normals(normals, r), [[[0, 0, -1], [1, 0, 0], [0, 1, 0]]], atol=1e-6)


def test_the_rotation_ignores_translation_and_scale_and_refuses_a_singular_matrix() -> None:
    m = look_at([1, 2, 3], [0, 0.5, -1], [0, 1, 0])
    r = world_to_camera(m)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    scaled = m.copy()
    scaled[:3, :3] *= 2.5
    scaled[:3, 3] += 7
    np.testing.assert_allclose(world_to_camera(scaled), r, atol=1e-12)
    direction = np.array([-1, -1.5, -4]) / np.linalg.norm([-1, -1.5, -4])
    np.testing.assert_allclose(r @ direction, [0, 0, 1], atol=1e-12)  # the viewing direction is +z
    with pytest.raises(SceneError, match="singular"):
        world_to_camera(np.diag([1.0, 0.0, 1.0, 1.0]))


def test_rotated_normals_keep_their_length_and_lose_non_finite_values(rng: np.random.Generator) -> None:
    normals = rng.normal(size=(5, 7, 3)).astype(np.float32)
    normals[0, 0] = [np.nan, np.inf, 1.0]
    r = world_to_camera(look_at([0.3, -2, 1], [0, 0, 0], [0, 0, 1]))
    out = rotate_normals(normals, r)
    assert out.dtype == np.float32 and np.isfinite(out).all()
    np.testing.assert_allclose(np.linalg.norm(out[1:], axis=2), np.linalg.norm(normals[1:], axis=2), rtol=1e-5)
    np.testing.assert_allclose(out[0, 0], r @ [0, 0, 1.0], atol=1e-6)


def _sphere_scene(origin: list[float]) -> str:
    return f"""<scene version="3.0.0">
    <integrator type="path"/>
    <sensor type="perspective">
        <float name="fov" value="30"/>
        <transform name="to_world"><lookat origin="{','.join(map(str, origin))}" target="0,0,0" up="0,1,0"/></transform>
        <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="24"/></film>
    </sensor>
    <shape type="sphere"><float name="radius" value="1"/><bsdf type="diffuse"/></shape>
    <emitter type="constant"/>
</scene>"""


def test_mitsuba_s_sensor_and_its_rendered_normals_in_the_camera_frame(mi: Any, tmp_path: Path) -> None:
    """A unit sphere filling the middle of an oblique camera's view: in the camera's frame its
    normals face the camera (z < 0 on average), point left (+x) on the image's left half and up
    (+y) on its top half; the sensor's rotation is the written-out look_at's, from a loaded scene,
    a render and the scene's file."""
    origin = [3.0, 2.0, 4.0]
    path = tmp_path / "sphere.xml"
    path.write_text(_sphere_scene(origin))
    want = world_to_camera(look_at(origin, [0, 0, 0], [0, 1, 0]))
    scene = load_scene(prepare(path, (24, 24), ("sh_normal",)))
    np.testing.assert_allclose(sensor_rotation(scene), want, atol=1e-6)
    np.testing.assert_allclose(scene_file_rotation(path), want, atol=1e-6)
    render = render_loaded(scene, 4, 0, ("sh_normal",))
    np.testing.assert_allclose(render.to_camera, want, atol=1e-6)
    n = rotate_normals(render.aovs["sh_normal"], render.to_camera)
    on = np.linalg.norm(n, axis=2) > 0.5  # pixels on the sphere
    middle = slice(8, 16)
    assert n[..., 2][on].mean() < -0.5
    assert n[middle, :10, 0][on[middle, :10]].mean() > 0.2 and n[middle, 14:, 0][on[middle, 14:]].mean() < -0.2
    assert n[:10, middle, 1][on[:10, middle]].mean() > 0.2 and n[14:, middle, 1][on[14:, middle]].mean() < -0.2
    with pytest.raises(SceneError):
        scene_file_rotation(tmp_path / "missing.xml")
