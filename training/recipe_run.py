"""Running a recipe from nothing: render what is missing, train the stages in order, resume anywhere.

``train --recipe NAME --out DIR`` lays out::

    DIR/recipe.json         the recipe's name, sha256 and content (a second run must be the same recipe)
    DIR/STAGE/              one train run per stage (train_config.json, log.jsonl, last/best.ckpt, curves.png)
    DIR/STAGE/done.json     written when the stage has finished (its steps, or its CPU budget)
    DIR/NAME.ckpt           the final stage's best checkpoint without the optimiser state: the model

Datasets go to ``DATA_ROOT/<dataset name>`` (``--data-root``, default ``data``), rendered by
:func:`dataset_gen.generate.generate_dataset`, which skips finished scenes; a folder there made with
other settings is refused, so recipes that share a dataset (by name and settings) render it once.
After a kill, the same command continues: the dataset where it stopped, a stage from its
``last.ckpt``, later stages from the start. A stage that a finished run of another recipe beside
``DIR`` (in the same parent folder) has already trained, the same computation by
:meth:`training.recipe.Recipe.stage_key`, is copied from there instead of trained again
(``done.json`` names the source; to train it again, run in another parent folder). ``--minutes``
stops the whole command after that much wall time, ``--cpu-minutes`` each stage after that much
optimisation CPU time, leaving the stage resumable (run again, with a larger budget to go further).

With ``--data MINE`` (and ``--extra-data``), the recipe trains on those folders instead of its
datasets; with ``--init-from MODEL`` as well, it fine-tunes: one stage, ``finetune``, with the final
stage's network and crops and the recipe's ``[finetune]`` optimisation, starting from MODEL's weights.
On the user's data, crops larger than its images shrink to fit them (:func:`fit_patch`), and data
without a held-out scene validates on its training scenes (:mod:`training.start_checks`).
:func:`check_run` makes every check of a start before anything is written (``--dry-run`` runs it
too), and a start that fails before a stage kept a file leaves no run folder behind.
"""
from __future__ import annotations

import dataclasses
import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from console.progress import ProgressFactory
from dataset_gen.generate import generate_dataset
from imaging.atomic_io import write_text_atomic
from imaging.errors import ConfigError, DatasetError
from imaging.json_read import parse_json
from model.checkpoint import read_checkpoint, strip_optimizer
from model.config import ModelConfig
from training.dataset import read_manifest
from training.recipe import FINETUNE, DatasetSpec, Recipe, Stage, parse_recipe
from training.start_checks import (OTHER_OUTPUTS, RUN_FILES, check_start, data_image_size, fitting_patch,
                                   validation_note)
from training.train import resume_config, train
from training.train_config import RESUMABLE_OVERRIDES, TrainConfig

DONE = "done.json"
Log = Callable[[str], None]


@dataclass(frozen=True)
class RecipeRun:
    """How to run a recipe here: run folder, data root, the user's data and warm start (fine-tuning),
    the wall-time limit of this command (minutes; None: none) and run control for every stage
    (``device``, ``threads``, ``workers``, ``progress``: TrainConfig fields)."""

    out: Path
    data_root: Path = Path("data")
    data: tuple[str, ...] = ()
    init_from: str | None = None
    minutes: float | None = None
    control: dict[str, Any] = dataclasses.field(default_factory=dict)


@dataclass(frozen=True)
class RecipeResult:
    """What a command did: the model file (None until the last stage has a checkpoint), the stage
    it stopped in (``stopped_in``; None: all finished) and each finished stage's ``done.json``."""

    model: Path | None
    stopped_in: str | None
    stages: dict[str, dict[str, Any]]


def stages_to_run(recipe: Recipe, run: RecipeRun) -> list[Stage]:
    """The stages this command trains: the recipe's, or the one ``finetune`` stage."""
    if run.init_from is None:
        return list(recipe.stages)
    if not run.data:
        raise ConfigError("--init-from with --recipe fine-tunes a model on your data: give --data too")
    final = recipe.final
    try:
        source = ModelConfig.from_dict(read_checkpoint(run.init_from).header.get("model_config"))
    except ConfigError:
        source = None
    if source != final.model:
        raise ConfigError(f"{run.init_from}: not the network recipe {recipe.name} trains ({final.network}); "
                          "fine-tune it with the recipe that made it")
    fields = {**final.fields, **recipe.finetune}
    return [dataclasses.replace(final, name=FINETUNE, init_from=None, fields=fields, measured={})]


