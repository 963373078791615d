"""Recipes: how one shipped model is made, from nothing, in one TOML file (training/recipes/NAME.toml).

A recipe names the datasets it needs (what ``generate-dataset`` takes: families or scene count,
resolution, spp levels, reference spp, seed, variance, pixel filter) and its training stages in
order. A stage is one ``train`` run: its network (``preset`` plus ``[stages.model]`` overrides),
its data (dataset names; the first is ``--data``, the others ``--extra-data``), ``TrainConfig``
fields (``steps``, ``lr``...; ``patch`` and ``detail_crops`` for the crops), and optionally
``init_from``: the name of an earlier stage of the same recipe, whose best checkpoint starts it
(a recipe never starts from a file no recipe makes). ``[stages.measured]`` records what the stage
took where it was run (CPU minutes, hardware, best step) and ``[finetune]`` the settings of
``train --recipe NAME --data MINE --init-from MODEL`` (:mod:`training.recipe_run`); neither
changes the recipe's identity, :attr:`Recipe.sha256` (the canonical JSON of everything else), which
every checkpoint a recipe writes records.

::

    name = "smoke"
    description = "..."
    [datasets.tiny]
    families = ["cornell_box"]          # or "default": the families of generate-dataset's default
    scenes = 12
    res = 32
    spp = [4, 16]
    ref_spp = 256
    [[stages]]
    name = "main"
    data = ["tiny"]
    preset = "flat-s"
    steps = 300
    patch = 32
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from dataset_gen.config import DatasetConfig, stored_filter
from imaging.errors import ConfigError, DatasetError
from model.config import ModelConfig, preset
from training.patches import PatchConfig
from training.train_config import TrainConfig

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

RECIPES_DIR = Path(__file__).resolve().parent / "recipes"
# TrainConfig fields a stage may not set: the runner fills them (paths, the warm start) or the
# stage's own keys do (model, patch).
_RUNNER_FIELDS = {"data", "extra_data", "out", "init_from", "model", "patch"}
_STAGE_KEYS = {"name", "data", "init_from", "preset", "model", "patch", "detail_crops", "measured"}
_DATASET_KEYS = {"families", "scenes", "res", "spp", "ref_spp", "seed", "variance", "val_fraction", "aovs",
                 "pixel_filter"}
FINETUNE = "finetune"  # the one stage of a fine-tune (--init-from): no recipe stage takes the name
_INFORMATION = {"description", "measured", "finetune"}  # left out of the recipe's hash


@dataclass(frozen=True)
class DatasetSpec:
    """One dataset of a recipe: the ``generate-dataset`` settings and how many scenes (0..N-1)."""

    name: str
    scenes: int
    config: DatasetConfig

    @classmethod
    def from_table(cls, name: str, table: dict[str, Any], where: str) -> DatasetSpec:
        """Parse ``[datasets.NAME]``; raises :class:`ConfigError` naming ``where``."""
        from scenes.registry import DEFAULT_FAMILIES, FAMILIES

        unknown = sorted(set(table) - _DATASET_KEYS)
        if unknown:
            raise ConfigError(f"{where}: dataset {name!r}: unknown key(s) {', '.join(unknown)} "
                              f"(known: {', '.join(sorted(_DATASET_KEYS))})")
        missing = sorted({"scenes", "res", "spp", "ref_spp"} - set(table))
        if missing:
            raise ConfigError(f"{where}: dataset {name!r} needs {', '.join(missing)}")
        families = table.get("families", "default")
        if families == "default":
            families = tuple(DEFAULT_FAMILIES)
        elif isinstance(families, list) and all(isinstance(f, str) for f in families):
            families = tuple(families)
        else:
            raise ConfigError(f"{where}: dataset {name!r}: families must be \"default\" or a list of names, "
                              f"got {families!r}")
        bad = [f for f in families if f not in FAMILIES]
        if bad:
            raise ConfigError(f"{where}: dataset {name!r}: unknown family {bad[0]!r} (known: {', '.join(FAMILIES)})")
        res = table["res"]
        try:
            config = DatasetConfig(res=(res, res) if isinstance(res, int) else tuple(res), spp=tuple(table["spp"]),
                                   ref_spp=table["ref_spp"], families=families, seed=table.get("seed", 0),
                                   aovs=tuple(table.get("aovs", ())), val_fraction=table.get("val_fraction", 0.1),
                                   filter=stored_filter(table.get("pixel_filter")),
                                   variance=bool(table.get("variance", False)))
            config.validate()
        except (DatasetError, TypeError) as exc:
            raise ConfigError(f"{where}: dataset {name!r}: {exc}") from None
        scenes = table["scenes"]
        if not isinstance(scenes, int) or isinstance(scenes, bool) or scenes < 1:
            raise ConfigError(f"{where}: dataset {name!r}: scenes must be a positive integer, got {scenes!r}")
        return cls(name, scenes, config)

    def command(self, data_root: str = "data") -> str:
        """The ``generate-dataset`` command that renders it."""
        c = self.config
        words = [f"generate-dataset --scenes {self.scenes} --out {data_root}/{self.name}",
                 f"--res {c.res[0]}x{c.res[1]}", f"--spp {','.join(map(str, c.spp))}", f"--ref-spp {c.ref_spp}"]
        from scenes.registry import DEFAULT_FAMILIES

        if tuple(c.families) != tuple(DEFAULT_FAMILIES):
            words.append(f"--families {','.join(c.families)}")
        if c.seed:
            words.append(f"--seed {c.seed}")
        if c.val_fraction != 0.1:
            words.append(f"--val-fraction {c.val_fraction:g}")
        if c.aovs:
            words.append(f"--aovs {','.join(c.aovs)}")
        if c.variance:
            words.append("--variance")
        if c.filter != "box":
            from dataset_gen.jobs import filter_label

            words.append(f"--pixel-filter {filter_label(c.pixel_filter)}")
        return " ".join(words)


@dataclass(frozen=True)
class Stage:
    """One ``train`` run of a recipe: its datasets (names), the stage it starts from (None: from
    scratch), its network, crop settings and other TrainConfig fields, and what it measured."""

    name: str
    data: tuple[str, ...]
    init_from: str | None
    model: ModelConfig
    patch: PatchConfig
    fields: dict[str, Any]
    measured: dict[str, Any] = field(default_factory=dict)
    network: str = ""  # the preset and its overrides as the recipe says them, e.g. "unet-m kernel=5"

    def train_config(self, out: str | Path, data: list[str], init_from: str | None,
                     overrides: dict[str, Any] | None = None) -> TrainConfig:
        """The stage's TrainConfig with its data folders, run folder, warm start and ``overrides``
        (run control: device, threads, workers, progress)."""
        values = {**self.fields, **(overrides or {})}
        return TrainConfig(data=data[0], extra_data=tuple(data[1:]), out=str(out), model=self.model,
                           patch=self.patch, init_from=init_from, **values)


@dataclass(frozen=True)
class Recipe:
    """A parsed recipe file (module docstring)."""

    name: str
    description: str
    datasets: dict[str, DatasetSpec]
    stages: tuple[Stage, ...]
    finetune: dict[str, Any]
    sha256: str
    path: Path

    @property
    def final(self) -> Stage:
        """The stage whose best checkpoint is the recipe's model."""
        return self.stages[-1]

    def stage(self, name: str) -> Stage:
        """The stage called ``name``."""
        for stage in self.stages:
            if stage.name == name:
                return stage
        raise ConfigError(f"recipe {self.name}: no stage {name!r}")

    def stage_key(self, name: str) -> str:
        """sha256 of what stage ``name`` computes: its network, crops and settings, the content of
        its datasets (settings and scene count, not their names) and, recursively, the stage it
        starts from. Two recipes' stages with the same key train the same thing (shared stages)."""
        stage = self.stage(name)
        data = [{"scenes": self.datasets[d].scenes, "config": dataclasses.asdict(self.datasets[d].config)}
                for d in stage.data]
        payload = {"model": stage.model.to_dict(), "patch": dataclasses.asdict(stage.patch), "fields": stage.fields,
                   "data": data, "init": self.stage_key(stage.init_from) if stage.init_from else None}
        return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()

    def identity(self, stage: str) -> dict[str, str]:
        """What a checkpoint of ``stage`` records about the recipe: {"name", "sha256", "stage"}."""
        return {"name": self.name, "sha256": self.sha256, "stage": stage}


