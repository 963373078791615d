"""model.registry: names a user types -> the checkpoints that run, the cards, auto's rule."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from model.registry import AUTO, CheckpointCard, Registry, RegistryError, registry, split_member, split_range, training_line
from tests.test_denoiser import write_tiny_checkpoint


def manifest(folder: Path, **changes: object) -> Path:
    """A small manifest of three tiny checkpoints in ``folder`` (its own copy of the shape)."""
    for name in ("a", "b", "c"):
        write_tiny_checkpoint(folder / f"{name}.ckpt", seed=ord(name))
    unknown = [{"below": 0.1, "run": "a@bfloat16"}, {"run": "b"}]
    data = {"default": "high",
            "entries": {"fast": {"purpose": "quick", "members": "b", "unknown_spp": unknown},
                        "balanced": {"purpose": "middle", "members": "a:-16+b:-16+c:17-", "unknown_spp": unknown},
                        "high": {"purpose": "best", "members": "a:17-+a:-16+b+c:-16", "unknown_spp": unknown}},
            "checkpoints": {n: {"file": f"{n}.ckpt", "sha256": "0" * 64, "preset": "p", "description": n,
                                "trained_spp": [0, 0], "recipe": n} for n in ("a", "b", "c")},
            "retired": {"old-a": "a", "gone": "abc1234", "fast": "a"}}
    data.update(changes)
    path = folder / "manifest.json"
    path.write_text(json.dumps(data))
    return path


def test_names_resolve_to_their_checkpoints_and_ranges(tmp_path: Path) -> None:
    reg = Registry.load(manifest(tmp_path))
    assert reg.names == ["fast", "balanced", "high", AUTO]
    high = reg.select("high")
    assert high.name == "high" and not high.auto
    assert [m.spec for m in high.choices[0].by_spp] == ["a:17-", "a:-16", "b", "c:-16"]
    assert [m.path for m in high.choices[0].by_spp] == [tmp_path / f"{n}.ckpt" for n in "aabc"]
    assert reg.select(None).name == "high"  # the default
    auto = reg.select(AUTO)
    assert auto.auto and [c.name for c in auto.choices] == ["fast", "balanced", "high"]
    assert {m.spec for m in auto.members} == {"b", "a@bfloat16", "a:-16", "b:-16", "c:17-", "a:17-", "c:-16"}


def test_specs_take_checkpoints_earlier_names_and_files(tmp_path: Path) -> None:
    """Inside a spec a name is a checkpoint, also a name that is an entry elsewhere (``fast`` here is
    what ``a`` was called before): specs written before the registry run what they ran."""
    reg = Registry.load(manifest(tmp_path))
    spec = reg.select(f"fast:17-+old-a:-8+{tmp_path / 'c.ckpt'}")
    assert [(m.path.name, m.lo, m.hi) for m in spec.members] == [("a.ckpt", 17, 0), ("a.ckpt", 0, 8), ("c.ckpt", 0, 0)]
    assert reg.select("fast").name == "fast" and reg.select("fast").choices[0].by_spp[0].path.name == "b.ckpt"
    assert [m.path.name for m in reg.select_list([str(tmp_path / "b.ckpt"), "c"]).members] == ["b.ckpt", "c.ckpt"]


@pytest.mark.parametrize("name, message", [
    ("fsat", "unknown model 'fsat' (registry names: fast, balanced, high, auto; checkpoints: a, b, c)"),
    ("gone", "no longer shipped; its file is in git: `git show abc1234:model/weights/gone.ckpt"),
    ("missing.ckpt", "missing.ckpt: checkpoint file not found"),
    ("a+", "no empty member"),
    ("a:-", "expected NAME:LO-HI"),
    ("a:9-4", "expected NAME:LO-HI"),
    ("", "empty model name"),
])
def test_a_wrong_name_is_one_line_that_lists_the_valid_ones(tmp_path: Path, name: str, message: str) -> None:
    with pytest.raises(RegistryError) as info:
        Registry.load(manifest(tmp_path)).select(name)
    assert message in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("changes, message", [
    ({"default": "fastest"}, "registry default 'fastest' is not an entry"),
    ({"entries": {"a": {"purpose": "x", "members": "a", "unknown_spp": [{"run": "a"}]}}, "default": "a"},
     "names mean two things: a"),
    ({"entries": {"high": {"purpose": "x", "members": "a+zz", "unknown_spp": [{"run": "a"}]}}},
     "'zz' is not a registry checkpoint"),
    ({"entries": {"high": {"purpose": "x", "members": "a", "unknown_spp": [{"run": "a"}, {"below": 1, "run": "b"}]}}},
     "rising 'below' bounds"),
    ({"checkpoints": []}, "not a model registry manifest"),
])
def test_a_broken_manifest_is_refused_naming_the_problem(tmp_path: Path, changes: dict, message: str) -> None:
    with pytest.raises(RegistryError, match=message):
        Registry.load(manifest(tmp_path, **changes))
    (tmp_path / "manifest.json").write_text("{")
    with pytest.raises(RegistryError, match="not a model registry manifest"):
        Registry.load(tmp_path / "manifest.json")


def test_auto_takes_the_cheapest_entry_level_with_the_best_at_the_nearest_measured_spp(tmp_path: Path) -> None:
    path = manifest(tmp_path)
    data = json.loads(path.read_text())
    figures = {"fast": ({"4": 30.0, "16": 35.0, "128": 40.0}, 0.5),
               "balanced": ({"4": 31.95, "16": 35.5, "128": 40.0}, 1.0),
               "high": ({"4": 32.0, "16": 36.0, "128": 40.05}, 2.0)}
    for name, (psnr, ratio) in figures.items():
        data["entries"][name]["figures"] = {"psnr": psnr, "time_ratio": ratio}
    path.write_text(json.dumps(data))
    reg = Registry.load(path)
    # 4 spp: balanced within 0.1 dB of high, cheaper; 16: high alone is best; 128: all within 0.1, fast cheapest
    assert [reg.auto_entry(s) for s in (1, 4, 6, 8, 16, 64, 128, 4096, None)] == [
        "balanced", "balanced", "balanced", "high", "high", "fast", "fast", "fast", "high"]
    assert reg.entries["high"].help_line() == "high: best; 32.00/36.00/40.05 dB at 4/16/128 spp; 2.00x OIDN's time"


def test_auto_compares_the_times_at_the_spp_where_measured(tmp_path: Path) -> None:
    """An entry dear at one spp (its ``time_ratio``) may be cheap at another (``time_by_spp``)."""
    path = manifest(tmp_path)
    data = json.loads(path.read_text())
    figures = {"fast": ({"4": 30.0, "16": 35.0, "128": 40.0}, 0.5, {"4": 0.5, "16": 0.5, "128": 0.5}),
               "balanced": ({"4": 30.0, "16": 35.95, "128": 40.3}, 2.5, {"4": 0.45, "16": 1.5, "128": 2.5}),
               "high": ({"4": 30.0, "16": 36.0, "128": 40.3}, 2.4, {"4": 2.0, "16": 2.4, "128": 2.4})}
    for name, (psnr, ratio, by_spp) in figures.items():
        data["entries"][name]["figures"] = {"psnr": psnr, "time_ratio": ratio, "time_by_spp": by_spp}
    data["entries"]["fast"]["figures"].pop("time_by_spp")  # measured only at its dearest spp
    path.write_text(json.dumps(data))
    reg = Registry.load(path)
    # 4: all level, balanced the cheapest there; 16: balanced level with high at 1.5x, not its dearest 2.5x;
    # 128: balanced level with high but dearer there
    assert [reg.auto_entry(s) for s in (4, 16, 128)] == ["balanced", "balanced", "high"]
    assert reg.entries["balanced"].time_ratio() == 2.5 and reg.entries["balanced"].time_ratio(16) == 1.5
    assert reg.entries["fast"].time_ratio(16) == 0.5 and reg.entries["high"].time_ratio(8) == 2.4


def test_an_unknown_spp_runs_the_tier_of_the_images_noise_level(tmp_path: Path) -> None:
    choice = Registry.load(manifest(tmp_path)).entry_choice("high")
    assert [m.spec for m in choice.for_unknown_spp(0.05)] == ["a@bfloat16"]
    assert [m.spec for m in choice.for_unknown_spp(float("nan"))] == ["a@bfloat16"]  # flat: the first tier
    assert [m.spec for m in choice.for_unknown_spp(0.1)] == ["b"] and [m.spec for m in choice.for_unknown_spp(9.0)] == ["b"]
    assert Registry.load(manifest(tmp_path)).entries["high"].unknown_spp == "a@bfloat16 below noise level 0.1; b"


def test_member_syntax_round_trips() -> None:
    assert split_range("u:17-") == ("u", 17, 0) and split_range("u") == ("u", 0, 0)
    assert split_member("u:-16@bfloat16") == ("u", 0, 16, "bfloat16") and split_member("a@b.ckpt")[3] is None
    assert split_range("odd:1-2.ckpt") == ("odd:1-2.ckpt", 0, 0)


def test_the_shipped_registry_is_whole() -> None:
    """Every shipped checkpoint file exists; every entry's members and unknown-spp choices resolve;
    the default is an entry; each entry's card names its checkpoints and recipes."""
    reg = registry()
    assert set(reg.entries) == {"fast", "balanced", "high"} and reg.default in reg.entries
    for card in reg.checkpoints.values():
        assert (reg.folder / card.file).is_file()
    for name in reg.entries:
        choice = reg.entry_choice(name)
        assert all(m.path.is_file() for m in (*choice.by_spp, *choice.unknown_members))
        card = reg.card(name)
        assert all(f"recipe {m.path.stem}" in card for m in choice.by_spp)
    assert sorted(p.name for p in reg.folder.iterdir()) == sorted(
        ["manifest.json", *(c.file for c in reg.checkpoints.values())])  # nothing else in the weights folder


