"""The licence: one for the whole project (LICENSE, pyproject.toml, the model cards), and every
shipped file that is not code listed in SOURCES.md with what made it and its terms."""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

from model.registry import registry

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
LICENSE_NAME = "BSD-3-Clause"


def shipped_files(root: Path = ROOT) -> set[str]:
    """The package data that pyproject.toml ships, and the README's pictures: repository paths."""
    project = tomllib.loads((root / "pyproject.toml").read_text())
    files = set()
    for package, patterns in project["tool"]["setuptools"]["package-data"].items():
        folder = root / package.replace(".", "/")
        files |= {str(p.relative_to(root)) for pattern in patterns for p in folder.glob(pattern) if p.is_file()
                  and "__pycache__" not in p.parts}
    readme = (root / "README.md").read_text()
    return files | set(re.findall(r"!\[[^\]]*\]\(([^)]+)\)", readme))


def listed_files(root: Path = ROOT) -> dict[str, str]:
    """SOURCES.md's table: repository path -> its terms."""
    rows = re.findall(r"^\| `([^`]+)` \|.*\| ([^|]+) \|$", (root / "SOURCES.md").read_text(), re.M)
    return {path: terms.strip() for path, terms in rows}


def test_one_licence_for_the_project_its_package_and_its_weights() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert project["license"] == LICENSE_NAME and project["license-files"] == ["LICENSE"]
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("BSD 3-Clause License\n") and "the mc-densenet-denoiser authors" in text
    assert "Neither the name of the copyright holder" in text  # the third clause
    assert registry().license == LICENSE_NAME
    for name in registry().entries:
        assert f"licence: the weights are under {LICENSE_NAME}" in registry().card(name)


def test_every_shipped_file_is_listed_with_what_made_it_and_its_terms() -> None:
    shipped, listed = shipped_files(), listed_files()
    assert {"model/weights/unet-l-allspp.ckpt", "scenes/examples/textures/bricks.exr",
            "docs/figures/strip.png"} <= shipped  # the reader sees the package data and the pictures
    assert sorted(shipped - set(listed)) == []
    assert sorted(p for p in listed if not (ROOT / p).is_file()) == []
    assert {p: t for p, t in listed.items() if t != LICENSE_NAME} == {}


def test_the_readmes_picture_is_of_the_scene_whose_terms_are_recorded() -> None:
    """The strip renders an eval scene (benchmarks/figures.py): SOURCES.md names that very scene
    beside the picture, with the terms that let the picture ship under ours (CC0), so a strip
    remade from another scene fails here until its terms are checked and written down."""
    scene = json.loads((ROOT / "benchmarks" / "results" / "figures.json").read_text())["strip"]["scene"]
    sources = (ROOT / "SOURCES.md").read_text()
    row = next(line for line in sources.splitlines() if line.startswith("| `docs/figures/strip.png` |"))
    paragraph = next(p for p in sources.split("\n\n") if p.startswith("`docs/figures/strip.png`"))
    assert f"`{scene}`" in row and f"`{scene}`" in paragraph and "CC0 1.0" in paragraph
