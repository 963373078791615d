"""generate-dataset on a Dask LocalCluster: same files as the local path, retries of transient
failures only, lost workers, workers with other code refused, resume."""
from __future__ import annotations

import functools
import logging
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from dataset_gen import cluster
from dataset_gen.cli import main as cli_main
from dataset_gen.code_version import PACKAGES, ROOT, CodeVersion, code_version, source_hash
from dataset_gen.config import DatasetConfig
from dataset_gen.generate import generate_dataset
from dataset_gen.jobs import run_job
from dataset_gen.manifest import read_records
from imaging.atomic_io import TMP_PREFIX
from imaging.errors import DatasetError, SceneError

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
    """Scene 0's first attempt raises an OSError; scene 1's first attempt kills its worker process."""
    attempt = _attempt(folder, index)
    if attempt == 1 and index == 0:
        raise OSError("transient failure (a file server that did not answer)")
    if attempt == 1 and index == 1:
        os._exit(1)  # the worker dies mid-task, as on a lost machine
    return run_job(cfg, index, folder)


def broken_job(cfg: DatasetConfig, index: int, folder: Path) -> dict[str, Any]:
    """Scene 1 always fails (after leaving a partial temporary file)."""
    if index == 1:
        (folder / "images" / f"{TMP_PREFIX}partial.exr").write_bytes(b"partial")
        raise RuntimeError("broken scene")
    return run_job(cfg, index, folder)


def bad_scene_job(error: type[Exception], cfg: DatasetConfig, index: int, folder: Path) -> dict[str, Any]:
    """Scene 1 fails as a scene with bad parameters or invalid XML does: every time, anywhere."""
    _attempt(folder, index)
    if index == 1:
        raise error("scene 1: invalid XML (bad parameters)")
    return run_job(cfg, index, folder)


