"""One dataset job: generate scene ``index``, write its XML, render noisy images and reference.

Everything a job does depends only on the dataset config and the scene index: the family, the
scene seed, the split and every render seed are derived from (config seed, index), so a scene can
be re-rendered anywhere with identical results.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dataset_gen.config import DatasetConfig
from imaging.exr import write_exr
from imaging.metrics import RELMSE_EPS, tonemap
from imaging.naming import image_name, scene_name
from rendering.render import check_render_memory, load_scene, prepare, render_loaded

IMAGES_DIR = "images"
SCENES_DIR = "scenes"
SCENE_XML = "scene.xml"  # a generated scene's file in its folder SCENES_DIR/sceneNNNN
_AOV_RENDER_NAMES = {"alb": "albedo", "nrm": "sh_normal"}
SCENE_FILE_FAMILY = "scene-file"  # the family of a scene rendered from a user's file
_AOV_LAYER_NAMES = {"alb": "albedo", "nrm": "normal"}


@dataclass(frozen=True)
class SceneSeeds:
    """Everything random about scene ``index``: family, generator seed, split, render seeds."""

    family: str
    scene_seed: int
    split: str
    noisy: dict[int, int]
    reference_halves: tuple[int, int]


def scene_seeds(cfg: DatasetConfig, index: int) -> SceneSeeds:
    """Derive scene ``index``'s seeds from the dataset seed (deterministic, order-independent).

    Families rotate with the index so every family gets its share; the split is a seeded draw so
    that "val" covers all families.
    """
    words = np.random.SeedSequence([cfg.seed, index]).generate_state(4 + len(cfg.spp))
    family = cfg.families[index % len(cfg.families)] if cfg.families else SCENE_FILE_FAMILY
    split = "val" if (int(words[1]) / 2**32) < cfg.val_fraction else "train"
    noisy = {spp: int(words[4 + i]) for i, spp in enumerate(cfg.spp)}
    return SceneSeeds(family, int(words[0]), split, noisy, (int(words[2]), int(words[3])))


def filter_label(spec: dict[str, Any]) -> str:
    """A pixel filter as one string for an EXR header: ``box``, ``gaussian:stddev=0.5``."""
    params = ",".join(f"{k}={v:g}" for k, v in spec.items() if k != "type")
    return spec["type"] + (f":{params}" if params else "")


def reference_noise(half_a: np.ndarray, half_b: np.ndarray) -> dict[str, float]:
    """Estimated error of the mean of two independent half renders against the truth.

    Their difference has twice the variance of one half, so (a-b)/2 has the variance of the
    mean's error: its tonemapped MSE gives a PSNR ceiling, its relative MSE the reference relMSE.
    """
    mean = 0.5 * (half_a + half_b)
    err_tm = 0.5 * (tonemap(half_a) - tonemap(half_b))
    mse = float(np.mean(err_tm**2))
    err = 0.5 * (half_a.astype(np.float64) - half_b)
    return {
        "psnr_ceiling_db": float("inf") if mse == 0 else float(-10 * np.log10(mse)),
        "relmse": float(np.mean(err**2 / (mean.astype(np.float64) ** 2 + RELMSE_EPS))),
    }


def check_job_memory(cfg: DatasetConfig) -> None:
    """Raise :class:`imaging.errors.RenderError` when one job's renders do not fit in this
    machine's memory (:func:`rendering.render.check_render_memory`): a noisy render with its AOVs
    (and its variance with ``cfg.variance``), and the reference's second half beside the first and
    their mean."""
    width, height = cfg.res
    check_render_memory(width, height, tuple(_AOV_RENDER_NAMES[a] for a in cfg.aovs), cfg.variance)
    check_render_memory(width, height, held=("reference half", "reference mean"))


def _render(scene: Any, spp: int, seed: int, aovs: tuple[str, ...], halves: bool = False) -> Any:
    return render_loaded(scene, spp, seed, aovs=aovs, halves=halves)


def finite_variance(variance: np.ndarray) -> np.ndarray:
    """A render's variance estimate as stored: NaN (a NaN sample) -> 0, +Inf -> float32 max."""
    return np.nan_to_num(variance, nan=0.0, posinf=np.finfo(np.float32).max, neginf=0.0).astype(np.float32)


