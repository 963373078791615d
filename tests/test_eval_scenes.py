"""The one listing of ../shared/eval-scenes that every benchmark uses."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.eval_scenes import EVAL_DIR, SEED, eval_scenes, finish_record, run_record
from imaging.errors import DenoiserError


def _scene(root: Path, name: str, reference: bool = True) -> None:
    (root / name).mkdir(parents=True)
    (root / name / "scene.xml").write_text("<scene version='3.0.0'/>")
    if reference:
        (root / name / "reference.exr").write_bytes(b"")
        (root / name / "reference.json").write_text(json.dumps({"reference_psnr_ceiling_db": 41.5,
                                                                "shape": [12, 16, 3]}))


def test_lists_scene_folders_with_a_reference_by_name(tmp_path: Path) -> None:
    for name in ("b", "a"):
        _scene(tmp_path, name)
    _scene(tmp_path, "no_reference", reference=False)
    (tmp_path / "README.md").write_text("")
    scenes = eval_scenes(eval_dir=tmp_path)
    assert [s.name for s in scenes] == ["a", "b"]
    assert scenes[0].ceiling_db == 41.5 and scenes[0].resolution == (16, 12)
    settings = scenes[0].settings()
    assert settings.seed == SEED and settings.resolution == (16, 12) and settings.noise_guard
    assert settings.reference == str(tmp_path / "a" / "reference.exr")
    assert [s.name for s in eval_scenes(["b"], tmp_path)] == ["b"]


def test_unknown_names_and_a_missing_folder_are_errors(tmp_path: Path) -> None:
    _scene(tmp_path, "a")
    with pytest.raises(DenoiserError, match="unknown scene.*: nope"):
        eval_scenes(["a", "nope"], tmp_path)
    with pytest.raises(DenoiserError, match="evaluation scenes not found"):
        eval_scenes(eval_dir=tmp_path / "missing")


@pytest.mark.skipif(not EVAL_DIR.is_dir(), reason="../shared/eval-scenes is not here")
def test_the_shared_scenes() -> None:
    scenes = eval_scenes()
    assert len(scenes) == 17 and all(s.resolution[0] > 0 and s.ceiling_db > 0 for s in scenes)


def test_run_record_names_the_command_and_the_load() -> None:
    record = finish_record(run_record("benchmarks.x", ["--scenes", "a b"]), 0.0)
    assert record["command"] == "python -m benchmarks.x --scenes 'a b'"
    assert record["machine"]["cores"] >= 1 and record["machine"]["load_after"] >= 0 and record["wall_s"] > 0
