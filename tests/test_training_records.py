"""benchmarks.training_records: the shipped recipes' training figures, from each stage's log,
agree with the checkpoints' cards, the recipes' [stages.measured] and docs/training.md."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from benchmarks.readme_tables import MARKERS
from benchmarks.training_records import lineage, read_stage_log, recipe_record
from model.registry import registry
from training.recipe import load_recipe, parse_recipe

ROOT = Path(__file__).resolve().parents[1]


def test_every_shipped_files_hours_are_its_stages_cpu_to_their_best_steps() -> None:
    """A card's CPU-hours (its file's own record, summed as the stages ran) equal the logs' CPU
    minutes of the stages that lead to it, each to its best step, to the card's 0.01 h."""
    for name, card in registry().checkpoints.items():
        record = recipe_record(load_recipe(card.recipe))
        assert record.hours_to_file == pytest.approx(card.training["hours"]["cpu"], abs=0.006), name
        assert record.hours_whole_run >= record.hours_to_file


def test_the_recipes_measured_figures_are_their_logs() -> None:
    """Every stage with a log records in its recipe the best step, the held-out PSNR and the CPU
    minutes to the best step and to the end, as its log gives them."""
    for name in registry().checkpoints:
        record = recipe_record(load_recipe(name))
        for stage in record.recipe.stages:
            run, measured = record.stages[stage.name], stage.measured
            assert run is not None, (name, stage.name)
            assert (measured["best_step"], measured["held_out_psnr"]) == (run.best_step, round(run.best_psnr, 2))
            assert measured["cpu_minutes_to_best"] == round(run.cpu_min_to_best, 1), (name, stage.name)
            assert measured["cpu_minutes"] == round(run.cpu_min, 1), (name, stage.name)


def test_a_stage_trained_by_another_recipe_is_read_from_its_log_and_the_totals_follow_the_warm_starts(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two recipes sharing a first stage: the second's is read from the first's folder; to the file
    is each stage of the lineage to its best, the whole run every stage to its end."""
    base = ('name = "{name}"\n[datasets.d]\nfamilies = ["cornell_box"]\nscenes = 2\nres = 16\nspp = [4]\nref_spp = 16\n'
            '[[stages]]\nname = "{first}"\ndata = ["d"]\npreset = "flat-s"\nsteps = 4\n'
            '[[stages]]\nname = "main"\ndata = ["d"]\ninit_from = "{first}"\npreset = "flat-s"\nsteps = {steps}\n')
    a = parse_recipe(base.format(name="a", first="pre", steps=6), tmp_path / "a.toml")
    b = parse_recipe(base.format(name="b", first="flat", steps=8), tmp_path / "b.toml")

    def log(path: Path, cpu_per_step: float, best: int, steps: int) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        rows = [{"type": "train", "step": s, "cpu_s": 60 * cpu_per_step * s} for s in range(1, steps + 1)]
        rows += [{"type": "val", "step": s, "psnr": 30.0 - abs(s - best)} for s in range(2, steps + 1, 2)]
        path.write_text("".join(json.dumps(r) + "\n" for r in rows))

    training = tmp_path / "experiments" / "training"
    log(training / "a" / "stage-pre" / "log.jsonl", 1.0, 2, 4)
    log(training / "a" / "log.jsonl", 2.0, 4, 6)
    log(training / "b" / "log.jsonl", 3.0, 8, 8)
    import benchmarks.training_records as records

    monkeypatch.setattr(records, "recipe_names", lambda: ["a", "b"])
    monkeypatch.setattr(records, "load_recipe", {"a": a, "b": b}.__getitem__)
    got = recipe_record(b, tmp_path)
    assert lineage(b) == ["flat", "main"]
    assert got.stages["flat"] == read_stage_log(training / "a" / "stage-pre" / "log.jsonl")
    assert got.hours_to_file == pytest.approx((2 * 1.0 + 8 * 3.0) / 60)
    assert got.hours_whole_run == pytest.approx((4 * 1.0 + 8 * 3.0) / 60)


def test_the_recipes_section_of_training_md_states_training_figures_only_in_its_generated_tables() -> None:
    text = (ROOT / "docs" / "training.md").read_text()
    section = text[text.index("## Recipes"):]
    section = MARKERS.sub("", section[:section.index("\n## ", 1)])
    assert re.findall(r"\d[\d.,]*\s*(?:CPU-|GPU-)?(?:hours|min\b|minutes)", section) == []
    assert "<!-- table:recipe_runs -->" in text
