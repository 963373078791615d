"""Dataset generation on a Dask cluster: one task per scene; only this client writes the manifest.

``--scheduler tcp://host:8786`` connects to a running Dask scheduler; ``--scheduler local:N``
starts a ``LocalCluster`` of N single-threaded worker processes on this machine (for trying it
out). Each task runs :func:`dataset_gen.jobs.run_job`, the function the local pool runs: a scene's
files depend only on (dataset seed, scene index), so any worker renders the same images.

Guarantees, as on one machine:

- Workers write every file atomically straight into the dataset folder, which must therefore be
  shared storage mounted at the same absolute path on every worker (NFS, a cluster file system).
- The manifest line of a scene is appended by this client process only, after its task returned.
- A task that raises is retried ``retries`` times (Dask's ``retries=``); a task whose worker dies
  is rescheduled on another worker by the scheduler (up to its ``allowed-failures``, 3 by default).
  A scene that still fails is reported; re-running the command retries it and skips finished ones.
- A worker whose Mitsuba version or variant differs from the dataset's refuses the scene.
"""
from __future__ import annotations

import contextlib
import logging
import os
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from dataset_gen.config import DatasetConfig, DatasetError
from dataset_gen.jobs import run_job

LOCAL_PREFIX = "local:"
DEFAULT_RETRIES = 2
CONNECT_TIMEOUT_S = 30

Job = Callable[[DatasetConfig, int, Path], dict[str, Any]]
Finish = Callable[[int, "dict[str, Any] | None", "BaseException | None"], None]


@dataclass(frozen=True)
class SchedulerSpec:
    """Where scene tasks go: a scheduler ``address`` (``tcp://host:8786``) or, when
    ``local_workers`` > 0, a LocalCluster of that many worker processes started here."""

    address: str | None = None
    local_workers: int = 0

    def __str__(self) -> str:
        return f"{LOCAL_PREFIX}{self.local_workers}" if self.local_workers else str(self.address)


def parse_scheduler(text: str) -> SchedulerSpec:
    """``local:N`` or a scheduler address (``tcp://host:port``, ``host:port``...)."""
    text = text.strip()
    if text.startswith(LOCAL_PREFIX):
        count = text[len(LOCAL_PREFIX):]
        if not count.isdigit() or int(count) < 1:
            raise DatasetError(f"--scheduler {text}: expected local:N with N >= 1 worker processes")
        return SchedulerSpec(local_workers=int(count))
    if not text or any(c.isspace() for c in text):
        raise DatasetError(f"--scheduler {text!r}: expected a scheduler address (tcp://host:8786) or local:N")
    return SchedulerSpec(address=text)


@contextlib.contextmanager
def connect(spec: SchedulerSpec) -> Iterator[Any]:
    """A ``distributed.Client`` for ``spec``; a LocalCluster is started and shut down with it."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise DatasetError("--scheduler needs Dask: pip install 'mc-densenet-denoiser[cluster]'") from None
    if spec.local_workers:
        with LocalCluster(n_workers=spec.local_workers, threads_per_worker=1, processes=True,
                          dashboard_address=None, silence_logs=logging.CRITICAL) as cluster, \
                Client(cluster) as client:
            yield client
        return
    try:
        client = Client(spec.address, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError, ValueError) as exc:
        raise DatasetError(f"cannot reach the Dask scheduler at {spec.address} ({exc})") from None
    with client:
        yield client


def local_threads(spec: SchedulerSpec) -> int | None:
    """Mitsuba threads per worker: this machine's cores shared among local workers, but at least
    2 (with 1 thread Dr.Jit deadlocks loading a scene with textures, measured with mitsuba 3.9.1);
    None (all of the worker machine's cores) for a remote cluster, one task per worker at a time."""
    return max(2, (os.cpu_count() or 1) // spec.local_workers) if spec.local_workers else None


def cluster_job(cfg: DatasetConfig, index: int, folder: Path, threads: int | None,
                job: Job = run_job) -> dict[str, Any]:
    """Worker side of one scene task: check this worker's Mitsuba, then ``job(cfg, index, folder)``."""
    from pipeline.backend import select_variant

    variant = select_variant()
    version = metadata.version("mitsuba")
    if (version, variant) != (cfg.mitsuba, cfg.variant):
        raise DatasetError(f"worker has Mitsuba {version} {variant}, the dataset was started with "
                           f"{cfg.mitsuba} {cfg.variant}; install the same on every worker")
    if threads:
        import drjit as dr

        dr.set_thread_count(threads)
    return job(cfg, index, folder)


def render_on_cluster(spec: SchedulerSpec, cfg: DatasetConfig, todo: Sequence[int], folder: Path,
                      finish: Finish, retries: int = DEFAULT_RETRIES, job: Job = run_job) -> None:
    """Submit one task per scene of ``todo``; call ``finish(index, record, error)`` as each completes.

    ``finish`` runs in this process, in completion order (it appends the manifest and drives the
    progress bar). ``job`` defaults to :func:`run_job` (tests pass a wrapper that fails once).
    """
    if not todo:
        return
    from distributed import as_completed

    folder = folder.resolve()
    threads = local_threads(spec)
    batch = uuid.uuid4().hex[:8]  # unique keys: a long-lived scheduler may remember older runs
    with connect(spec) as client:
        futures = {client.submit(cluster_job, cfg, index, folder, threads, job, retries=retries,
                                 key=f"scene-{index:06d}-{batch}"): index for index in todo}
        for future in as_completed(futures):
            index = futures[future]
            error = future.exception() if future.status == "error" else None
            if error is None and future.status != "finished":
                error = DatasetError(f"task {future.status}")
            finish(index, None if error is not None else future.result(), error)
            future.release()
