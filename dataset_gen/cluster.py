"""Dataset generation on a Dask cluster: one task per scene; only this client writes the manifest.

``--scheduler tcp://host:8786`` connects to a running Dask scheduler; ``--scheduler local:N``
starts a ``LocalCluster`` of N single-threaded worker processes on this machine (for trying it
out). Each task runs :func:`dataset_gen.jobs.run_job`, the function the local pool runs: a scene's
files depend only on (dataset seed, scene index), so any worker renders the same images.

Guarantees, as on one machine:

- Workers write every file atomically straight into the dataset folder, which must therefore be
  shared storage mounted at the same absolute path on every worker (NFS, a cluster file system).
- The manifest line of a scene is appended by this client process only, after its task returned.
- Every worker runs the client's code: before anything is submitted, each connected worker
  reports its :class:`~dataset_gen.code_version.CodeVersion` and one that differs stops the run
  with a one-line error naming both; a worker that joins later refuses the scenes it is given.
  A worker whose Mitsuba version or variant differs from the dataset's refuses the scene too.
- A scene that fails deterministically (:data:`DETERMINISTIC`: bad scene parameters, invalid XML,
  a refused worker) is reported at once; any other failure is transient and the scene is
  submitted again, up to ``retries`` times: a lost worker (Dask reruns the task itself up to the
  scheduler's ``allowed-failures``, 3 by default, then reports ``KilledWorker``), an OSError...
  A scene that still fails is reported; re-running the command retries it and skips finished ones.
"""
from __future__ import annotations

import contextlib
import itertools
import logging
import os
import uuid
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import Any

from dataset_gen.code_version import DIST, CodeVersion, code_version, worker_code_version
from dataset_gen.config import DatasetConfig
from dataset_gen.jobs import run_job
from imaging.errors import DatasetError, DenoiserError

LOCAL_PREFIX = "local:"
DEFAULT_RETRIES = 2
CONNECT_TIMEOUT_S = 30
WINDOW = 1024  # scene tasks submitted at once: enough to keep that many worker threads busy, and no
# more client and scheduler memory whatever the scene count

# Failures that recur whatever the worker: our own errors (SceneError, RenderError, DatasetError...)
# and what scene generation raises for bad parameters. Not retried.
DETERMINISTIC: tuple[type[BaseException], ...] = (DenoiserError, ValueError, TypeError)

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
                job: Job = run_job, client_code: dict[str, Any] | None = None) -> dict[str, Any]:
    """Worker side of one scene task: check this worker's code and Mitsuba against the client's
    (``client_code``: its :class:`CodeVersion` as a dict), then ``job(cfg, index, folder)``."""
    from rendering.backend import select_variant

    if client_code is not None:
        check_code(CodeVersion.from_dict(client_code), {_worker_name(): worker_code_version()})
    variant = select_variant()
    version = metadata.version("mitsuba")
    if (version, variant) != (cfg.mitsuba, cfg.variant):
        raise DatasetError(f"worker has Mitsuba {version} {variant}, the dataset was started with "
                           f"{cfg.mitsuba} {cfg.variant}; install the same on every worker")
    if threads:
        import drjit as dr

        dr.set_thread_count(threads)
    return job(cfg, index, folder)


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return f"worker {get_worker().address}"
    except (ImportError, ValueError):  # called outside a Dask worker
        return "this process"


def check_code(client: CodeVersion, workers: dict[str, dict[str, Any]]) -> None:
    """Raise :class:`DatasetError` (one line, both versions) if a worker's code is not the client's.

    ``workers`` maps a worker's name to its :func:`worker_code_version` dict.
    """
    for name, reported in sorted(workers.items()):
        theirs = CodeVersion.from_dict(reported)
        if not theirs.same_code(client):
            raise DatasetError(f"{name} runs {DIST} {theirs}, the client runs {client}; "
                               f"install the same code on every worker")


def is_deterministic(error: BaseException) -> bool:
    """True for a failure that would recur on any worker (not worth a retry)."""
    return isinstance(error, DETERMINISTIC)


def render_on_cluster(spec: SchedulerSpec, cfg: DatasetConfig, todo: Iterable[int], folder: Path,
                      finish: Finish, retries: int = DEFAULT_RETRIES, job: Job = run_job,
                      window: int = WINDOW) -> None:
    """Submit one task per scene of ``todo``, at most ``window`` at once; call ``finish(index,
    record, error)`` as each completes.

    Raises :class:`DatasetError` before submitting anything if a connected worker runs other code.
    A scene whose task fails transiently is submitted again, up to ``retries`` times (see the
    module doc). ``finish`` runs in this process, in completion order (it appends the manifest and
    drives the progress bar). ``job`` defaults to :func:`run_job` (tests pass a wrapper that fails).
    """
    queue = iter(todo)
    first = next(queue, None)
    if first is None:
        return
    queue = itertools.chain([first], queue)
    from distributed import as_completed

    folder = folder.resolve()
    threads = local_threads(spec)
    mine = code_version()
    batch = uuid.uuid4().hex[:8]  # unique keys: a long-lived scheduler may remember older runs
    attempts: dict[int, int] = {}  # of the scenes submitted and not finished
    with connect(spec) as client:
        check_code(mine, {f"worker {address}": version
                          for address, version in client.run(worker_code_version).items()})

        def submit(index: int) -> Any:
            return client.submit(cluster_job, cfg, index, folder, threads, job, mine.to_dict(), retries=0,
                                 key=f"scene-{index:06d}-{batch}-{attempts[index]}")

        futures: dict[Any, int] = {}
        pending = as_completed()

        def top_up() -> None:
            for index in itertools.islice(queue, window - len(futures)):
                attempts[index] = 0
                future = submit(index)
                futures[future] = index
                pending.add(future)

        top_up()
        for future in pending:
            index = futures.pop(future)
            error = future.exception() if future.status == "error" else None
            if error is None and future.status != "finished":
                error = DatasetError(f"task {future.status}")
            if error is not None and not is_deterministic(error) and attempts[index] < retries:
                attempts[index] += 1
                again = submit(index)
                futures[again] = index
                pending.add(again)
            else:
                finish(index, None if error is not None else future.result(), error)
                del attempts[index]
            future.release()
            top_up()