def stage_data(recipe: Recipe, stage: Stage, run: RecipeRun) -> list[str]:
    """The dataset folders of ``stage``: the user's (``--data``) or the recipe's under the data root."""
    return list(run.data) if run.data else [str(run.data_root / name) for name in stage.data]


def stage_init(recipe: Recipe, stage: Stage, run: RecipeRun) -> str | None:
    """The checkpoint that starts ``stage``: the earlier stage's best (its last when that stage does
    not validate), or the fine-tune's model."""
    if stage.name == FINETUNE:
        return run.init_from
    if stage.init_from is None:
        return None
    validates = recipe.stage(stage.init_from).fields.get("val_every", 1)
    return str(run.out / stage.init_from / ("best.ckpt" if validates else "last.ckpt"))


def stage_config(recipe: Recipe, stage: Stage, run: RecipeRun) -> tuple[TrainConfig, bool, list[str]]:
    """The TrainConfig ``stage`` trains with here, whether it resumes (its folder holds a
    ``last.ckpt``), and the lines a start prints about its choices. On the user's data the crops
    shrink to fit its images where the recipe's do not (:func:`fit_patch`)."""
    folder = run.out / stage.name
    wanted = stage.train_config(folder, stage_data(recipe, stage, run), stage_init(recipe, stage, run), run.control)
    notes: list[str] = []
    if run.data:
        wanted, note = fit_patch(wanted)
        notes += [note] if note else []
    resume = (folder / "last.ckpt").exists()
    return (_resumed_config(folder, wanted) if resume else wanted), resume, notes


def fit_patch(config: TrainConfig) -> tuple[TrainConfig, str | None]:
    """``config`` with crops no larger than its data's smallest images (the largest side the
    network takes without padding: :func:`training.start_checks.fitting_patch`), and the line that
    says so (None: the recipe's crops fit, or no crop does and the start refuses the data)."""
    size = data_image_size([config.data, *config.extra_data])
    if size is None or config.patch.size <= min(size):
        return config, None
    fits = fitting_patch(config.model, size)
    if not fits:
        return config, None
    note = (f"training crops of {fits} px: the recipe's {config.patch.size} px crops are larger than the data's "
            f"{size[0]}x{size[1]} images")
    return dataclasses.replace(config, patch=dataclasses.replace(config.patch, size=fits)), note


def check_run(recipe: Recipe, run: RecipeRun) -> dict[str, list[str]]:
    """Every check a start makes before it writes anything: the run folder (:func:`_check_recipe`),
    and for each stage that trains on the user's data and is not finished, its folder, data and
    crops (:func:`training.start_checks.check_start`). Returns each such stage's lines for the
    console (its crops, its validation). The recipe's own datasets are checked once rendered."""
    _check_recipe(run, recipe)
    notes: dict[str, list[str]] = {}
    if not run.data:
        return notes
    for stage in stages_to_run(recipe, run):
        if (run.out / stage.name / DONE).exists():
            continue
        config, resume, lines = stage_config(recipe, stage, run)
        data_plan, _ = check_start(config, resume, replace_partial=True)
        note = validation_note(config, data_plan)
        notes[stage.name] = lines + ([note] if note else [])
    return notes


