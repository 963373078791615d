"""training.provenance.recipe_meta: the card record of a file a recipe's stage made before runs
wrote one, from the file's own record of its run; refused where the file is not that stage's."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from imaging.errors import ConfigError
from model.checkpoint import checkpoint_meta, read_checkpoint
from model.registry import registry
from training.provenance import recipe_meta
from training.recipe import load_recipe, parse_recipe

ONE_STAGE = """
name = "one"
[datasets.d]
families = ["cornell_box"]
scenes = 2
res = 16
spp = [4]
ref_spp = 16
[[stages]]
name = "main"
data = ["d"]
preset = "flat-s"
steps = 10
lr = 5e-4
"""


def _header(recipe_text: str, tmp_path: Path, **changes: object) -> tuple[dict, object]:
    recipe = parse_recipe(recipe_text, tmp_path / "one.toml")
    config = json.loads(json.dumps(dataclasses.asdict(recipe.final.train_config("runs/x", ["data/a", "data/b"], None,
                                                                                   {"threads": 2}))))
    config.update(changes)
    return {"train_config": config, "extra": {"cpu_s": 5400.0}, "data_config": {"filter": "box"}}, recipe


def test_a_from_scratch_files_record_is_its_own_run_under_its_recipe(tmp_path: Path) -> None:
    header, recipe = _header(ONE_STAGE, tmp_path, cpu_budget_s=7200.0)  # run control may differ
    assert recipe_meta(header, recipe, "CPU A, 1 thread") == {
        "hours": {"cpu": 1.5, "gpu": 0.0}, "hardware": ["CPU A, 1 thread"], "pixel_filter": {"type": "box"},
        "recipe": {"name": "one", "sha256": recipe.sha256, "stage": "main"}}


def test_a_file_trained_otherwise_or_warm_started_is_refused(tmp_path: Path) -> None:
    header, recipe = _header(ONE_STAGE, tmp_path, lr=1e-3, steps=11)
    with pytest.raises(ConfigError, match=r"recipe one: the file was trained with other settings than stage main "
                                          r"\(lr, steps\)"):
        recipe_meta(header, recipe, "CPU")
    header, recipe = _header(ONE_STAGE, tmp_path, init_from="old.ckpt")
    with pytest.raises(ConfigError, match="only a run from scratch has its hours in its own file"):
        recipe_meta(header, recipe, "CPU")


def test_the_shipped_file_given_its_record_so_has_this_one() -> None:
    """unet-m-k5-lowspp-b was trained before runs wrote their card's record; its header now holds
    the one recipe_meta gives from the rest of that header and its recipe's measured hardware."""
    path = registry().path_of("unet-m-k5-lowspp-b")
    header = read_checkpoint(path).header
    recipe = load_recipe("unet-m-k5-lowspp-b")
    assert checkpoint_meta(header) == recipe_meta(header, recipe, recipe.final.measured["hardware"])
