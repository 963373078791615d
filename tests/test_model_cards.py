"""benchmarks.model_cards: the cards' generated fields are what the files they describe say."""
from __future__ import annotations

import json

from benchmarks.model_cards import entry_figures, fill, training_summary, warm_start_name
from model.registry import MANIFEST, registry


def test_the_shipped_cards_match_their_files() -> None:
    """Hashes, training records and figures in the manifest are those the checkpoints and the
    result files give now: run `python -m benchmarks.model_cards` after changing either."""
    current = json.loads(MANIFEST.read_text())
    assert fill(current) == current


def test_figures_are_taken_only_from_results_that_measured_the_entrys_files() -> None:
    shas = {"a" * 64, "b" * 64}
    evaluate = {"summary": {"scored": {str(s): {"models": {"fast": {"psnr": 30.0 + s / 100, "flip": 0.05}}}
                                       for s in (4, 16, 128)}},
                "models": {"fast": {"sha256": "+".join(sorted(shas))}}}
    inference = {"sha256": {"fast": "+".join(sorted(shas))},
                 "ratios": {"1280x720": {"fast": {"4": 0.5, "128": 0.9, "unknown": 0.7}}}}
    figures = entry_figures("fast", shas, evaluate, inference)
    assert figures["psnr"] == {"4": 30.04, "16": 30.16, "128": 31.28} and figures["flip"] == {"16": 0.05}
    assert figures["time"] == {"1280x720": {"spp": 128, "ratio": 0.9}} and figures["time_ratio"] == 0.9
    assert figures["time_unknown_spp"] == {"1280x720": 0.7}
    inference["ratios"]["256x256"] = {"fast": {"4": 0.6, "128": 0.8}}
    by_spp = entry_figures("fast", shas, evaluate, inference)["time_by_spp"]
    assert by_spp == {"4": 0.6, "128": 0.9}  # each spp's largest over sizes
    assert entry_figures("fast", {"c" * 64}, evaluate, inference) == {}  # other files: nothing taken


def test_a_checkpoints_training_summary_comes_from_its_header() -> None:
    card = registry().checkpoints["unet-m-k5-lowspp"]
    summary = training_summary(registry().folder / card.file)
    assert summary["steps"] > 0 and summary["cpu_minutes"] > 0 and "1-16 spp" in summary["data"]
    # a recipe's run: the stage and the hours and hardware of everything up to the file, from its meta
    assert summary["recipe_stage"] == "main" and summary["hours"]["cpu"] > 5 and summary["hardware"]


def test_a_recipe_stages_warm_start_is_named_by_its_stage() -> None:
    summary = training_summary(registry().folder / registry().checkpoints["unet-l-allspp"].file)
    assert summary["recipe_stage"] == "main" and summary["warm_start"] == "stage first"
    assert warm_start_name("runs/x/first/best.ckpt", "main") == "stage first"
    assert warm_start_name("model/weights/flat-s-allspp.ckpt", "finetune") == "flat-s-allspp"
    assert warm_start_name("runs/old/best.ckpt", None) == "best"  # outside a recipe: the file, as it was given
    assert warm_start_name(None, "main") is None


def test_every_shipped_checkpoint_names_its_recipe_in_its_own_header() -> None:
    """Each file describes itself: its header's card record names the recipe and final stage
    that make it (the recipe as it is now: the same sha256), the hours and hardware, and agrees
    with the manifest's card of it."""
    from model.checkpoint import checkpoint_meta, read_checkpoint
    from training.recipe import load_recipe

    for name, card in registry().checkpoints.items():
        meta = checkpoint_meta(read_checkpoint(registry().folder / card.file).header)
        recipe = load_recipe(card.recipe)
        assert meta.get("recipe") == recipe.identity(recipe.final.name), name
        assert card.training["recipe_stage"] == recipe.final.name and card.training["hardware"], name
        assert card.training["hours"] == {k: round(v, 2) for k, v in meta["hours"].items()}, name