def plan(recipe: Recipe, run: RecipeRun) -> list[str]:
    """The commands the recipe amounts to (what ``--dry-run`` prints): generate-dataset per dataset
    it needs, then train per stage, each with the lines its start would print. Runs the checks of
    a start (:func:`check_run`), so that a command that would fail fails here, writing nothing."""
    lines = [f"# recipe {recipe.name} ({recipe.path}), sha256 {recipe.sha256[:16]}"]
    stages = stages_to_run(recipe, run)
    notes = check_run(recipe, run)
    if run.minutes is not None:
        lines.append(f"# this command stops after {run.minutes:g} minutes (the same command continues the run)")
    if "cpu_budget_s" in run.control:
        lines.append(f"# each stage stops after {run.control['cpu_budget_s'] / 60:g} CPU-minutes of optimisation "
                     "(the same command continues it)")
    if not run.data:
        needed = dict.fromkeys(name for stage in stages for name in stage.data)
        lines += [recipe.datasets[name].command(str(run.data_root)) for name in needed]
    for stage in stages:
        config = stage_config(recipe, stage, run)[0]
        words = [f"train --data {config.data}"] + [f"--extra-data {d}" for d in config.extra_data]
        words += [f"--out {config.out}"] + ([f"--init-from {config.init_from}"] if config.init_from else [])
        settings = ", ".join(f"{k} {v}" for k, v in {"network": stage.network, "patch": config.patch.size,
                                                          "detail_crops": stage.patch.detail, **stage.fields}.items())
        source = shared_stage(recipe, stage, run) if _untrained(run.out / stage.name) else None
        lines.append(f"# stage {stage.name}: " + (f"copied from {source} (the same stage, finished)" if source
                                                   else " ".join(words)))
        lines.append(f"#   with {settings}")
        lines += [f"#   {note}" for note in notes.get(stage.name, [])]
        if stage.measured:
            lines.append("#   measured: " + ", ".join(f"{k} {v}" for k, v in stage.measured.items()))
    return lines


def render_datasets(recipe: Recipe, stages: list[Stage], run: RecipeRun,
                    progress: ProgressFactory | None, log: Log) -> None:
    """Render every scene the stages' datasets still lack (resuming where a dataset stopped)."""
    for name in dict.fromkeys(n for stage in stages for n in stage.data):
        spec = recipe.datasets[name]
        folder = run.data_root / name
        have = _scene_count(folder)
        if have < spec.scenes:
            log(f"rendering {name}: {spec.scenes - have} of {spec.scenes} scenes into {folder}")
            summary = generate_dataset(folder, spec.config, spec.scenes, 0, progress)
            if summary.failed:
                raise DatasetError(f"{folder}: {len(summary.failed)} scene(s) failed to render, first: "
                                   f"{summary.failed[0]}; run the command again to retry")
        _check_scenes(folder, spec)


def _scene_count(folder: Path) -> int:
    try:
        return len(read_manifest(folder))
    except DatasetError:
        return 0


def _check_scenes(folder: Path, spec: DatasetSpec) -> None:
    """The recipe trains on exactly its scenes: a folder holding more was made for something else."""
    count = _scene_count(folder)
    if count != spec.scenes:
        raise DatasetError(f"{folder}: holds {count} scenes, the recipe's dataset {spec.name!r} has {spec.scenes} "
                           "(use another --data-root)")


def _read_record(path: Path, remedy: str) -> dict[str, Any]:
    """The JSON object a run wrote at ``path``; raises :class:`ConfigError` (naming ``remedy``) for
    a file that cannot be read or holds something else."""
    try:
        record = parse_json(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc}); {remedy}") from None
    if not isinstance(record, dict):
        raise ConfigError(f"{path}: not a run's record (a JSON object); {remedy}")
    return record


def _inputs(run: RecipeRun) -> dict[str, Any]:
    """What ``recipe.json`` records of the user's inputs (``--data``, ``--init-from``)."""
    return {"data": [str(Path(d).resolve()) for d in run.data],
            "init_from": str(Path(run.init_from).resolve()) if run.init_from else None}


def _check_recipe(run: RecipeRun, recipe: Recipe) -> None:
    """``run.out`` holds nothing, a run of this very recipe (its sha256) on the same data from the
    same warm start (``--data``, ``--init-from``), or stage folders without ``recipe.json`` (a run
    carried from another machine); never a mix, a file, a plain run's files or a dataset."""
    out, path = run.out, run.out / "recipe.json"
    if path.exists():
        saved = _read_record(path, "use another --out")
        if saved.get("sha256") != recipe.sha256:
            raise ConfigError(f"{out} holds a run of recipe {saved.get('name')!r} (sha256 "
                              f"{str(saved.get('sha256'))[:12]}), not of {recipe.name} ({recipe.sha256[:12]}); "
                              "use another --out")
        inputs = _inputs(run)
        for key, flag in (("data", "--data"), ("init_from", "--init-from")):
            was = saved.get(key, [] if key == "data" else None)
            if was != inputs[key]:
                raise ConfigError(f"{out} holds a run with {flag} {was or 'not given'}, not "
                                  f"{inputs[key] or 'not given'}; use another --out")
        return
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: exists and is not a folder; use another --out")
    found = [name for name in (*RUN_FILES, *OTHER_OUTPUTS) if (out / name).exists()]
    if found:
        raise ConfigError(f"{out} holds {', '.join(found)}: not a recipe run (a plain train run or a dataset); "
                          "use another --out")


