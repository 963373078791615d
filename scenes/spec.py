"""What a scene generator returns: a Mitsuba scene dict plus the asset files it references."""
from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import PurePosixPath
from typing import Any

import numpy as np

Asset = np.ndarray | bytes


def referenced_files(node: Mapping[str, Any]) -> Iterator[str]:
    """Every ``filename`` string in a (nested) Mitsuba scene dict, in dict order."""
    for key, value in node.items():
        if key == "filename" and isinstance(value, str):
            yield value
        elif isinstance(value, Mapping):
            yield from referenced_files(value)


def check_asset_name(name: str) -> None:
    """Raise ValueError unless ``name`` is a relative POSIX path inside the scene folder."""
    path = PurePosixPath(name)
    if not name or path.is_absolute() or ".." in path.parts or "\\" in name:
        raise ValueError(f"asset name {name!r} must be a relative path inside the scene folder")


@dataclass
class GeneratedScene:
    """A procedurally generated scene.

    ``scene`` is a Mitsuba 3 scene dict (for ``mi.load_dict``) with one ``perspective`` sensor
    (``hdrfilm`` film, ``independent`` sampler) and a ``path`` integrator. Its file-based plugins
    name assets by relative POSIX paths (``"textures/env.exr"``, ``"meshes/terrain.ply"``) that
    resolve against the folder the scene is written to. ``assets`` maps each of those names to its
    content: an HxWx3 float32 array (linear values, written as an EXR) or raw bytes (e.g. a
    binary PLY). Every referenced file has an asset and every asset is referenced.
    """

    family: str
    seed: int
    scene: dict[str, Any]
    assets: dict[str, Asset] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, content in self.assets.items():
            check_asset_name(name)
            if isinstance(content, np.ndarray):
                if content.ndim != 3 or content.shape[2] != 3 or content.dtype != np.float32:
                    raise ValueError(f"asset {name!r}: expected an HxWx3 float32 array, "
                                     f"got {content.dtype} {content.shape}")
            elif not isinstance(content, bytes):
                raise ValueError(f"asset {name!r}: expected a numpy array or bytes, "
                                 f"got {type(content).__name__}")
        files = set(referenced_files(self.scene))
        missing = sorted(files - set(self.assets))
        unused = sorted(set(self.assets) - files)
        if missing:
            raise ValueError(f"{self.family}/{self.seed}: scene references files without an "
                             f"asset: {', '.join(missing)}")
        if unused:
            raise ValueError(f"{self.family}/{self.seed}: assets not referenced by the scene: "
                             f"{', '.join(unused)}")