def killing_job(cfg: DatasetConfig, index: int, folder: Path) -> dict[str, Any]:
    """Scene 0's first attempt kills its worker."""
    if _attempt(folder, index) == 1 and index == 0:
        os._exit(1)
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
                      functools.partial(cluster.render_on_cluster, job=broken_job, retries=1, window=2))  # the third scene waits for a slot
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
    with pytest.raises(SystemExit) as exc:
        cli_main([*args, "--scheduler", "local:2", "--workers", "2"])
    assert exc.value.code == 2 and "exclude each other" in capsys.readouterr().err
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT_S", 1)
    assert cli_main([*args, "--scheduler", "tcp://127.0.0.1:9"]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in err


# ----------------------------------------------------------------------------- failures and retries
@pytest.mark.slow
@pytest.mark.parametrize("error", [SceneError, ValueError])
def test_deterministic_failure_is_not_retried(scheduler: cluster.SchedulerSpec, tmp_path: Path,
                                              monkeypatch: pytest.MonkeyPatch, error: type[Exception]) -> None:
    folder = tmp_path / "ds"
    monkeypatch.setattr("dataset_gen.generate.render_on_cluster",
                        functools.partial(cluster.render_on_cluster, job=functools.partial(bad_scene_job, error)))
    summary = generate_dataset(folder, CFG, scenes=2, scheduler=scheduler)
    assert summary.done == 1 and len(summary.failed) == 1 and "scene 1: invalid XML" in summary.failed[0]
    assert len((tmp_path / "attempts" / "1").read_text().split()) == 1  # rendered once, not three times
    assert sorted(r["index"] for r in read_records(folder)) == [0]


def test_failures_are_classified() -> None:
    from distributed.scheduler import KilledWorker

    for error in (SceneError("x"), DatasetError("x"), ValueError("x"), TypeError("x")):
        assert cluster.is_deterministic(error), error
    for error in (OSError("x"), KilledWorker("scene-1", None, 0), RuntimeError("x"), MemoryError()):
        assert not cluster.is_deterministic(error), error


@pytest.mark.slow
def test_killed_worker_is_submitted_again(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With allowed-failures 0 the scheduler gives up on the first lost worker (KilledWorker):
    the client submits the scene again."""
    import dask
    from distributed import LocalCluster

    folder = tmp_path / "ds"
    monkeypatch.setattr("dataset_gen.generate.render_on_cluster",
                        functools.partial(cluster.render_on_cluster, job=killing_job))
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}), \
            LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None,
                         silence_logs=logging.CRITICAL) as local:
        summary = generate_dataset(folder, CFG, scenes=1,
                                   scheduler=cluster.SchedulerSpec(address=local.scheduler_address))
    assert summary.done == 1 and not summary.failed
    assert len((tmp_path / "attempts" / "0").read_text().split()) == 2


# ----------------------------------------------------------------------------- the workers' code
def _copy_project(into: Path) -> Path:
    """The project's packages copied to ``into`` (no .git, no weights): what a worker installs."""
    for package in PACKAGES:
        shutil.copytree(ROOT / package, into / package, ignore=shutil.ignore_patterns("__pycache__", "weights"))
    return into


def test_code_version_identifies_the_source(tmp_path: Path) -> None:
    from importlib import metadata

    here = code_version.__wrapped__()  # now: the tree may have changed since the cached call
    assert here.package == metadata.version("mc-densenet-denoiser") and len(here.source) == 12
    copy = _copy_project(tmp_path / "copy")
    assert code_version(copy).commit is None and code_version(copy).same_code(here)  # no git, same code
    (copy / "dataset_gen" / "jobs.py").write_text((copy / "dataset_gen" / "jobs.py").read_text() + "# edited\n")
    assert source_hash(copy) != here.source
    git = ["git", "-C", str(copy), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run([*git, "init", "-q"], check=True)
    subprocess.run([*git, "add", "."], check=True)
    subprocess.run([*git, "commit", "-q", "-m", "x"], check=True)
    committed = code_version.__wrapped__(copy)
    assert committed.commit is not None and len(committed.commit) == 12 and not committed.modified
    assert str(committed) == f"{here.package} (git {committed.commit}, source {committed.source})"
    (copy / "model" / "new.py").write_text("x = 1\n")
    assert code_version.__wrapped__(copy).modified


def test_check_code_names_both_versions_in_one_line() -> None:
    client = CodeVersion("0.1.0", "aaaaaaaaaaaa", "1234567890ab", False)
    cluster.check_code(client, {"worker tcp://a:1": client.to_dict()})
    other = CodeVersion("0.1.0", "bbbbbbbbbbbb")
    with pytest.raises(DatasetError) as exc:
        cluster.check_code(client, {"worker tcp://a:1": client.to_dict(), "worker tcp://b:2": other.to_dict()})
    message = str(exc.value)
    assert "\n" not in message and message.startswith("worker tcp://b:2 runs mc-densenet-denoiser 0.1.0 "
                                                      "(source bbbbbbbbbbbb), the client runs 0.1.0 "
                                                      "(git 1234567890ab, source aaaaaaaaaaaa)")
    with pytest.raises(DatasetError, match="runs mc-densenet-denoiser unknown"):  # a worker of older code
        cluster.check_code(client, {"worker tcp://c:3": {}})


@pytest.fixture
def other_code_worker(tmp_path: Path) -> Iterator[cluster.SchedulerSpec]:
    """A scheduler with one ``dask worker`` process running an edited copy of the project."""
    from distributed import Client, LocalCluster

    copy = _copy_project(tmp_path / "worker-code")
    (copy / "scenes" / "registry.py").write_text((copy / "scenes" / "registry.py").read_text() + "# edited\n")
    with LocalCluster(n_workers=0, processes=True, dashboard_address=None, silence_logs=logging.CRITICAL) as local:
        worker = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", local.scheduler_address,
                                   "--nworkers", "1", "--nthreads", "1", "--no-dashboard"], cwd=copy,
                                  env={**os.environ, "PYTHONPATH": str(copy)}, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL)
        try:
            with Client(local.scheduler_address) as client:
                client.wait_for_workers(1, timeout=120)
            yield cluster.SchedulerSpec(address=local.scheduler_address)
        finally:
            worker.terminate()
            try:
                worker.wait(30)
            except subprocess.TimeoutExpired:
                worker.kill()
                worker.wait()


@pytest.mark.slow
def test_worker_with_other_code_is_refused_at_submission(other_code_worker: cluster.SchedulerSpec,
                                                         tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "ds"
    assert cli_main(["--scenes", "2", "--out", str(out), *CFG_ARGS, "--scheduler", other_code_worker.address]) == 1
    err = capsys.readouterr().err.strip()
    mine = code_version()
    assert "\n" not in err and err.startswith("generate-dataset: error: worker tcp://"), err
    assert f"the client runs {mine}" in err and "runs mc-densenet-denoiser 0.1.0 (source " in err
    assert str(mine.source) not in err.split("the client runs")[0]  # the worker's source hash differs
    assert not (out / "images").exists() or not list((out / "images").iterdir())  # nothing was rendered
    assert not read_records(out)
