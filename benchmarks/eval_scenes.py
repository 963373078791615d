"""The evaluation scenes of ``../shared/eval-scenes`` (public Mitsuba scenes the model never saw),
listed once for every benchmark: each folder holds ``scene.xml``, ``reference.exr`` (2048 spp, box
filter) and ``reference.json`` (how it was rendered, its noise ceiling, figures at seed 7)."""
from __future__ import annotations

import json
import os
import shlex
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from imaging.atomic_io import write_json_atomic, write_text_atomic
from imaging.errors import DenoiserError
from imaging.exr import read_exr
from rendering.render import RenderResult
from pipeline.evaluation import RenderSettings, render_input

ROOT = Path(__file__).resolve().parents[1]
EVAL_DIR = ROOT.parent / "shared" / "eval-scenes"
RESULTS = ROOT / "benchmarks" / "results"
SEED = 7  # the seed of the noisy figures recorded in every reference.json
CEILING_DB = 40.0  # a reference whose own PSNR ceiling is below this cannot score a denoiser


@dataclass(frozen=True)
class EvalScene:
    """One evaluation scene folder."""

    folder: Path

    @property
    def name(self) -> str:
        return self.folder.name

    @cached_property
    def info(self) -> dict[str, Any]:
        """``reference.json``: reference spp, ``reference_psnr_ceiling_db``, ``shape`` [H, W, 3]..."""
        return json.loads((self.folder / "reference.json").read_text())

    @property
    def ceiling_db(self) -> float:
        return float(self.info["reference_psnr_ceiling_db"])

    @property
    def resolution(self) -> tuple[int, int]:
        """The reference's [W, H]."""
        h, w = self.info["shape"][:2]
        return int(w), int(h)

    def reference(self) -> np.ndarray:
        """HxWx3 float32 linear radiance of ``reference.exr``."""
        return read_exr(self.folder / "reference.exr").rgb

    def settings(self, seed: int = SEED, resolution: tuple[int, int] | None = None,
                 noise_guard: bool = True) -> RenderSettings:
        """How ``render-and-denoise`` renders this scene for its reference (its size unless
        ``resolution`` is given, ``seed``)."""
        return RenderSettings(str(self.folder / "scene.xml"), resolution or self.resolution, seed,
                              noise_guard=noise_guard, reference=str(self.folder / "reference.exr"))


def eval_scenes(names: Sequence[str] | None = None, eval_dir: Path = EVAL_DIR) -> list[EvalScene]:
    """The scene folders of ``eval_dir`` (``scene.xml`` and ``reference.exr`` present), by name;
    ``names``: only those. Raises :class:`DenoiserError` for a missing folder or unknown names."""
    if not eval_dir.is_dir():
        raise DenoiserError(f"{eval_dir}: evaluation scenes not found")
    scenes = [EvalScene(d) for d in sorted(eval_dir.iterdir())
              if (d / "scene.xml").is_file() and (d / "reference.exr").is_file()]
    if names:
        unknown = sorted(set(names) - {s.name for s in scenes})
        if unknown:
            raise DenoiserError(f"unknown scene(s) in {eval_dir}: {', '.join(unknown)}")
        scenes = [s for s in scenes if s.name in names]
    return scenes


def scored_renders(names: Sequence[str] | None, spps: Sequence[int], eval_dir: Path = EVAL_DIR,
                   halves: bool = True) -> Iterator[tuple[int, RenderResult, np.ndarray]]:
    """``(spp, render, reference)`` for every scored scene (ceiling >= :data:`CEILING_DB`) of
    ``names`` and every spp: rendered as ``render-and-denoise`` does (two halves, seed
    :data:`SEED`; ``halves`` False: in one piece, as with ``--no-noise-guard``), each scene loaded
    once, a progress bar over the scenes."""
    from tqdm import tqdm

    for scene in tqdm(eval_scenes(names, eval_dir), desc="eval scenes", unit="scene"):
        if scene.ceiling_db < CEILING_DB:
            continue
        ref = scene.reference()
        case = scene.settings(resolution=(ref.shape[1], ref.shape[0]), noise_guard=halves)
        loaded = case.load()
        for spp in spps:
            yield spp, render_input(loaded, spp, case), ref


def run_record(module: str, argv: Sequence[str]) -> dict[str, Any]:
    """What a result file records about its run: the command (``python -m MODULE ARGV``), the date
    and the machine's cores and 1-minute load average; :func:`finish_record` adds the load at the end."""
    return {"command": shlex.join(["python", "-m", module, *argv]), "date": time.strftime("%Y-%m-%d %H:%M"),
            "machine": {"cores": len(os.sched_getaffinity(0)), "load_before": os.getloadavg()[0]}}


def save_result(out: Path, name: str, result: dict[str, Any], markdown: str) -> Path:
    """Write ``OUT/NAME.json`` (the result) and ``OUT/NAME.md`` (its table) atomically, making
    ``out`` if needed; returns the JSON's path."""
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / f"{name}.json", result)
    write_text_atomic(out / f"{name}.md", markdown)
    return out / f"{name}.json"


def finish_record(record: dict[str, Any], started: float) -> dict[str, Any]:
    """``record`` with the wall time since ``started`` (``time.perf_counter()``) and the load now."""
    record["wall_s"] = time.perf_counter() - started
    record["machine"]["load_after"] = os.getloadavg()[0]
    return record
