"""Recipes: parsing and its errors, the shipped recipes, and a tiny recipe run end to end through
``train --recipe`` (16-px scenes rendered by Mitsuba, two stages, a kill and resume, a fine-tune)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from imaging.errors import ConfigError
from model.checkpoint import checkpoint_meta, pixel_filter, read_checkpoint
from model.config import DEFAULT_TRAIN_MODEL
from training.cli import main
from training.recipe import load_recipe, parse_recipe, recipe_names
from training.recipe_run import RecipeRun, plan, run_recipe
from training.synthetic import write_synthetic_dataset
from training.train_config import TrainConfig

TINY = """
name = "tiny"
[datasets.tiny16]
families = ["cornell_box", "material_preview"]
scenes = 3
res = 16
spp = [2, 8]
ref_spp = 16
seed = 0
val_fraction = 0.5
[[stages]]
name = "first"
data = ["tiny16"]
preset = "flat-s"
model = { layers = 2 }
patch = 16
batch = 4
steps = 4
lr_warmup = 0
val_every = 2
ckpt_every = 1
log_every = 1
threads = 1
oidn = false
[stages.measured]
cpu_minutes = 0.1
[[stages]]
name = "second"
data = ["tiny16"]
init_from = "first"
preset = "flat-s"
model = { layers = 2 }
patch = 16
batch = 4
steps = 3
lr = 5e-4
val_every = 3
ckpt_every = 1
log_every = 1
threads = 1
oidn = false
[finetune]
lr = 2e-4
steps = 2
"""


def _parse(text: str) -> object:
    return parse_recipe(text, Path("test.toml"))


@pytest.mark.parametrize("change, message", [
    (("preset = \"flat-s\"\nmodel = { layers = 2 }\npatch = 16\nbatch = 4\nsteps = 3", "preset = \"flat-x\""),
     "unknown model preset 'flat-x' (valid: flat-s"),
    (("init_from = \"first\"", "init_from = \"second\""),
     "init_from must name an earlier stage of this recipe (first)"),
    (("data = [\"tiny16\"]\ninit_from", "data = [\"other\"]\ninit_from"), "data must list datasets of the recipe"),
    (("lr = 5e-4", "lr = 5e-4\nlearning_rate = 1"), "unknown key(s) learning_rate"),
    (("lr = 5e-4", "lr = 5e-4\nout = \"x\""), "unknown key(s) out"),
    (("ref_spp = 16", "ref_spp = 15"), "reference spp must be even"),
    (("families = [\"cornell_box\", \"material_preview\"]", "families = [\"cornel\"]"), "unknown family 'cornel'"),
    (("val_fraction = 0.5", "val_fraction = 0.5\npixel_filter = \"blackman-harris\""),
     "unknown pixel filter 'blackman-harris' (valid: box, tent, gaussian"),
    (("steps = 3", "steps = 0"), "steps must be a positive integer"),
    (("families = [\"cornell_box\", \"material_preview\"]", "families = \"media\""),
     "families must be \"default\" or a list of names, got 'media'"),
    (("name = \"second\"", "name = \"../up\""), "a stage's name is a folder name"),
    (("name = \"second\"", "name = \"finetune\""), "(not 'finetune', the name of a fine-tune)"),
    (("name = \"second\"", "name = 2"), "a stage's name is a folder name"),
])
def test_bad_recipes_are_one_line_errors(change: tuple[str, str], message: str) -> None:
    text = TINY.replace(*change, 1)
    assert text != TINY
    with pytest.raises(ConfigError) as exc:
        _parse(text)
    assert message in str(exc.value) and "\n" not in str(exc.value)


@pytest.mark.parametrize("text, message", [
    ('finetune = "fast"\n[[stages]]\nname = "a"', "finetune must be a [finetune] table"),
    ("datasets = [1]\n[[stages]]\nname = \"a\"", "datasets must be [datasets.NAME] tables"),
    ("datasets = { d = 1 }\n[[stages]]\nname = \"a\"", "datasets must be [datasets.NAME] tables"),
    ("[stages]\nname = \"a\"", "stages must be [[stages]] tables"),
])
def test_recipe_tables_of_the_wrong_kind_are_one_line_errors(text: str, message: str) -> None:
    with pytest.raises(ConfigError) as exc:
        _parse(text)
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_hash_names_what_is_trained_not_the_notes() -> None:
    base = _parse(TINY)
    noted = _parse(TINY.replace("cpu_minutes = 0.1", "cpu_minutes = 7\nhardware = \"x\"")
                   .replace('name = "tiny"', 'name = "tiny"\ndescription = "notes"'))
    assert noted.sha256 == base.sha256 and noted.description == "notes"
    assert _parse(TINY.replace("lr = 5e-4", "lr = 4e-4")).sha256 != base.sha256
    assert _parse(TINY.replace("seed = 0", "seed = 1")).sha256 != base.sha256


def test_a_stage_key_names_what_is_computed_not_what_it_is_called() -> None:
    tiny = _parse(TINY)
    renamed = _parse(TINY.replace('"first"', '"warm"').replace("tiny16", "other16"))
    assert tiny.stage_key("first") == renamed.stage_key("warm") and tiny.stage_key("second") == renamed.stage_key("second")
    for change in (("steps = 4", "steps = 5"), ("seed = 0", "seed = 1"), ("layers = 2 }\npatch = 16\nbatch = 4\nsteps = 4",
                                                                          "layers = 3 }\npatch = 16\nbatch = 4\nsteps = 4")):
        assert change[0] in TINY
        other = _parse(TINY.replace(*change, 1))
        assert other.stage_key("first") != tiny.stage_key("first")
        assert other.stage_key("second") != tiny.stage_key("second")  # it starts from another stage
    shipped = load_recipe("flat-s-allspp"), load_recipe("flat-s-lowspp")
    assert [shipped[0].stage_key(s) for s in ("pretrain", "main")] == [shipped[1].stage_key(s) for s in ("pretrain", "flat")]


def test_a_recipe_stage_can_warm_start_an_aux_arm_from_an_rgb_stage() -> None:
    """The albedo/normal options are model fields: a stage names them and starts from the RGB stage."""
    text = (TINY.replace("val_fraction = 0.5", "val_fraction = 0.5\naovs = [\"alb\", \"nrm\"]")
            .replace('preset = "flat-s"\nmodel = { layers = 2 }', 'preset = "unet-s"\nmodel = { kernel = 3 }', 1)
            .replace('init_from = "first"\npreset = "flat-s"\nmodel = { layers = 2 }',
                     'init_from = "first"\npreset = "unet-s"\nmodel = { kernel = 3, aux_inputs = true, '
                     'aux_mode = "levels", aux_normals = "camera", aux_prefilter = "bilateral" }'))
    recipe = _parse(text)
    first, second = recipe.stage("first").model, recipe.stage("second").model
    assert recipe.datasets["tiny16"].config.aovs == ("alb", "nrm") and not first.aux_inputs
    assert dataclasses.replace(second, aux_inputs=False, aux_mode="stem", aux_normals="world",
                               aux_prefilter="none") == first
    with pytest.raises(ConfigError, match="stage 'second': model aux_mode 'kernel' needs a predicted filter"):
        _parse(text.replace("kernel = 3, aux_inputs", "kernel = 0, aux_inputs").replace('"levels"', '"kernel"'))


def test_shipped_recipes_parse_and_start_from_scratch() -> None:
    """Every shipped recipe parses; its first stage starts from scratch and every later warm start
    names an earlier stage (so no stage needs a file no recipe makes)."""
    names = recipe_names()
    assert {"flat-s-allspp", "flat-s-lowspp", "unet-l-allspp", "unet-m-k5-lowspp", "unet-m-k5-lowspp-b",
            "smoke"} <= set(names)
    for name in names:
        recipe = load_recipe(name)
        assert recipe.name == name and recipe.stages[0].init_from is None
        for i, stage in enumerate(recipe.stages[1:], 1):
            assert stage.init_from in {s.name for s in recipe.stages[:i]}


def test_every_registry_checkpoint_has_its_recipe_and_a_fine_tune_starts_from_it(
        capsys: pytest.CaptureFixture, tmp_path: Path) -> None:
    """The registry's cards name a recipe each, and ``--init-from`` takes a registry checkpoint's
    name (the network must be the recipe's; an entry, an ensemble, is refused)."""
    from model.registry import registry

    shipped = registry()
    assert {card.recipe for card in shipped.checkpoints.values()} <= set(recipe_names())
    for name, card in shipped.checkpoints.items():
        assert card.recipe == name and load_recipe(name).final.model == \
            load_model_config(shipped.path_of(name)), name
    mine = write_synthetic_dataset(tmp_path / "mine", scenes=3, res=(64, 64), spp=(1, 2, 4), val_scenes=())
    assert main(["--recipe", "unet-m-k5-lowspp", "--out", str(tmp_path / "r"), "--data", str(mine), "--init-from",
                 "unet-m-k5-lowspp", "--minutes", "2", "--dry-run"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert f"--init-from {shipped.path_of('unet-m-k5-lowspp')}" in out[2]
    # 64-px renders of a few scenes (issue 54): the crops fit the images, the training scenes validate
    assert out[4:6] == [
        "#   training crops of 64 px: the recipe's 128 px crops are larger than the data's 64x64 images",
        "#   validating every 500 steps on the 3 training scenes (9 images): the data holds no scene out (split "
        "'val'), so the score measures the fit to these scenes, not to others"]
    assert out[1] == "# this command stops after 2 minutes (the same command continues the run)"
    assert not (tmp_path / "r").exists()
    assert main(["--recipe", "unet-m-k5-lowspp", "--out", str(tmp_path / "r"), "--data", str(mine), "--init-from",
                 "fast"]) == 1
    assert "--init-from fast: a registry entry (an ensemble), not one network" in capsys.readouterr().err


def load_model_config(path: Path) -> object:
    from model.config import ModelConfig

    return ModelConfig.from_dict(read_checkpoint(path).header["model_config"])


def test_unknown_recipe_lists_the_shipped_ones(capsys: pytest.CaptureFixture) -> None:
    assert main(["--recipe", "no-such", "--out", "x"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("train: error: unknown recipe 'no-such' (shipped: ") and "unet-m-k5-lowspp" in err


def test_train_defaults_are_the_default_models_recipe() -> None:
    """What ``train`` does without --recipe is the final stage of unet-m-k5-lowspp, the default
    model's U-Net, in everything that shapes the network it learns (not the data or run control)."""
    stage = load_recipe("unet-m-k5-lowspp").final
    recipe = stage.train_config("o", ["d"], None)
    defaults = TrainConfig(data="d", out="o")
    assert defaults.model == DEFAULT_TRAIN_MODEL == recipe.model
    for name in ("patch", "batch", "lr", "lr_warmup", "lr_cosine_steps", "lr_final", "steps", "gradient_weight",
                 "loss_norm", "loss_space"):
        assert getattr(defaults, name) == getattr(recipe, name), name


def test_recipe_flags_refuse_what_the_recipe_sets(capsys: pytest.CaptureFixture) -> None:
    assert main(["--recipe", "smoke", "--out", "x", "--lr", "0.1", "--preset", "flat-m"]) == 1
    err = capsys.readouterr().err.strip()
    assert "--lr, --preset cannot be combined with --recipe" in err
    for flags, named in ((["--seed", "0"], "--seed"), (["--no-oidn"], "--no-oidn"), (["--val-every", "0"], "--val-every"),
                         (["--resume"], "--resume")):  # zero and False are values too
        assert main(["--recipe", "smoke", "--out", "x", *flags]) == 1
        assert f"{named} cannot be combined with --recipe" in capsys.readouterr().err


def test_dry_run_prints_the_commands(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    recipe = tmp_path / "tiny.toml"
    recipe.write_text(TINY)
    assert main(["--recipe", str(recipe), "--out", str(tmp_path / "run"), "--data-root", "D", "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "generate-dataset --scenes 3 --out D/tiny16 --res 16x16 --spp 2,8 --ref-spp 16" in out
    assert f"--init-from {tmp_path / 'run' / 'first' / 'best.ckpt'}" in out
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_tiny_recipe_end_to_end_with_a_kill_and_a_fine_tune(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture) -> None:
    """A recipe from nothing: its data rendered, stage one stopped after its first step (as a kill
    would leave it) and resumed by the same call, stage two warm-started from stage one's best;
    the model file's card names the recipe, its hours and the box filter; the same command again
    does nothing; another recipe may not share the folder; a fine-tune on the rendered data."""
    recipe = parse_recipe(TINY, tmp_path / "tiny.toml")
    (tmp_path / "tiny.toml").write_text(TINY)
    out, data = tmp_path / "run", tmp_path / "data"
    run = RecipeRun(out=out, data_root=data, minutes=1e-6, control={"progress": False})
    stopped = run_recipe(recipe, run, log=lambda line: None)
    assert stopped.model is None and stopped.stopped_in == "first"
    assert len((data / "tiny16" / "manifest.jsonl").read_text().splitlines()) == 3
    assert not (out / "first" / "done.json").exists()

    result = run_recipe(recipe, dataclasses.replace(run, minutes=None), log=lambda line: None)
    assert result.model == out / "tiny.ckpt" and set(result.stages) == {"first", "second"}
    log = [json.loads(line) for line in (out / "first" / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log if r["type"] == "train"] == [1, 2, 3, 4]
    header = read_checkpoint(result.model).header
    best = read_checkpoint(out / "second" / "best.ckpt").header
    assert header["optimizer"] is None and header["step"] == best["step"]
    meta = checkpoint_meta(header)
    assert meta["recipe"] == {"name": "tiny", "sha256": recipe.sha256, "stage": "second"}
    first = checkpoint_meta(read_checkpoint(out / "first" / "best.ckpt").header)
    assert meta["hours"]["cpu"] > first["hours"]["cpu"] > 0 and meta["hours"]["gpu"] == 0
    assert len(meta["hardware"]) == 1 and "cores" in meta["hardware"][0]
    assert pixel_filter(header) == {"type": "box"} == meta["pixel_filter"]
    assert header["train_config"]["init_from"] == str(out / "first" / "best.ckpt")

    again = run_recipe(recipe, dataclasses.replace(run, minutes=None), log=lambda line: None)
    assert again.model == result.model and again.stages == result.stages

    # another recipe whose first stage is this one's (other names) takes it from the run beside it
    shares = TINY.replace('name = "tiny"', 'name = "tiny2"').replace('"first"', '"warm"').replace("5e-4", "3e-4")
    (tmp_path / "tiny2.toml").write_text(shares)
    run2 = dataclasses.replace(run, out=tmp_path / "run2", minutes=None)
    lines: list[str] = []
    second = run_recipe(parse_recipe(shares, tmp_path / "tiny2.toml"), run2, log=lines.append)
    assert second.stages["warm"]["taken_from"] == str(out / "first") and "taken_from" not in second.stages["second"]
    assert (run2.out / "warm" / "log.jsonl").read_bytes() == (out / "first" / "log.jsonl").read_bytes()
    assert any("copied, not trained" in line for line in lines)
    assert read_checkpoint(second.model).header["train_config"]["init_from"] == str(run2.out / "warm" / "best.ckpt")
    planned = plan(parse_recipe(shares, tmp_path / "tiny2.toml"), dataclasses.replace(run2, out=tmp_path / "run3"))
    assert f"# stage warm: copied from {out / 'first'} (the same stage, finished)" in planned
    assert any(line.startswith("# stage second: train --data") for line in planned)  # tiny2 is a repeat: not shared

    other = parse_recipe(TINY.replace("lr = 5e-4", "lr = 4e-4"), tmp_path / "tiny.toml")
    with pytest.raises(ConfigError, match="holds a run of recipe 'tiny'"):
        run_recipe(other, run, log=lambda line: None)
    with pytest.raises(ConfigError, match="holds a run with --data not given, not "):
        run_recipe(recipe, dataclasses.replace(run, data=(str(data / "tiny16"),)), log=lambda line: None)
    done = out / "second" / "done.json"
    kept = done.read_text()
    for broken in ("{", "[" * 100_000):  # malformed, and nested past Python's recursion limit
        done.write_text(broken)
        with pytest.raises(ConfigError, match="done.json: cannot read .*delete it to train the stage again"):
            run_recipe(recipe, dataclasses.replace(run, minutes=None), log=lambda line: None)
    done.write_text(kept)

    limited = tmp_path / "limited"  # a fine-tune stopped by its budget still leaves its model so far
    assert main(["--recipe", str(tmp_path / "tiny.toml"), "--out", str(limited), "--data", str(data / "tiny16"),
                 "--init-from", str(result.model), "--cpu-minutes", "0.000001", "--no-progress"]) == 0
    assert "stopped in stage finetune by the command's limit; the model so far: " in capsys.readouterr().out
    assert (limited / "tiny-finetuned.ckpt").exists() and not (limited / "finetune" / "done.json").exists()

    tuned = tmp_path / "tuned"
    assert main(["--recipe", str(tmp_path / "tiny.toml"), "--out", str(tuned), "--data", str(data / "tiny16"),
                 "--init-from", str(result.model), "--no-progress"]) == 0
    assert "recipe tiny done: " in capsys.readouterr().out
    assert main(["--recipe", str(tmp_path / "tiny.toml"), "--out", str(tuned), "--data", str(data / "tiny16"),
                 "--init-from", str(out / "first" / "best.ckpt"), "--no-progress"]) == 1
    assert "holds a run with --init-from " in capsys.readouterr().err
    config = read_checkpoint(tuned / "tiny-finetuned.ckpt").header["train_config"]
    assert config["init_from"] == str(result.model) and config["lr"] == 2e-4 and config["steps"] == 2
    assert main(["--recipe", "smoke", "--out", str(tmp_path / "t2"), "--data", str(data / "tiny16"),
                 "--init-from", str(result.model)]) == 1
    assert "not the network recipe smoke trains (flat-s)" in capsys.readouterr().err


FINETUNE = """
name = "tiny-unet"
[datasets.unused]
scenes = 20
res = 256
spp = [1]
ref_spp = 16
[[stages]]
name = "main"
data = ["unused"]
preset = "unet-s"
model = { levels = 1, layers = 1, growth = 4, init_features = 8 }
patch = 32
batch = 2
steps = 100
threads = 1
oidn = false
[finetune]
steps = 2
lr_warmup = 0
val_every = 1
ckpt_every = 1
log_every = 1
"""


@pytest.fixture
def tiny_unet(tmp_path: Path) -> tuple[Path, Path]:
    """A recipe of a small U-Net (alignment 4, 32-px crops) and a checkpoint of its network."""
    from model.architectures import build_model
    from model.checkpoint import save_checkpoint

    path = tmp_path / "tiny-unet.toml"
    path.write_text(FINETUNE)
    base = tmp_path / "base.ckpt"
    save_checkpoint(base, build_model(parse_recipe(FINETUNE, path).final.model), step=0)
    return path, base


def test_a_fine_tune_on_a_few_small_renders_just_works(tiny_unet: tuple[Path, Path], tmp_path: Path,
                                                       capsys: pytest.CaptureFixture) -> None:
    """Three scenes smaller than the recipe's crops, none held out: --dry-run says what the start
    will do (crops shrunk to fit, validation on the training scenes) and creates nothing; the run
    does it, printing those lines and each validation's score, and the same command again is done."""
    recipe, base = tiny_unet
    data = write_synthetic_dataset(tmp_path / "mine", scenes=3, res=(30, 26), spp=(2, 8), val_scenes=())
    out = tmp_path / "runs" / "mine"
    argv = ["--recipe", str(recipe), "--data", str(data), "--init-from", str(base), "--out", str(out), "--no-progress"]
    crops = "training crops of 24 px: the recipe's 32 px crops are larger than the data's 30x26 images"
    validation = ("validating every 1 steps on the 3 training scenes (6 images): the data holds no scene out "
                  "(split 'val'), so the score measures the fit to these scenes, not to others")
    assert main([*argv, "--dry-run"]) == 0
    planned = capsys.readouterr().out.splitlines()
    assert "patch 24" in planned[2] and planned[3:5] == [f"#   {crops}", f"#   {validation}"]
    assert not (tmp_path / "runs").exists()
    assert main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("train: stage finetune: starting (2 steps, dense_unet, data mine)")
    assert lines[1:3] == [f"train: {crops}", f"train: {validation}"]
    assert [line.split(":")[1] for line in lines[3:5]] == [" step 1", " step 2"]
    assert all(" dB on the training scenes (6 images; noisy " in line for line in lines[3:5])
    assert lines[5] == f"recipe tiny-unet done: {out / 'tiny-unet-finetuned.ckpt'}"
    config = read_checkpoint(out / "tiny-unet-finetuned.ckpt").header["train_config"]
    assert config["patch"]["size"] == 24 and config["val_every"] == 1
    assert main(argv) == 0 and "recipe tiny-unet done" in capsys.readouterr().out


def test_a_fine_tune_that_cannot_start_leaves_nothing(tiny_unet: tuple[Path, Path], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture) -> None:
    """Data that will fail (no dataset; images smaller than any crop the network takes) fails
    --dry-run as it fails the run, before a run folder exists; a plain train run's folder is not
    taken for a recipe's."""
    recipe, base = tiny_unet
    out = tmp_path / "runs" / "mine"
    tiny = write_synthetic_dataset(tmp_path / "tiny", scenes=2, res=(3, 3), spp=(2,), val_scenes=())
    for data, message in ((tmp_path / "nothing", "nothing/dataset.json: not found"),
                          (tiny, "its 3x3 images are smaller than the 32px training crops; render the data at a "
                                 "larger --res")):
        for dry in ([], ["--dry-run"]):
            assert main(["--recipe", str(recipe), "--data", str(data), "--init-from", str(base), "--out", str(out),
                         "--no-progress", *dry]) == 1
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and message in err[0], err
            assert not (tmp_path / "runs").exists()
    plain = tmp_path / "plain"
    plain.mkdir()
    (plain / "last.ckpt").write_bytes(base.read_bytes())
    data = write_synthetic_dataset(tmp_path / "mine", scenes=2, res=(32, 32), spp=(2,), val_scenes=())
    assert main(["--recipe", str(recipe), "--data", str(data), "--init-from", str(base), "--out", str(plain)]) == 1
    assert "holds last.ckpt: not a recipe run" in capsys.readouterr().err
    assert [p.name for p in plain.iterdir()] == ["last.ckpt"]
