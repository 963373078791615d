"""generate-dataset on a Dask LocalCluster: same files as the local path, retries, lost workers, resume."""
from __future__ import annotations

import functools
import logging
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dataset_gen import cluster
from dataset_gen.cli import main as cli_main
from dataset_gen.config import DatasetConfig, DatasetError
from dataset_gen.generate import generate_dataset
from dataset_gen.jobs import run_job
from dataset_gen.manifest import read_records
from pipeline.atomic_io import TMP_PREFIX

pytest.importorskip("distributed")

CFG = DatasetConfig(res=(32, 32), spp=(1, 2), ref_spp=4, families=("cornell_box", "material_preview"), seed=5,
                    val_fraction=0.5)
CFG_ARGS = ["--res", "32", "--spp", "1,2", "--ref-spp", "4", "--families", "cornell_box,material_preview",
            "--seed", "5", "--val-fraction", "0.5", "--quiet"]


class _Bar:
    """Records what generate_dataset reports to its progress bar."""

    def __init__(self, total: int) -> None:
        self.total, self.n = total, 0

    def update(self, n: int = 1) -> None:
        self.n += n

    def set_postfix_str(self, s: str) -> None:
        pass

    def write(self, s: str) -> None:
        pass

    def close(self) -> None:
        pass


def _attempt(folder: Path, index: int) -> int:
    """Count this attempt at scene ``index`` in a file beside the dataset; return its number."""
    marks = folder.parent / "attempts"
    marks.mkdir(exist_ok=True)
    with open(marks / str(index), "a") as fh:
        fh.write(f"{os.getpid()}\n")
    return len((marks / str(index)).read_text().splitlines())


def flaky_job(cfg: DatasetConfig, index: int, folder: Path) -> dict[str, Any]:
    """Scene 0's first attempt raises; scene 1's first attempt kills its worker process."""
    attempt = _attempt(folder, index)
    if attempt == 1 and index == 0:
        raise RuntimeError("transient failure")
    if attempt == 1 and index == 1:
        os._exit(1)  # the worker dies mid-task, as on a lost machine
    return run_job(cfg, index, folder)


def broken_job(cfg: DatasetConfig, index: int, folder: Path) -> dict[str, Any]:
    """Scene 1 always fails (after leaving a partial temporary file)."""
    if index == 1:
        (folder / "images" / f"{TMP_PREFIX}partial.exr").write_bytes(b"partial")
        raise RuntimeError("broken scene")
    return run_job(cfg, index, folder)


def _without_timings(folder: Path) -> dict[int, dict[str, Any]]:
    return {r["index"]: {k: v for k, v in r.items() if k != "timings"} for r in read_records(folder)}


def _files(folder: Path) -> dict[str, bytes]:
    """Every image and scene file (XML, assets) by relative path."""
    return {str(p.relative_to(folder)): p.read_bytes() for sub in ("images", "scenes")
            for p in sorted((folder / sub).rglob("*")) if p.is_file()}


def test_parse_scheduler() -> None:
    assert cluster.parse_scheduler("local:2") == cluster.SchedulerSpec(local_workers=2)
    assert cluster.parse_scheduler("tcp://10.0.0.5:8786").address == "tcp://10.0.0.5:8786"
    assert str(cluster.parse_scheduler("local:3")) == "local:3"
    for bad in ("local:0", "local:x", "", "tcp://a b"):
        with pytest.raises(DatasetError, match="--scheduler"):
            cluster.parse_scheduler(bad)


@pytest.fixture(scope="module")
def scheduler() -> Iterator[cluster.SchedulerSpec]:
    """A 2-worker LocalCluster reached by its tcp:// address, as a remote scheduler would be."""
    from distributed import LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.CRITICAL) as local:
        yield cluster.SchedulerSpec(address=local.scheduler_address)


@pytest.mark.slow
def test_cli_local_cluster_matches_local_run(tmp_path: Path, capsys) -> None:
    local, dask = tmp_path / "local", tmp_path / "dask"
    generate_dataset(local, CFG, scenes=2)
    assert cli_main(["--scenes", "2", "--out", str(dask), *CFG_ARGS, "--scheduler", "local:2"]) == 0
    assert "2 scenes rendered" in capsys.readouterr().out
    assert _without_timings(dask) == _without_timings(local)  # lines may be in another order
    files = _files(local)
    assert sum(name.startswith("images/") for name in files) == 2 * 3
    assert files == _files(dask)  # byte-identical EXRs, scene XMLs and assets


@pytest.mark.slow
def test_failed_task_is_retried_and_lost_worker_rescheduled(scheduler: cluster.SchedulerSpec, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    folder = tmp_path / "ds"
    monkeypatch.setattr("dataset_gen.generate.render_on_cluster",
                        functools.partial(cluster.render_on_cluster, job=flaky_job))
    bars: list[_Bar] = []
    summary = generate_dataset(folder, CFG, scenes=2, make_progress=lambda n: bars.append(_Bar(n)) or bars[-1],
                               scheduler=scheduler)
    assert summary.done == 2 and not summary.failed
    assert (bars[0].total, bars[0].n) == (2, 2)  # driven by the completed futures
    assert sorted(r["index"] for r in read_records(folder)) == [0, 1]
    attempts = {i: (tmp_path / "attempts" / str(i)).read_text().split() for i in (0, 1)}
    assert len(attempts[0]) == 2  # raised once, retried
    assert len(attempts[1]) == 2 and attempts[1][0] != attempts[1][1]  # its worker died; rerun elsewhere


@pytest.mark.slow
def test_failed_scene_is_reported_and_rerun_resumes(scheduler: cluster.SchedulerSpec, tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    folder = tmp_path / "ds"
    with monkeypatch.context() as patch:
        patch.setattr("dataset_gen.generate.render_on_cluster",
                      functools.partial(cluster.render_on_cluster, job=broken_job, retries=1))
        summary = generate_dataset(folder, CFG, scenes=3, scheduler=scheduler)
    assert summary.done == 2 and len(summary.failed) == 1 and "broken scene" in summary.failed[0]
    assert sorted(r["index"] for r in read_records(folder)) == [0, 2]
    summary = generate_dataset(folder, CFG, scenes=3, scheduler=scheduler)
    assert (summary.skipped, summary.done) == (2, 1)
    assert sorted(r["index"] for r in read_records(folder)) == [0, 1, 2]
    assert not list(folder.rglob(f"{TMP_PREFIX}*"))


def test_cli_scheduler_errors(tmp_path: Path, capsys, monkeypatch) -> None:
    args = ["--scenes", "1", "--out", str(tmp_path / "ds"), "--res", "16", "--spp", "1", "--ref-spp", "2",
            "--quiet"]
    with pytest.raises(SystemExit) as exc:
        cli_main([*args, "--scheduler", "local:0"])
    assert exc.value.code == 2 and "local:N with N >= 1" in capsys.readouterr().err
    assert cli_main([*args, "--scheduler", "local:2", "--workers", "2"]) == 2
    assert "exclude each other" in capsys.readouterr().err
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 1)
    assert cli_main([*args, "--scheduler", "tcp://127.0.0.1:9"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in err
