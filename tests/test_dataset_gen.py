"""generate-dataset: determinism, resumability, crash safety, refusing other settings."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dataset_gen import jobs
from dataset_gen.cli import main as cli_main
from dataset_gen.config import DatasetConfig, open_dataset
from dataset_gen.generate import generate_dataset
from dataset_gen.manifest import MANIFEST_NAME, append_record, read_records, repair
from imaging.atomic_io import TMP_PREFIX
from imaging.errors import DatasetError
from imaging.exr import read_exr
from imaging.naming import image_name

TINY = DatasetConfig(res=(16, 16), spp=(1, 2), ref_spp=4, families=("cornell_box", "material_preview"), seed=3,
                     val_fraction=0.5)
TINY_ARGS = ["--res", "16", "--spp", "1,2", "--ref-spp", "4", "--families", "cornell_box,material_preview",
             "--seed", "3", "--val-fraction", "0.5", "--quiet"]


def _pixels(folder: Path, index: int) -> list[np.ndarray]:
    return [read_exr(folder / "images" / image_name(index, s)).rgb for s in (1, 2, None)]


def _no_temporaries(folder: Path) -> bool:
    return not [p for p in folder.rglob(f"{TMP_PREFIX}*")]


def test_scene_seeds_are_deterministic_and_cover_families() -> None:
    cfg = DatasetConfig(families=("a", "b", "c"), seed=1)
    assert jobs.scene_seeds(cfg, 5) == jobs.scene_seeds(cfg, 5)
    assert jobs.scene_seeds(cfg, 5).scene_seed != jobs.scene_seeds(cfg, 6).scene_seed
    assert [jobs.scene_seeds(cfg, i).family for i in range(3)] == ["a", "b", "c"]
    splits = [jobs.scene_seeds(cfg, i).split for i in range(300)]
    assert 15 < splits.count("val") < 50  # val_fraction 0.1 of 300
    val_families = {jobs.scene_seeds(cfg, i).family for i in range(300) if splits[i] == "val"}
    assert val_families == {"a", "b", "c"}


def test_reference_noise_estimate() -> None:
    rng = np.random.default_rng(0)
    truth = np.full((64, 64, 3), 0.5)
    halves = [truth + rng.normal(0, 0.02, truth.shape) for _ in range(2)]
    noise = jobs.reference_noise(*halves)
    mean = 0.5 * (halves[0] + halves[1])
    actual = float(np.mean((mean - truth) ** 2 / (truth**2 + 0.01)))
    assert noise["relmse"] == pytest.approx(actual, rel=0.1)
    assert noise["psnr_ceiling_db"] > 40


def test_generate_is_deterministic_and_complete(tmp_path: Path) -> None:
    a, b = tmp_path / "a", tmp_path / "b"
    summary = generate_dataset(a, TINY, scenes=2)
    generate_dataset(b, TINY, scenes=2)
    assert summary.done == 2 and not summary.failed and summary.render_s > 0
    recs = read_records(a)
    assert [r["index"] for r in recs] == [0, 1]
    assert [r["family"] for r in recs] == ["cornell_box", "material_preview"]
    for rec in recs:
        assert rec["filter"] == "box" and rec["mitsuba"] == "3.9.1" and rec["ref_spp"] == 4
        assert np.isfinite(rec["ref_noise"]["relmse"])
        assert (a / "scenes" / rec["scene"] / "scene.xml").exists()
        for x, y in zip(_pixels(a, rec["index"]), _pixels(b, rec["index"])):
            assert np.array_equal(x, y) and np.isfinite(x).all()
    assert json.loads((a / "dataset.json").read_text())["spp"] == [1, 2]
    assert read_exr(a / "images" / image_name(0, 2)).metadata["spp"] == 2


def test_rerun_skips_finished_and_grows(tmp_path: Path) -> None:
    generate_dataset(tmp_path, TINY, scenes=1)
    summary = generate_dataset(tmp_path, TINY, scenes=2)
    assert (summary.skipped, summary.done) == (1, 1)
    assert [r["index"] for r in read_records(tmp_path)] == [0, 1]


def test_other_settings_are_refused(tmp_path: Path) -> None:
    generate_dataset(tmp_path, TINY, scenes=1)
    other = DatasetConfig(**{**TINY.to_json(), "ref_spp": 8, "families": TINY.families,
                             "spp": TINY.spp, "res": TINY.res, "aovs": ()})
    with pytest.raises(DatasetError, match=r"other settings \(ref_spp: 4 vs 8\)"):
        generate_dataset(tmp_path, other, scenes=1)


def test_failed_job_is_not_listed_and_rerun_completes(tmp_path: Path, monkeypatch) -> None:
    real = jobs.run_job

    def crash_on_one(cfg, index, folder):
        if index == 1:
            (folder / "images" / f"{TMP_PREFIX}half.exr").write_bytes(b"partial")
            raise RuntimeError("worker died")
        return real(cfg, index, folder)

    monkeypatch.setattr("dataset_gen.generate.run_job", crash_on_one)
    summary = generate_dataset(tmp_path, TINY, scenes=3)
    assert summary.done == 2 and len(summary.failed) == 1 and "worker died" in summary.failed[0]
    assert [r["index"] for r in read_records(tmp_path)] == [0, 2]
    monkeypatch.setattr("dataset_gen.generate.run_job", real)
    summary = generate_dataset(tmp_path, TINY, scenes=3)
    assert summary.done == 1 and sorted(r["index"] for r in read_records(tmp_path)) == [0, 1, 2]
    assert _no_temporaries(tmp_path)


def test_torn_manifest_line_is_ignored_and_repaired(tmp_path: Path) -> None:
    append_record(tmp_path, {"index": 0})
    with open(tmp_path / MANIFEST_NAME, "a") as fh:
        fh.write('{"index": 1, "fam')
    assert [r["index"] for r in read_records(tmp_path)] == [0]
    repair(tmp_path)
    append_record(tmp_path, {"index": 2})
    assert [r["index"] for r in read_records(tmp_path)] == [0, 2]


@pytest.mark.slow
def test_kill_9_mid_run_then_resume_matches_clean_run(tmp_path: Path) -> None:
    killed, clean = tmp_path / "killed", tmp_path / "clean"
    args = [sys.executable, "-m", "dataset_gen.cli", "--scenes", "6", "--out", str(killed), *TINY_ARGS]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and len(read_records(killed)) < 2 and proc.poll() is None:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    partial = {r["index"] for r in read_records(killed)}
    assert partial, "the run should have finished some scenes before the kill"
    assert cli_main(["--scenes", "6", "--out", str(killed), *TINY_ARGS]) == 0
    assert cli_main(["--scenes", "6", "--out", str(clean), *TINY_ARGS]) == 0
    assert sorted(r["index"] for r in read_records(killed)) == list(range(6))
    assert _no_temporaries(killed)
    for i in range(6):
        for x, y in zip(_pixels(killed, i), _pixels(clean, i)):
            assert np.array_equal(x, y)


def test_cli_errors_are_one_line(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit) as exc:  # a usage error, as every command's
        cli_main(["--scenes", "1", "--out", str(tmp_path / "x"), "--families", "nope"])
    err = capsys.readouterr().err.strip()
    assert exc.value.code == 2 and "\n" not in err
    assert err.startswith("generate-dataset: error: unknown family 'nope'")
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert cli_main(["--scenes", "1", "--out", str(blocker), *TINY_ARGS]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "not a directory" in err


def test_cli_refuses_a_folder_that_holds_no_dataset_and_touches_nothing(tmp_path: Path, capsys) -> None:
    """A folder of someone else's files is refused in one line, nothing in it written, moved or removed;
    a folder empty but for a crash's temporary is taken (open_dataset writes only dataset.json)."""
    mine = tmp_path / "mine"
    (mine / "sub").mkdir(parents=True)
    (mine / "notes.txt").write_text("mine")
    (mine / "sub" / f"{TMP_PREFIX}keep").write_text("mine too")
    before = sorted((p.relative_to(mine), p.stat().st_mtime_ns, p.is_file() and p.read_bytes())
                    for p in mine.rglob("*"))
    assert cli_main(["--scenes", "1", "--out", str(mine), *TINY_ARGS]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and f"{mine}: is not empty and holds no dataset (dataset.json)" in err
    assert sorted((p.relative_to(mine), p.stat().st_mtime_ns, p.is_file() and p.read_bytes())
                  for p in mine.rglob("*")) == before
    crashed = tmp_path / "crashed"
    crashed.mkdir()
    (crashed / f"{TMP_PREFIX}dataset.json").write_text("{")
    assert open_dataset(crashed, TINY) == TINY and (crashed / "dataset.json").exists()


def test_cli_writes_dataset_and_preview(tmp_path: Path, capsys) -> None:
    assert cli_main(["--scenes", "2", "--out", str(tmp_path), "--preview", *TINY_ARGS]) == 0
    out = capsys.readouterr().out
    assert "2 scenes rendered" in out and (tmp_path / "preview.png").stat().st_size > 0


def test_variance_files_estimate_the_noise_of_each_noisy_image(tmp_path: Path) -> None:
    """--variance: every noisy image of >= 2 spp gets its two-halves variance estimate (none at
    1 spp); over many pixels it matches the squared error against a high-spp reference."""
    cfg = DatasetConfig(res=(32, 32), spp=(1, 4, 16), ref_spp=256, families=("cornell_box",), seed=2,
                        val_fraction=0.0, variance=True)
    summary = generate_dataset(tmp_path, cfg, 1)
    assert summary.done == 1 and not summary.failed
    record = read_records(tmp_path)[0]
    assert record["variance_spp"] == [4, 16]
    images = tmp_path / "images"
    assert not (images / image_name(0, 1, "var")).exists()
    ref = read_exr(images / image_name(0, None)).rgb
    for spp in (4, 16):
        var = read_exr(images / image_name(0, spp, "var")).rgb
        noisy = read_exr(images / image_name(0, spp)).rgb
        assert var.shape == noisy.shape and np.isfinite(var).all() and (var >= 0).all()
        estimated, actual = float(var.mean()), float(((noisy - ref) ** 2).mean())
        assert 0.3 * actual < estimated < 3.0 * actual  # one degree of freedom per pixel, 3072 values
    with pytest.raises(DatasetError, match="variance"):
        generate_dataset(tmp_path, DatasetConfig(**{**cfg.to_json(), "variance": False, "families": ("cornell_box",)}), 1)


def test_variance_flag_reaches_the_config(tmp_path: Path) -> None:
    assert cli_main([*TINY_ARGS, "--scenes", "1", "--out", str(tmp_path / "d"), "--variance"]) == 0
    saved = json.loads((tmp_path / "d" / "dataset.json").read_text())
    assert saved["variance"] is True
    assert (tmp_path / "d" / "images" / image_name(0, 2, "var")).exists()


def test_pixel_filter_is_rendered_and_recorded(tmp_path: Path, capsys) -> None:
    """--pixel-filter: dataset.json and every image's header say it; a folder made with another
    filter is refused; an unknown filter is a usage error."""
    out = tmp_path / "g"
    assert cli_main([*TINY_ARGS, "--scenes", "1", "--out", str(out), "--pixel-filter", "gaussian:stddev=0.4"]) == 0
    saved = json.loads((out / "dataset.json").read_text())
    assert saved["filter"] == {"type": "gaussian", "stddev": 0.4}
    assert read_exr(out / "images" / image_name(0, 2)).metadata["filter"] == "gaussian:stddev=0.4"
    assert cli_main([*TINY_ARGS, "--scenes", "2", "--out", str(out)]) == 1
    assert "generated with other settings (filter: " in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        cli_main([*TINY_ARGS, "--scenes", "1", "--out", str(tmp_path / "b"), "--pixel-filter", "blackman"])
    assert exc.value.code == 2 and "unknown pixel filter 'blackman'" in capsys.readouterr().err


def test_scene_files_are_the_scenes(tmp_path: Path, capsys) -> None:
    """--scene-files: scene i is file i (a folder gives its *.xml, sorted), rendered at --res;
    --scenes defaults to one per file and may not exceed them."""
    from scenes.registry import generate
    from scenes.xml_export import write_scene

    paths = [str(write_scene(generate(family, i), tmp_path / "mine" / f"{i}"))
             for i, family in enumerate(("cornell_box", "material_preview"))]
    out = tmp_path / "d"
    assert cli_main(["--scene-files", *paths, "--out", str(out), "--res", "16", "--spp", "1,2", "--ref-spp", "4",
                     "--quiet"]) == 0
    records = read_records(out)
    assert [r["family"] for r in records] == ["scene-file"] * 2
    assert [r["scene_file"] for r in records] == [str(Path(p).resolve()) for p in paths]
    assert read_exr(out / "images" / image_name(1, 2)).rgb.shape == (16, 16, 3)
    assert json.loads((out / "dataset.json").read_text())["families"] == []
    assert cli_main(["--scene-files", paths[0], "--scenes", "3", "--out", str(tmp_path / "e"), "--quiet"]) == 1
    assert "--scenes 3: only 1 scene file(s) given" in capsys.readouterr().err
    assert cli_main(["--scene-files", str(tmp_path / "none.xml"), "--out", str(tmp_path / "f"), "--quiet"]) == 1
    assert "none.xml: scene file not found" in capsys.readouterr().err


def test_a_resolution_too_large_for_the_memory_is_refused_before_any_scene(
        tmp_path: Path, capsys, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--res 100000``: one line naming the size, the bytes and the memory left (64 GiB here),
    before the folder is made; not a failure of every scene."""
    import imaging.memory_limit

    monkeypatch.setattr(imaging.memory_limit, "available_bytes", lambda: 64 * 2**30)
    args = [arg if arg != "16" else "100000" for arg in TINY_ARGS]
    assert cli_main(["--scenes", "3", "--out", str(tmp_path / "ds"), *args]) == 1
    captured = capsys.readouterr()
    assert captured.err.strip() == ("generate-dataset: error: 100000x100000 pixels: 1 float32 image (rgb) and the "
                                    "render's scratch need 115,465 MB, more than the 65,536 MB of memory available")
    assert not (tmp_path / "ds").exists()


def test_any_scene_count_starts_at_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``--scenes 10**12``: the scenes to do are made one at a time (a list of them would not fit),
    so the first job starts at once."""
    started: list[int] = []

    def first_only(cfg: DatasetConfig, index: int, folder: Path) -> dict:
        started.append(index)
        raise KeyboardInterrupt

    import resource

    from dataset_gen.generate import with_runtime
    from imaging import memory_limit

    with_runtime(TINY)  # Mitsuba loaded before the limit
    monkeypatch.setattr("dataset_gen.generate.run_job", first_only)
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    size = memory_limit.kb_field(memory_limit._STATUS, "VmSize") or 0
    resource.setrlimit(resource.RLIMIT_AS, (size + 2**30, hard))  # a list would fail, not fill the machine
    try:
        with pytest.raises(KeyboardInterrupt):
            generate_dataset(tmp_path / "ds", TINY, scenes=10**12, workers=1)
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
    assert started == [0]


@pytest.mark.slow
def test_a_process_pool_renders_every_scene_two_jobs_a_worker_at_a_time(tmp_path: Path) -> None:
    """Two workers hold at most four jobs: the fifth scene is submitted as one finishes."""
    summary = generate_dataset(tmp_path / "ds", TINY, scenes=5, workers=2)
    assert (summary.done, summary.failed) == (5, [])
    assert sorted(r["index"] for r in read_records(tmp_path / "ds")) == [0, 1, 2, 3, 4]