def scene_file(folder: Path, index: int) -> Path:
    """Where the dataset in ``folder`` keeps generated scene ``index``'s Mitsuba XML."""
    return folder / SCENES_DIR / scene_name(index) / SCENE_XML


def run_job(cfg: DatasetConfig, index: int, folder: Path) -> dict[str, Any]:
    """Render scene ``index`` into ``folder`` and return its manifest record.

    Files are written atomically; the caller appends the record only after this returns.
    """
    from scenes.registry import generate
    from scenes.xml_export import write_scene

    t0 = time.perf_counter()
    seeds = scene_seeds(cfg, index)
    if cfg.scene_files:
        xml = Path(cfg.scene_files[index])
    else:
        path = scene_file(folder, index)
        xml = write_scene(generate(seeds.family, seeds.scene_seed), path.parent, path.name)
    t_gen = time.perf_counter() - t0

    render_aovs = tuple(_AOV_RENDER_NAMES[a] for a in cfg.aovs)
    meta_base = {"scene": scene_name(index), "family": seeds.family, "mitsuba": cfg.mitsuba,
                 "variant": cfg.variant, "filter": filter_label(cfg.pixel_filter)}
    timings: dict[str, float] = {"generate_s": t_gen}
    nonfinite: dict[str, int] = {}
    variance_spp: list[int] = []
    images = folder / IMAGES_DIR
    pixel_filter = cfg.pixel_filter
    with_aovs = load_scene(prepare(xml, tuple(cfg.res), render_aovs, pixel_filter=pixel_filter)) if render_aovs else None
    plain = load_scene(prepare(xml, tuple(cfg.res), pixel_filter=pixel_filter))
    timings["load_s"] = time.perf_counter() - t0 - t_gen

    for spp in cfg.spp:
        res = _render(with_aovs or plain, spp, seeds.noisy[spp], render_aovs, halves=cfg.variance)
        meta = {**meta_base, "spp": spp, "seed": seeds.noisy[spp]}
        write_exr(images / image_name(index, spp, "hdr"), res.rgb, metadata=meta)
        if res.variance is not None:
            write_exr(images / image_name(index, spp, "var"), finite_variance(res.variance),
                      metadata={**meta, "layer": "variance of the mean (two halves)"})
            variance_spp.append(spp)
        for kind, render_name in zip(cfg.aovs, render_aovs):
            write_exr(images / image_name(index, spp, kind), res.aovs[render_name],
                      layers=None, metadata={**meta, "layer": _AOV_LAYER_NAMES[kind]})
        timings[f"render_{spp}spp_s"] = res.seconds
        nonfinite[str(spp)] = res.nonfinite

    half = cfg.ref_spp // 2
    halves = [_render(plain, half, s, ()) for s in seeds.reference_halves]
    ref = 0.5 * (halves[0].rgb + halves[1].rgb)
    noise = reference_noise(halves[0].rgb, halves[1].rgb)
    write_exr(images / image_name(index, None, "hdr"), ref,
              metadata={**meta_base, "spp": cfg.ref_spp, "seed": seeds.reference_halves[0]})
    timings["render_ref_s"] = halves[0].seconds + halves[1].seconds
    nonfinite["ref"] = halves[0].nonfinite + halves[1].nonfinite
    timings["total_s"] = time.perf_counter() - t0
    return {
        "index": index, "scene": scene_name(index), "family": seeds.family,
        "seed": seeds.scene_seed, "split": seeds.split, "spp": list(cfg.spp),
        "ref_spp": cfg.ref_spp, "aovs": list(cfg.aovs), "res": list(cfg.res),
        "variance_spp": variance_spp,
        "ref_noise": noise, "timings": timings, "nonfinite": nonfinite,
        "mitsuba": cfg.mitsuba, "variant": cfg.variant, "filter": cfg.filter,
        **({"scene_file": str(xml)} if cfg.scene_files else {}),
        "samples": int(cfg.res[0] * cfg.res[1] * (sum(cfg.spp) + cfg.ref_spp)),
    }
