"""Which code a process runs, so that Dask workers can be held to the client's.

A :class:`CodeVersion` is the installed package's version, a hash of the project's source files
(every ``*.py`` of :data:`PACKAGES`, by relative path and content) and, when the project is a git
checkout, its commit and whether the packages differ from it. Two processes run the same code when
package version and source hash agree: a worker with an unmodified copy of the client's tree, with
or without git, matches it; a worker one edit away does not. The commit is there for people.

It is computed once per process and root (the first call), from the files on disk: a worker
whose files change under it after that keeps reporting what it started with.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import subprocess
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

DIST = "mc-densenet-denoiser"
PACKAGES = ("dataset_gen", "model", "pipeline", "scenes")
ROOT = Path(__file__).resolve().parents[1]
GIT_TIMEOUT_S = 10


@dataclass(frozen=True)
class CodeVersion:
    """``package``: the installed distribution's version; ``source``: 12 hex digits of the sha256
    of the source files; ``commit``: git HEAD (12 hex) or None; ``modified``: the checkout's
    packages differ from that commit (tracked changes or new files)."""

    package: str
    source: str
    commit: str | None = None
    modified: bool = False

    def same_code(self, other: CodeVersion) -> bool:
        return (self.package, self.source) == (other.package, other.source)

    def __str__(self) -> str:
        git = f"git {self.commit}{'+modified' if self.modified else ''}, " if self.commit else ""
        return f"{self.package} ({git}source {self.source})"

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CodeVersion:
        """The inverse of :meth:`to_dict`; missing fields (an older worker) read as unknown."""
        return cls(package=str(data.get("package", "unknown")), source=str(data.get("source", "unknown")),
                   commit=data.get("commit"), modified=bool(data.get("modified", False)))


def source_hash(root: Path) -> str:
    """12 hex digits of the sha256 of every ``*.py`` under ``root``/PACKAGES (path and bytes)."""
    digest = hashlib.sha256()
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            digest.update(path.relative_to(root).as_posix().encode() + b"\0")
            digest.update(path.read_bytes() + b"\0")
    return digest.hexdigest()[:12]


def _git(root: Path, *args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True,
                              timeout=GIT_TIMEOUT_S, check=True)
    except (OSError, subprocess.SubprocessError):  # no git, not a checkout, hung file system
        return None
    return done.stdout


def _package_version() -> str:
    try:
        return metadata.version(DIST)
    except metadata.PackageNotFoundError:
        return "not installed"


@functools.lru_cache(maxsize=None)
def code_version(root: Path = ROOT) -> CodeVersion:
    """This process's :class:`CodeVersion` for the project at ``root`` (default: this one)."""
    commit = modified = None
    if (root / ".git").exists():
        head = _git(root, "rev-parse", "HEAD")
        commit = head.strip()[:12] if head else None
        status = _git(root, "status", "--porcelain", "--", *PACKAGES) if commit else None
        modified = bool(status and status.strip())
    return CodeVersion(package=_package_version(), source=source_hash(root), commit=commit,
                       modified=bool(modified))


def worker_code_version() -> dict[str, Any]:
    """:func:`code_version` as a plain dict (what a Dask worker sends back to the client)."""
    return code_version().to_dict()