def _start_recipe(run: RecipeRun, recipe: Recipe) -> list[Path]:
    """Write ``recipe.json`` into ``run.out`` where it is not yet; returns what this made (the
    file, then the folders it made, deepest first; nothing for a run that goes on)."""
    out, path = run.out, run.out / "recipe.json"
    if path.exists():
        return []
    made = [p for p in (out, *out.parents) if not p.exists()]
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(path, json.dumps({"name": recipe.name, "sha256": recipe.sha256, "source": str(recipe.path),
                                        **_inputs(run), "text": recipe.path.read_text(encoding="utf-8")},
                                       indent=1) + "\n")
    return [path, *made]


def _undo_start(made: list[Path]) -> None:
    """Remove ``recipe.json`` and the folders this command made (:func:`_start_recipe`) where the
    run folder holds nothing else: a start that failed before any stage kept a file leaves
    nothing behind (a stage's own failed start removes its files: :func:`training.train.train`)."""
    if not made:
        return
    path, folders = made[0], made[1:]
    if any(p != path for p in path.parent.iterdir()):
        return
    path.unlink(missing_ok=True)
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:  # not empty: something else is in it
            return


def _resumed_config(folder: Path, wanted: TrainConfig) -> TrainConfig:
    """The config to resume ``folder`` with: its checkpoint's, which must train what the stage
    trains (only run control and data paths may differ)."""
    overrides = {k: getattr(wanted, k) for k in RESUMABLE_OVERRIDES}
    config = resume_config(folder, overrides)
    differ = sorted(f.name for f in dataclasses.fields(TrainConfig)
                    if f.name not in RESUMABLE_OVERRIDES | {"out", "init_from"}
                    and getattr(config, f.name) != getattr(wanted, f.name))
    if differ:
        raise ConfigError(f"{folder}: its run trains something else than the recipe's stage "
                          f"({', '.join(differ)} differ); use another --out")
    return config


def run_stage(recipe: Recipe, stage: Stage, run: RecipeRun, progress: ProgressFactory | None,
              minutes: float | None, log: Log) -> dict[str, Any] | None:
    """Train ``stage`` to its end (None: stopped by ``minutes`` first) and mark it done."""
    folder = run.out / stage.name
    done = folder / DONE
    if done.exists():
        return _read_record(done, "delete it to train the stage again")
    if _untrained(folder):
        source = shared_stage(recipe, stage, run)
        if source is not None:
            return take_shared_stage(source, folder, log)
    config, resume, notes = stage_config(recipe, stage, run)
    where = f"resuming at step {read_checkpoint(folder / 'last.ckpt').header['step']}" if resume else "starting"
    data = ", ".join(Path(d).name for d in (config.data, *config.extra_data))
    limits = [f"{config.steps} steps"] + ([f"{minutes:.3g} minutes"] if minutes is not None else []) + \
        ([f"{config.cpu_budget_s / 60:.3g} CPU-minutes"] if "cpu_budget_s" in run.control else [])
    span = limits[0] if len(limits) == 1 else f"{', '.join(limits[:-1])} or {limits[-1]}, whichever comes first"
    log(f"stage {stage.name}: {where} ({span}, {config.model.arch}, data {data})")
    for note in notes:
        log(note)
    result = train(config, resume=resume, progress=progress, minutes=minutes, recipe=recipe.identity(stage.name),
                   log=log, replace_partial=True)
    if result.stopped == "time" or (result.stopped == "cpu budget" and "cpu_budget_s" in run.control):
        return None  # stopped by this command's limit, not the recipe's: the same command goes on
    record = {"step": result.step, "best_psnr": result.best_psnr, "stopped": result.stopped}
    write_text_atomic(done, json.dumps(record) + "\n")
    return record