def canonical_hash(table: dict[str, Any]) -> str:
    """sha256 of a recipe's content without its informational parts (``description``, each stage's
    ``measured``, ``finetune``): equal for recipes that train the same thing."""
    def strip(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: strip(v) for k, v in value.items() if k not in _INFORMATION}
        if isinstance(value, list):
            return [strip(v) for v in value]
        return value
    return hashlib.sha256(json.dumps(strip(table), sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def _stage(table: dict[str, Any], index: int, datasets: dict[str, DatasetSpec], earlier: list[str],
           where: str) -> Stage:
    name = table.get("name", f"stage{index + 1}")
    label = f"{where}: stage {name!r}"
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", name) or name == FINETUNE:
        raise ConfigError(f"{label}: a stage's name is a folder name of letters, digits, '_', '.', '-' "
                          f"(not {FINETUNE!r}, the name of a fine-tune)")
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(table) - _STAGE_KEYS - (fields - _RUNNER_FIELDS))
    if unknown:
        raise ConfigError(f"{label}: unknown key(s) {', '.join(unknown)} (a stage takes "
                          f"{', '.join(sorted(_STAGE_KEYS))} and TrainConfig fields)")
    data = table.get("data")
    if not isinstance(data, list) or not data or any(d not in datasets for d in data):
        raise ConfigError(f"{label}: data must list datasets of the recipe ({', '.join(datasets) or 'none'}), "
                          f"got {data!r}")
    init_from = table.get("init_from")
    if init_from is not None and init_from not in earlier:
        raise ConfigError(f"{label}: init_from must name an earlier stage of this recipe "
                          f"({', '.join(earlier) or 'none before it'}), got {init_from!r}")
    try:
        model = preset(table["preset"], **table.get("model", {})) if "preset" in table \
            else ModelConfig.from_dict(table.get("model", {}))
        patch = PatchConfig(size=table.get("patch", 128), detail=table.get("detail_crops", 0.0))
        values = {k: v for k, v in table.items() if k in fields - _RUNNER_FIELDS}
        TrainConfig(data="-", out="-", model=model, patch=patch, **values)  # checks every value now
    except (ConfigError, TypeError) as exc:
        raise ConfigError(f"{label}: {exc}") from None
    network = " ".join([str(table.get("preset", "custom")), *(f"{k}={v}" for k, v in table.get("model", {}).items())])
    return Stage(name, tuple(data), init_from, model, patch, values, dict(table.get("measured", {})), network)


def parse_recipe(text: str, path: Path) -> Recipe:
    """A :class:`Recipe` from TOML ``text`` (read from ``path``); raises :class:`ConfigError`."""
    try:
        table = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    known = {"name", "description", "datasets", "stages", "finetune"}
    unknown = sorted(set(table) - known)
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
    name = table.get("name") or path.stem
    dataset_tables, stage_tables = table.get("datasets", {}), table.get("stages", [])
    finetune = table.get("finetune", {})
    if not isinstance(dataset_tables, dict) or not all(isinstance(t, dict) for t in dataset_tables.values()):
        raise ConfigError(f"{path}: datasets must be [datasets.NAME] tables")
    if not isinstance(stage_tables, list) or not all(isinstance(t, dict) for t in stage_tables):
        raise ConfigError(f"{path}: stages must be [[stages]] tables")
    if not isinstance(finetune, dict):
        raise ConfigError(f"{path}: finetune must be a [finetune] table")
    datasets = {n: DatasetSpec.from_table(n, t, str(path)) for n, t in dataset_tables.items()}
    stages: list[Stage] = []
    for i, entry in enumerate(stage_tables):
        stages.append(_stage(entry, i, datasets, [s.name for s in stages], str(path)))
    if not stages:
        raise ConfigError(f"{path}: a recipe needs at least one [[stages]] entry")
    if len({s.name for s in stages}) != len(stages):
        raise ConfigError(f"{path}: stage names must differ")
    bad = sorted(set(finetune) - ({f.name for f in dataclasses.fields(TrainConfig)} - _RUNNER_FIELDS))
    if bad:
        raise ConfigError(f"{path}: [finetune] takes TrainConfig fields, not {', '.join(bad)}")
    return Recipe(name, str(table.get("description", "")).strip(), datasets, tuple(stages), dict(finetune),
                  canonical_hash(table), path)


def recipe_names() -> list[str]:
    """The recipes that ship (training/recipes/*.toml), by name."""
    return sorted(p.stem for p in RECIPES_DIR.glob("*.toml"))


def load_recipe(name_or_path: str | Path) -> Recipe:
    """The recipe called ``name_or_path`` (training/recipes/NAME.toml) or in that TOML file; raises
    :class:`ConfigError` listing the shipped recipes when there is none."""
    path = Path(name_or_path)
    if not path.is_file():
        path = RECIPES_DIR / f"{name_or_path}.toml"
    if not path.is_file():
        raise ConfigError(f"unknown recipe {str(name_or_path)!r} (shipped: {', '.join(recipe_names())}; "
                          "or a path to a .toml file)")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({exc})") from None
    return parse_recipe(text, path)
