"""What a training run checks before it creates anything: its folder, its data, its crops.

:func:`check_start` reads only small files (``dataset.json``, ``manifest.jsonl``, the checkpoint
being resumed), so ``train --recipe ... --dry-run`` runs the very checks a start runs and a start
that would fail is refused before a run folder exists. The data's choices are made here too:

- **Validation.** Held-out scenes (split ``val``) when the data has any; a dataset too small to
  hold one out (``generate-dataset`` puts each scene there with a seeded chance of 10%: a few
  scenes often give none) is validated on its training scenes instead, whole images as for held-out ones, and the
  start says so: the score then measures the fit to those scenes, not how the network does on
  others. ``val_every = 0``: no validation.
- **Crops.** A crop larger than the data's images is refused, naming the largest that fits
  (:func:`fitting_patch`: a multiple of the network's alignment).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from imaging.errors import CheckpointError, ConfigError, DatasetError
from model.architectures import alignment
from model.checkpoint import Checkpoint, read_checkpoint
from model.config import ModelConfig
from training.dataset import SceneRecord, read_dataset_config, read_manifest
from training.train_config import TrainConfig

RUN_FILES = ("last.ckpt", "best.ckpt", "log.jsonl", "train_config.json", "curves.png")  # what a run writes
# files that mark a folder as something other than a plain run: a recipe run, a dataset
OTHER_OUTPUTS = {"recipe.json": "a recipe run", "dataset.json": "a dataset", "manifest.jsonl": "a dataset"}
# dataset.json fields a resumed run must see unchanged
_DATA_KEYS = ("spp", "ref_spp", "filter", "aovs", "variance")


@dataclass(frozen=True)
class DataPlan:
    """What a run will train and validate on, read from the datasets' small files: the primary
    dataset's config (with ``scenes`` {"train", "val"} counts and the extra datasets' under
    ``extra_data``), each dataset's (folder, train records, validation records), whether the
    validation records are the training scenes (no scene held out), and the smallest image
    (W, H) of the datasets (None where a ``dataset.json`` does not say)."""

    data_config: dict[str, Any]
    datasets: list[tuple[Path, list[SceneRecord], list[SceneRecord]]]
    val_on_train: bool
    image_size: tuple[int, int] | None

    def val_images(self) -> int:
        """How many whole images each validation denoises (one per scene and spp level)."""
        return sum(len(r.spp) for _, _, val in self.datasets for r in val)

    def val_scenes(self) -> int:
        """How many scenes the validation images come from."""
        return sum(len(val) for _, _, val in self.datasets)


def check_run_folder(folder: Path, resume: bool, replace_partial: bool = False) -> None:
    """Refuse a new run's folder that holds something it would replace: a file, a run (``last.ckpt``:
    ``--resume`` continues it), a recipe run or a dataset, or a run's files without its
    ``last.ckpt`` (``replace_partial``: they may go, the caller owns the folder). A missing
    folder, an empty one, or one of other files passes. ``resume``: nothing to check here."""
    if resume:
        return
    if folder.exists() and not folder.is_dir():
        raise ConfigError(f"{folder}: exists and is not a folder")
    if (folder / "last.ckpt").exists():
        raise ConfigError(f"{folder} already holds a run (last.ckpt); use --resume or another --out")
    for name, what in OTHER_OUTPUTS.items():
        if (folder / name).exists():
            raise ConfigError(f"{folder} holds {what} ({name}), not a run to add to; choose another --out")
    partial = [name for name in RUN_FILES if (folder / name).exists()]
    if partial and not replace_partial:
        raise ConfigError(f"{folder} holds a run's files without a last.ckpt to resume from "
                          f"({', '.join(partial)}); delete them or choose another --out")


def fitting_patch(model: ModelConfig, size: tuple[int, int]) -> int:
    """The largest crop side that fits images of ``size`` (W, H) and that the network takes without
    padding (a multiple of its alignment); 0 when the images are smaller than one alignment cell."""
    align = alignment(model)
    return min(size) // align * align


def _within(record: SceneRecord, min_spp: int, max_spp: int, root: Path) -> SceneRecord:
    """``record`` with its renders of fewer than ``min_spp`` or more than ``max_spp`` (0: no limit)
    spp left out (none left: an error)."""
    spp = tuple(s for s in record.spp if s >= min_spp and (not max_spp or s <= max_spp))
    if not spp:
        wanted = " and ".join(f"{op} {n}" for op, n in ((">=", min_spp), ("<=", max_spp)) if n)
        raise DatasetError(f"{root}: scene {record.index} has no render at {wanted} spp "
                           f"(it has {', '.join(map(str, record.spp))})")
    return dataclasses.replace(record, spp=spp)


def _check_data_config(data_config: dict[str, Any], ckpt: Checkpoint | None, config: TrainConfig) -> None:
    if config.model.aux_inputs and not {"alb", "nrm"} <= set(data_config.get("aovs") or []):
        raise DatasetError(f"{config.data}: the model needs albedo/normal but dataset.json lists aovs "
                           f"{data_config.get('aovs')!r}")
    if config.model.noise_input and not data_config.get("variance"):
        raise DatasetError(f"{config.data}: the model takes noise input but the dataset has no variance "
                           "images (generate it with --variance)")
    saved = ckpt.header.get("data_config") if ckpt is not None else None
    if saved:
        diff = [k for k in _DATA_KEYS if saved.get(k) != data_config.get(k)]
        if diff:
            raise DatasetError(f"{config.data}: dataset differs from the one this run was trained on "
                               f"({', '.join(f'{k}: {saved.get(k)!r} -> {data_config.get(k)!r}' for k in diff)})")


def _split_counts(scenes: Any) -> tuple[Any, Any]:
    """(train, val) of a data config's ``scenes`` record (as recorded, whatever it holds)."""
    return (scenes.get("train"), scenes.get("val")) if isinstance(scenes, dict) else (scenes, None)