def test_a_cards_training_line_says_what_its_file_records() -> None:
    def card(**training: object) -> CheckpointCard:
        return CheckpointCard(name="n", file="n.ckpt", sha256="0" * 64, preset="flat-s", description="d",
                              trained_spp=(0, 0), recipe="r", training=training)

    recipe_run = card(steps=10, cpu_minutes=3.0, warm_start="best", recipe_stage="main",
                      hours={"cpu": 5.5, "gpu": 0.25}, hardware=["CPU A", "GPU B"])
    assert training_line(recipe_run) == ("trained: 5.5 CPU-hours, 0.25 GPU-hours from nothing to this file, on "
                                         "CPU A, GPU B: stage main of `train --recipe r`")
    # a warm start outside a recipe: only its own run is known to be in its hours
    warm = card(steps=2000, cpu_minutes=11.3, warm_start="old", hours={"cpu": 0.19, "gpu": 0.0}, hardware=["CPU A"])
    assert training_line(warm) == ("trained: 2,000 steps, 11.3 CPU-minutes on CPU A in its last run, from old "
                                   "(earlier runs not recorded); recipe: `train --recipe r`")
    fine = card(steps=5, cpu_minutes=1.0, warm_start="x", recipe_stage="finetune", hours={"cpu": 0.1}, hardware=["A"])
    assert "in its last run, from x (earlier runs not recorded)" in training_line(fine)
    assert training_line(card(steps=20000, cpu_minutes=113.8)) == (
        "trained: 20,000 steps, 113.8 CPU-minutes in one run from scratch (hardware not recorded); "
        "recipe: `train --recipe r`")