def shared_stage(recipe: Recipe, stage: Stage, run: RecipeRun) -> Path | None:
    """A finished stage that computes what ``stage`` does (:meth:`Recipe.stage_key`) in a run of
    another recipe beside ``run.out`` (the same parent folder), or None. Only runs from their
    recipes' own datasets share stages; another run of the same recipe (a repeat) does not."""
    if run.data or run.init_from:
        return None
    key = recipe.stage_key(stage.name)
    for other in sorted(p for p in run.out.parent.iterdir() if p.is_dir() and p != run.out):
        try:
            record = parse_json((other / "recipe.json").read_text(encoding="utf-8"))
            theirs = parse_recipe(record["text"], other / "recipe.json")
        except (OSError, UnicodeDecodeError, json.JSONDecodeError, ConfigError, KeyError, TypeError):
            continue  # not a recipe run (or one this code cannot read): nothing to share
        if record.get("data") or record.get("init_from") or record.get("sha256") == recipe.sha256:
            continue  # a fine-tune, or another run of this recipe (a repeat is meant to train again)
        for candidate in theirs.stages:
            folder = other / candidate.name
            if (folder / DONE).is_file() and (folder / "last.ckpt").is_file() \
                    and theirs.stage_key(candidate.name) == key:
                return folder
    return None


def _untrained(folder: Path) -> bool:
    """True while a stage's folder holds no training of its own (neither finished nor resumable),
    and the folder it would sit in exists (else there is nothing beside it to share)."""
    return folder.parent.parent.is_dir() and not (folder / DONE).exists() and not (folder / "last.ckpt").exists()


def take_shared_stage(source: Path, folder: Path, log: Log) -> dict[str, Any]:
    """Copy the finished stage ``source`` into ``folder`` (which holds nothing of this stage yet)
    and mark it done, naming where it came from."""
    if folder.exists():
        shutil.rmtree(folder)
    shutil.copytree(source, folder)
    record = {**_read_record(folder / DONE, "delete the folder to train the stage"), "taken_from": str(source)}
    write_text_atomic(folder / DONE, json.dumps(record) + "\n")
    log(f"stage {folder.name}: the same as {source} (same network, settings, data and start): copied, not trained")
    return record


def _model_file(recipe: Recipe, stages: list[Stage], run: RecipeRun) -> Path | None:
    """Write the model: the last stage's best checkpoint (its last without validation) without the
    optimiser state; None while that stage has no checkpoint."""
    folder = run.out / stages[-1].name
    source = next((p for p in (folder / "best.ckpt", folder / "last.ckpt") if p.exists()), None)
    if source is None:
        return None
    model = run.out / (f"{recipe.name}-{FINETUNE}d.ckpt" if run.init_from else f"{recipe.name}.ckpt")
    strip_optimizer(source, model)
    return model


def run_recipe(recipe: Recipe, run: RecipeRun, progress: ProgressFactory | None = None,
               data_progress: ProgressFactory | None = None, log: Log = print) -> RecipeResult:
    """Run ``recipe`` as ``run`` says (module docstring). Raises what ``train`` and
    ``generate-dataset`` raise. When this command's limit stops the last stage, the model file
    holds its best checkpoint so far (a fine-tune's result after ``--minutes``)."""
    import time

    start = time.monotonic()
    stages = stages_to_run(recipe, run)
    check_run(recipe, run)
    made = _start_recipe(run, recipe)
    try:
        if not run.data:
            render_datasets(recipe, stages, run, data_progress, log)
        finished: dict[str, dict[str, Any]] = {}
        for stage in stages:
            left = None if run.minutes is None else run.minutes - (time.monotonic() - start) / 60.0
            record = None if left is not None and left <= 0 else run_stage(recipe, stage, run, progress, left, log)
            if record is None:
                last = stage is stages[-1]
                return RecipeResult(_model_file(recipe, stages, run) if last else None, stage.name, finished)
            finished[stage.name] = record
        return RecipeResult(_model_file(recipe, stages, run), None, finished)
    except BaseException:
        _undo_start(made)
        raise
