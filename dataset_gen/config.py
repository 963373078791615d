"""The dataset's own configuration: how its images were rendered, saved as DIR/dataset.json.

Data carries its config: re-running ``generate-dataset`` into an existing folder with different
render settings is refused, and training can check what it reads. The scene count is not part of
the settings: a dataset can grow. A dataset is made in a new or empty folder only: a folder holding
files but no dataset config is refused, and nothing in it is touched.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from imaging.atomic_io import TMP_PREFIX, write_text_atomic
from imaging.errors import DatasetError, SceneError
from imaging.json_read import parse_json
from rendering.scene_io import pixel_filter_spec

CONFIG_NAME = "dataset.json"
FORMAT_VERSION = 1


@dataclass(frozen=True)
class DatasetConfig:
    """Render settings of a dataset. ``res`` is [width, height] in pixels; ``spp`` the noisy
    sample counts; ``ref_spp`` the reference's (rendered as two halves); ``aovs`` extra buffers
    rendered with each noisy image ("alb", "nrm"); ``val_fraction`` of scenes go to split "val";
    ``variance``: each noisy image of >= 2 spp is rendered as two halves of independent samples and
    its per-pixel variance estimate written beside it (kind ``var``), as ``render-and-denoise`` does.
    ``filter``: the pixel filter of every render, "box" or a dict such as {"type": "gaussian",
    "stddev": 0.5} (:func:`rendering.scene_io.pixel_filter_spec`; a box is stored as "box", as in
    datasets made before other filters existed). ``scene_files``: render these Mitsuba XML files
    (scene i is file i, absolute paths) instead of procedural ``families``."""

    res: tuple[int, int] = (128, 128)
    spp: tuple[int, ...] = (4, 16, 64, 128)
    ref_spp: int = 4096
    families: tuple[str, ...] = ()
    seed: int = 0
    aovs: tuple[str, ...] = ()
    val_fraction: float = 0.1
    filter: str | dict = "box"
    variance: bool = False
    scene_files: tuple[str, ...] = ()
    version: int = FORMAT_VERSION
    mitsuba: str = ""
    variant: str = ""
    extra: dict[str, str] = field(default_factory=dict)

    def validate(self) -> None:
        if len(self.res) != 2 or min(self.res) < 1:
            raise DatasetError(f"resolution must be two positive integers, got {self.res}")
        if not self.spp or min(self.spp) < 1 or len(set(self.spp)) != len(self.spp):
            raise DatasetError(f"noisy spp must be distinct positive integers, got {self.spp}")
        if self.ref_spp < 2 or self.ref_spp % 2:
            raise DatasetError(f"reference spp must be even and >= 2 (two halves), got {self.ref_spp}")
        if not 0.0 <= self.val_fraction < 1.0:
            raise DatasetError(f"val fraction must be in [0, 1), got {self.val_fraction}")
        if not self.families and not self.scene_files:
            raise DatasetError("no scene families selected")
        if self.families and self.scene_files:
            raise DatasetError("a dataset renders either procedural families or scene files, not both")
        try:
            pixel_filter_spec(self.filter)
        except SceneError as exc:
            raise DatasetError(str(exc)) from None
        bad = [a for a in self.aovs if a not in ("alb", "nrm")]
        if bad:
            raise DatasetError(f"unknown AOV {bad[0]!r} (known: alb, nrm)")

    @property
    def pixel_filter(self) -> dict:
        """The canonical pixel filter, {"type": NAME, PARAM: value...}."""
        return pixel_filter_spec(self.filter)

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> "DatasetConfig":
        names = {f.name for f in fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise DatasetError(f"unknown keys {sorted(unknown)}")
        tuples = {k: tuple(v) for k, v in data.items() if isinstance(v, list)}
        return cls(**{**data, **tuples})


def stored_filter(value: str | dict | None) -> str | dict:
    """A pixel filter as ``DatasetConfig.filter`` stores it: "box" for a box (as every dataset made
    before other filters existed says), else its canonical dict. Raises :class:`DatasetError`."""
    try:
        spec = pixel_filter_spec(value)
    except SceneError as exc:
        raise DatasetError(str(exc)) from None
    return "box" if spec["type"] == "box" else spec


def settings_diff(a: DatasetConfig, b: DatasetConfig) -> list[str]:
    """Human-readable differences in render settings (``extra`` and versions excluded)."""
    skip = {"extra", "mitsuba", "variant"}
    return [f"{f.name}: {getattr(a, f.name)} vs {getattr(b, f.name)}"
            for f in fields(DatasetConfig)
            if f.name not in skip and getattr(a, f.name) != getattr(b, f.name)]


def load_config(folder: Path) -> DatasetConfig | None:
    """The config saved in ``folder``, or None if the folder has none yet."""
    path = folder / CONFIG_NAME
    if not path.exists():
        return None
    try:
        data = parse_json(path.read_text())
        if not isinstance(data, dict):
            raise TypeError("not a JSON object")
        return DatasetConfig.from_json(data)
    except (json.JSONDecodeError, TypeError, UnicodeDecodeError, DatasetError) as exc:
        raise DatasetError(f"{path}: not a dataset config this version can use ({exc}); "
                           "use another --out folder") from None


def open_dataset(folder: Path, wanted: DatasetConfig) -> DatasetConfig:
    """Create ``folder`` (new, or empty but for a crash's temporaries) with ``wanted`` settings, or
    check that the dataset already in it has the same. Raises :class:`DatasetError`, before writing
    anything, for a path that is not a folder, a dataset of other settings, and a folder holding
    anything else."""
    wanted.validate()
    if folder.exists() and not folder.is_dir():
        raise DatasetError(f"{folder}: exists and is not a directory")
    existing = load_config(folder) if folder.exists() else None
    if existing is not None:
        diff = settings_diff(existing, wanted)
        if diff:
            raise DatasetError(f"{folder}: dataset was generated with other settings "
                               f"({'; '.join(diff)}); use another --out folder")
        return existing
    held = [p.name for p in folder.iterdir() if not p.name.startswith(TMP_PREFIX)] if folder.exists() else []
    if any(name in ("manifest.jsonl", "images") for name in held):
        raise DatasetError(f"{folder}: holds dataset files but no {CONFIG_NAME}; refusing to mix")
    if held:  # someone else's files: a dataset is made in a new or empty folder only
        raise DatasetError(f"{folder}: is not empty and holds no dataset ({CONFIG_NAME}); "
                           "use another --out folder (a new or empty one)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        write_text_atomic(folder / CONFIG_NAME, json.dumps(wanted.to_json(), indent=1) + "\n")
    except OSError as exc:
        raise DatasetError(f"{folder}: cannot write ({exc.strerror or exc})") from None
    return wanted