def _check_scene_counts(data_config: dict[str, Any], ckpt: Checkpoint | None, config: TrainConfig) -> None:
    """A resumed run must train on the scenes it started with: a dataset that has grown (or lost
    scenes) since would change the run without a trace. Checkpoints without the record pass."""
    saved = ckpt.header.get("data_config") if ckpt is not None else None
    if not saved:
        return
    extra = saved.get("extra_data") or []
    if not isinstance(extra, list) or not all(isinstance(o, dict) for o in extra):
        raise CheckpointError(f"{ckpt.path}: corrupt data_config in checkpoint")
    olds = [saved, *extra]
    folders = (config.data, *config.extra_data)
    for folder, old, new in zip(folders, olds, [data_config, *data_config.get("extra_data", [])]):
        if "scenes" in old and old["scenes"] != new["scenes"]:
            (was_train, was_val), (now_train, now_val) = _split_counts(old["scenes"]), _split_counts(new["scenes"])
            raise DatasetError(f"{folder}: the run was trained on {was_train} train / {was_val} val scenes, the "
                               f"dataset now gives {now_train} / {now_val} (scenes added or removed since; start a "
                               "new run, e.g. with --init-from, to train on them)")


def _image_size(config: dict[str, Any]) -> tuple[int, int] | None:
    res = config.get("res")
    if isinstance(res, list) and len(res) == 2 and all(isinstance(v, int) and v > 0 for v in res):
        return res[0], res[1]
    return None


def data_image_size(folders: list[str]) -> tuple[int, int] | None:
    """The smallest width and height (W, H) of the images of the datasets in ``folders``, from their
    ``dataset.json`` (None where none says); raises :class:`DatasetError` for a folder without one."""
    sizes = [s for s in (_image_size(read_dataset_config(Path(f))) for f in folders) if s is not None]
    return (min(s[0] for s in sizes), min(s[1] for s in sizes)) if sizes else None


def plan_data(config: TrainConfig, ckpt: Checkpoint | None) -> DataPlan:
    """The run's :class:`DataPlan`; raises :class:`DatasetError` for data the run cannot use (no
    training scene, renders outside the spp limits, inputs the model needs and the data lacks, or,
    on a resume, other data than the run started with)."""
    datasets = []
    data_config: dict[str, Any] = {}
    sizes = []
    for k, folder in enumerate((config.data, *config.extra_data)):
        root = Path(folder)
        this = read_dataset_config(root)
        _check_data_config(this, ckpt if k == 0 else None, config)
        records = [r for r in read_manifest(root) if not config.max_scenes or r.index < config.max_scenes]
        if config.min_spp or config.max_spp:
            records = [_within(r, config.min_spp, config.max_spp, root) for r in records]
        train = [r for r in records if r.split == "train"]
        val = [r for r in records if r.split == "val"]
        if not train:
            raise DatasetError(f"{root}: manifest has no scenes in split 'train'")
        scenes = {"train": len(train), "val": len(val)}
        if k == 0:
            data_config = {**this, "scenes": scenes}
        else:
            data_config.setdefault("extra_data", []).append({"path": folder, **this, "scenes": scenes})
        datasets.append((root, train, val))
        size = _image_size(this)
        if size is not None:
            sizes.append(size)
    _check_scene_counts(data_config, ckpt, config)
    val_on_train = bool(config.val_every) and not any(val for _, _, val in datasets)
    if val_on_train:
        datasets = [(root, train, train) for root, train, _ in datasets]
    size = (min(s[0] for s in sizes), min(s[1] for s in sizes)) if sizes else None
    return DataPlan(data_config, datasets, val_on_train, size)


def check_patch(config: TrainConfig, plan: DataPlan) -> None:
    """Refuse training crops larger than the data's smallest images, naming the largest that fits."""
    size = plan.image_size
    if size is None or config.patch.size <= min(size):
        return
    fits = fitting_patch(config.model, size)
    remedy = f"give --patch {fits} or less" if fits else "render the data at a larger --res"
    raise DatasetError(f"{config.data}: its {size[0]}x{size[1]} images are smaller than the "
                       f"{config.patch.size}px training crops; {remedy}")


def validation_note(config: TrainConfig, plan: DataPlan) -> str | None:
    """The one line a start prints about its validation (None: the run does not validate)."""
    if not config.val_every:
        return None
    scenes, images = plan.val_scenes(), plan.val_images()
    if plan.val_on_train:
        return (f"validating every {config.val_every} steps on the {scenes} training scenes ({images} images): "
                "the data holds no scene out (split 'val'), so the score measures the fit to these scenes, "
                "not to others")
    return f"validating every {config.val_every} steps on {scenes} held-out scenes ({images} images)"


def check_start(config: TrainConfig, resume: bool, replace_partial: bool = False) -> tuple[DataPlan, Checkpoint | None]:
    """Every check a run makes before it creates anything (module docstring): the folder
    (:func:`check_run_folder`), the checkpoint a resume continues, the data and the crops. Returns
    the data plan and that checkpoint (None for a new run)."""
    folder = Path(config.out)
    check_run_folder(folder, resume, replace_partial)
    ckpt = read_checkpoint(folder / "last.ckpt") if resume else None
    plan = plan_data(config, ckpt)
    check_patch(config, plan)
    return plan, ckpt
