"""A tiny synthetic dataset in the ``dataset_gen`` layout, for tests, smoke runs and benchmarks.

References are smooth procedural HDR images (gradients, discs, a bright emitter patch, values
0..~50); a noisy image at ``s`` spp is the reference times ``1 + N(0, 1) / sqrt(s)`` (clamped >= 0)
plus rare fireflies, so noise falls with spp like a Monte Carlo render. Albedo is the pattern's
colour in [0, 1], the normal a fixed tilted XYZ field in [-1, 1]. Deterministic in ``seed``.
With ``cameras`` each scene also gets a Mitsuba scene file where ``generate-dataset`` keeps a
generated scene's (a sphere seen from :func:`camera_origin`), so that its camera's frame is known.
"""
from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dataset_gen.jobs import scene_file
from imaging.exr import write_exr
from imaging.naming import image_name, scene_name


def _reference(rng: np.random.Generator, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    x, y = x / max(width - 1, 1), y / max(height - 1, 1)
    albedo = np.stack([0.2 + 0.6 * x, 0.3 + 0.5 * y, np.full_like(x, 0.5)], axis=-1)
    light = 0.5 + 1.5 * (1 - y)[..., None]
    for _ in range(3):
        cx, cy, r = rng.random(), rng.random(), 0.1 + 0.2 * rng.random()
        inside = ((x - cx) ** 2 + (y - cy) ** 2 < r * r)[..., None]
        albedo = np.where(inside, rng.random(3).astype(np.float32), albedo)
    radiance = albedo * light
    ex, ey = int(rng.integers(0, max(width - 4, 1))), int(rng.integers(0, max(height - 4, 1)))
    radiance[ey:ey + 4, ex:ex + 4] = 50.0
    return radiance.astype(np.float32), albedo.astype(np.float32)


def camera_origin(index: int) -> tuple[float, float, float]:
    """Where the sensor of synthetic scene ``index``'s file stands (it looks at the origin, up +y)."""
    return (3.0 + index, 1.0, 4.0 - 2.0 * index)


def _scene_xml(index: int) -> str:
    origin = ",".join(f"{v:g}" for v in camera_origin(index))
    return ('<scene version="3.0.0">\n    <integrator type="path"/>\n    <sensor type="perspective">\n'
            f'        <transform name="to_world"><lookat origin="{origin}" target="0,0,0" up="0,1,0"/></transform>\n'
            '    </sensor>\n'
            '    <shape type="sphere"/>\n    <emitter type="constant"/>\n</scene>\n')


def _noisy(rng: np.random.Generator, ref: np.ndarray, spp: int) -> np.ndarray:
    noisy = ref * (1.0 + rng.standard_normal(ref.shape).astype(np.float32) / np.sqrt(spp))
    fireflies = rng.random(ref.shape[:2]) < 0.01 / spp
    noisy[fireflies] += 20.0
    return np.clip(noisy, 0.0, None).astype(np.float32)


def write_synthetic_dataset(root: str | Path, scenes: int = 2, res: tuple[int, int] = (32, 32),
                            spp: Sequence[int] = (4, 16), val_scenes: Sequence[int] = (1,),
                            aovs: bool = False, seed: int = 0, variance: bool = False,
                            cameras: bool = False) -> Path:
    """Write ``scenes`` scenes (indices 0..scenes-1; those in ``val_scenes`` in split "val") of
    ``res`` = (W, H) pixels at each of ``spp`` plus a reference to ``root``; returns ``root``.
    ``variance``: also a variance image per noisy image (``ref^2 / spp``, the noise's variance),
    as ``generate-dataset --variance`` writes; ``cameras``: a scene file per scene (module docstring)."""
    root = Path(root)
    (root / "images").mkdir(parents=True, exist_ok=True)
    aov_names = ["alb", "nrm"] if aovs else []
    config = {"version": 1, "res": list(res), "spp": list(spp), "ref_spp": 4096, "aovs": aov_names,
              "filter": "box", "synthetic": True, "variance": variance}
    (root / "dataset.json").write_text(json.dumps(config) + "\n", encoding="utf-8")
    lines = []
    for index in range(scenes):
        rng = np.random.default_rng([seed, index])
        ref, albedo = _reference(rng, *res)
        write_exr(root / "images" / image_name(index, None, "hdr"), ref)
        normal = np.broadcast_to(np.array([0.0, 0.6, 0.8], np.float32), ref.shape).copy()
        for s in spp:
            write_exr(root / "images" / image_name(index, s, "hdr"), _noisy(rng, ref, s))
            if variance:
                write_exr(root / "images" / image_name(index, s, "var"), ref * ref / np.float32(s))
            if aovs:
                write_exr(root / "images" / image_name(index, s, "alb"), albedo)
                write_exr(root / "images" / image_name(index, s, "nrm"), normal)
        if cameras:
            path = scene_file(root, index)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(_scene_xml(index), encoding="utf-8")
        split = "val" if index in val_scenes else "train"
        lines.append(json.dumps({"index": index, "scene": scene_name(index), "family": "synthetic",
                                 "seed": seed, "split": split, "spp": list(spp), "aovs": aov_names,
                                 "variance_spp": list(spp) if variance else []}))
    (root / "manifest.jsonl").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return root