def test_a_card_says_which_networks_run_at_which_spp(tmp_path: Path) -> None:
    """The ranges of the spec, cut where a member's range or trained spp starts or ends."""
    reg = Registry.load(manifest(tmp_path))
    assert reg.spp_ranges("a:17-+a:-16+b+c:-16") == [(1, 16, ["a", "b", "c"]), (17, 0, ["a", "b"])]
    assert reg.spp_ranges("a:-8+b:9-16@bfloat16") == [(1, 8, ["a"]), (9, 16, ["b (bfloat16)"]), (17, 0, ["a"])]
    card = reg.card("balanced")
    assert "\n    1-16 spp: a + b\n    17+ spp: c\n" in card and "a:-16+" not in card
    assert "runs, spp unknown: a (bfloat16) where the image noise level is below 0.1, else b\n" in card


@pytest.mark.parametrize("name", ["fast", "balanced", "high"])
def test_the_shipped_cards_name_what_the_denoiser_runs(name: str) -> None:
    """What a card says runs at an spp is what :meth:`Denoiser.active` runs there."""
    from denoise.denoiser import Denoiser

    denoiser = Denoiser(name)
    for lo, hi, running in registry().spp_ranges(registry().entries[name].members):
        for spp in {lo, hi or lo + 100}:
            assert [n.path.stem for n in denoiser.active(spp)] == running, (name, spp)
