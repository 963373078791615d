"""What each shipped recipe's training took, from the one record of it: each stage's own log.

A recipe's final stage logged to ``experiments/training/NAME/log.jsonl``, an earlier stage to
``experiments/training/NAME/stage-STAGE/log.jsonl``; a stage that another recipe trained first (the
same :meth:`training.recipe.Recipe.stage_key`, copied by ``train --recipe``) is read from that
recipe's folder. From each log: the steps run, the best held-out step and its PSNR, and the CPU
minutes to that step and to the stage's end.

Two totals, both from these logs, mean different things:

* **to the shipped file**: the CPU time of every stage along the warm starts that lead to the
  shipped checkpoint, each up to its best step (a stage starts from the best of the one before):
  what the weights cost. A checkpoint's own card records the same figure (``meta.hours``, summed
  as the stages ran; ``tests/test_training_records.py`` checks the two agree);
* **the whole run**: every stage to its last step, which is what ``train --recipe NAME`` takes.

The recipes' ``[stages.measured]`` copy the per-stage figures (the tests check they agree) and the
tables of ``docs/training.md`` are drawn from here (``benchmarks/readme_tables.py``).
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from training.recipe import Recipe, load_recipe, recipe_names

ROOT = Path(__file__).resolve().parents[1]
TRAINING = ROOT / "experiments" / "training"


@dataclass(frozen=True)
class StageRecord:
    """One stage's run as its log records it: ``steps`` run, ``best_step`` (highest held-out PSNR,
    ``best_psnr`` dB), ``cpu_min_to_best`` and ``cpu_min`` (to its last step), and the ``log`` read."""

    steps: int
    best_step: int
    best_psnr: float
    cpu_min_to_best: float
    cpu_min: float
    log: Path


def read_stage_log(path: Path) -> StageRecord:
    """The :class:`StageRecord` of one run's ``log.jsonl``."""
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    cpu = {r["step"]: r["cpu_s"] for r in rows if r["type"] == "train" and r.get("cpu_s") is not None}
    best = max((r for r in rows if r["type"] == "val"), key=lambda r: r["psnr"])
    last = max(cpu)
    return StageRecord(last, best["step"], float(best["psnr"]), cpu[best["step"]] / 60, cpu[last] / 60, path)


def stage_log(recipe: Recipe, stage: str, root: Path = ROOT) -> Path | None:
    """The log of ``recipe``'s ``stage`` (module docstring), or None where none was kept."""
    def own(owner: Recipe, name: str) -> Path:
        kept = "log.jsonl" if name == owner.final.name else f"stage-{name}/log.jsonl"
        return root / "experiments" / "training" / owner.name / kept

    if own(recipe, stage).is_file():
        return own(recipe, stage)
    key = recipe.stage_key(stage)
    others = (load_recipe(name) for name in recipe_names() if name != recipe.name)
    return next((own(other, s.name) for other in others for s in other.stages
                 if other.stage_key(s.name) == key and own(other, s.name).is_file()), None)


def lineage(recipe: Recipe) -> list[str]:
    """The stages whose best checkpoints lead to the final one, first to last."""
    chain = [recipe.final.name]
    while recipe.stage(chain[0]).init_from:
        chain.insert(0, recipe.stage(chain[0]).init_from)
    return chain


@dataclass(frozen=True)
class RecipeRecord:
    """A recipe's stages in order, each with its :class:`StageRecord` (None: no log kept), and the
    two totals in CPU-hours (None where a stage they need has no log)."""

    recipe: Recipe
    stages: dict[str, StageRecord | None]
    hours_to_file: float | None
    hours_whole_run: float | None


def recipe_record(recipe: Recipe, root: Path = ROOT) -> RecipeRecord:
    """The :class:`RecipeRecord` of ``recipe`` from the logs under ``root``."""
    stages = {s.name: (read_stage_log(p) if (p := stage_log(recipe, s.name, root)) else None) for s in recipe.stages}

    def total(minutes: list[float | None]) -> float | None:
        return None if any(m is None for m in minutes) else sum(minutes) / 60  # type: ignore[arg-type]

    to_file = total([r.cpu_min_to_best if (r := stages[s]) else None for s in lineage(recipe)])
    whole = total([r.cpu_min if r else None for r in stages.values()])
    return RecipeRecord(recipe, stages, to_file, whole)


def measured_disagreements(record: RecipeRecord) -> list[str]:
    """``STAGE: FIELD recipe X, log Y`` for every figure of the recipe's ``[stages.measured]`` that
    its stage's log does not give (to the figure's last digit)."""
    out = []
    for stage in record.recipe.stages:
        run = record.stages[stage.name]
        if run is None:
            continue
        from_log: dict[str, Any] = {"best_step": run.best_step, "cpu_minutes_to_best": round(run.cpu_min_to_best, 1),
                                    "cpu_minutes": round(run.cpu_min, 1), "held_out_psnr": round(run.best_psnr, 2),
                                    "cpu_hours": round(run.cpu_min_to_best / 60, 2)}
        for key, value in stage.measured.items():
            if key in from_log and value != from_log[key]:
                out.append(f"{record.recipe.name} {stage.name}: {key} recipe {value}, log {from_log[key]}")
    return out
