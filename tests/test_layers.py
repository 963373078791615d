"""The folders are the layers, and imports point down only (README, "Layout").

Every import of every .py file of the packages is read with ``ast`` (function-level and
``TYPE_CHECKING`` imports included) and checked against :data:`ALLOWED`: the foundation
(``imaging``; ``console`` above it) uses nothing else of ours; ``rendering`` uses ``imaging``;
``scenes`` and ``dataset_gen`` build on rendering; ``model`` (networks, checkpoints, registry) uses
``imaging`` only; ``denoise`` (the engine) uses ``model``; ``training`` uses ``denoise`` (validation
runs the users' chain) and ``dataset_gen`` and ``scenes`` (a recipe renders its data); ``pipeline`` is the application and uses all of them; nothing imports
``pipeline`` or ``benchmarks`` but themselves (and the tests).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOOLS = ("benchmarks", "fuzz", "mutation")  # run from the command line; nothing of the product imports them
PACKAGES = ("imaging", "console", "rendering", "scenes", "dataset_gen", "model", "denoise", "training",
            "pipeline", *TOOLS)
FOUNDATION = {"imaging", "console"}
ALLOWED = {
    "imaging": {"imaging"},
    "console": {"imaging", "console"},
    "rendering": {"imaging", "rendering"},
    "scenes": {"imaging", "rendering", "scenes"},
    "dataset_gen": FOUNDATION | {"rendering", "scenes", "dataset_gen"},
    "model": {"imaging", "model"},
    "denoise": {"imaging", "rendering", "model", "denoise"},
    "training": FOUNDATION | {"rendering", "scenes", "dataset_gen", "model", "denoise", "training"},
    "pipeline": set(PACKAGES) - set(TOOLS),
    **{tool: set(PACKAGES) for tool in TOOLS},
}


def imported_packages(path: Path, package: str) -> list[tuple[int, str]]:
    """(line, top-level package) of every import in ``path`` (a file of ``package``) that names one
    of ours, in line order."""
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [package if node.level else node.module or ""]
        else:
            continue
        found += [(node.lineno, name.split(".")[0]) for name in names if name.split(".")[0] in PACKAGES]
    return sorted(found)


def upward_imports(package: str, root: Path = ROOT) -> list[str]:
    """``FILE:LINE imports PACKAGE`` for each import of ``root/package`` that the rule forbids."""
    return [f"{path.relative_to(root)}:{line} imports {target}"
            for path in sorted((root / package).rglob("*.py"))
            for line, target in imported_packages(path, package) if target not in ALLOWED[package]]


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_point_down_only(package: str) -> None:
    assert (ROOT / package).is_dir()
    assert upward_imports(package) == []


def test_the_rule_sees_every_kind_of_import(tmp_path: Path) -> None:
    """Upward imports at any depth, relative imports and allowed ones (so the test above can fail)."""
    (tmp_path / "model" / "sub").mkdir(parents=True)
    (tmp_path / "model" / "sub" / "probe.py").write_text(
        "from imaging.errors import ConfigError\nfrom . import loss\nif False:\n    import scenes\n"
        "def f():\n    if True:\n        from pipeline.run import run\n"
        "    import os, benchmarks.evaluate\n")
    assert upward_imports("model", tmp_path) == ["model/sub/probe.py:4 imports scenes",
                                                 "model/sub/probe.py:7 imports pipeline",
                                                 "model/sub/probe.py:8 imports benchmarks"]
