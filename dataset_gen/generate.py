"""Generate a dataset: many scene jobs, resumable, crash-safe, parallel across scenes.

Each finished scene is appended to the manifest by this (parent) process only, after its files
are complete. Re-running the same command skips listed scenes; leftover temporary files from a
crash are removed first. Jobs run in-process (``workers=1``), in a spawn-started process pool,
each worker limiting Mitsuba's thread pool to its share of the cores, or as tasks on a Dask
cluster (``scheduler``, see :mod:`dataset_gen.cluster`).
"""
from __future__ import annotations

import concurrent.futures as cf
import itertools
import multiprocessing
import os
import time
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from dataset_gen.cluster import SchedulerSpec, render_on_cluster
from dataset_gen.config import DatasetConfig, open_dataset
from dataset_gen.jobs import IMAGES_DIR, SCENES_DIR, check_job_memory, run_job
from dataset_gen.manifest import append_record, read_records, repair
from imaging.atomic_io import TMP_PREFIX
from rendering.backend import LLVM_VARIANT, resolve_variant
from console.progress import ProgressFactory
from imaging.errors import DatasetError


@dataclass
class GenerateSummary:
    """What a run did. ``render_s`` sums the jobs' own render times; ``job_s`` their wall times."""

    done: int = 0
    skipped: int = 0
    failed: list[str] = field(default_factory=list)
    wall_s: float = 0.0
    render_s: float = 0.0
    job_s: float = 0.0
    samples: int = 0

    def overhead(self) -> float:
        """Fraction of job time spent outside Mitsuba's renders (scene generation, I/O...)."""
        return 0.0 if self.job_s == 0 else 1.0 - self.render_s / self.job_s


def with_runtime(cfg: DatasetConfig) -> DatasetConfig:
    """``cfg`` with the Mitsuba version and the variant this machine will use filled in."""
    from dataclasses import replace

    variant, _ = resolve_variant(os.environ.get("DENOISER_MI_VARIANT") or LLVM_VARIANT)
    return replace(cfg, mitsuba=metadata.version("mitsuba"), variant=variant)


def remove_stale_temporaries(folder: Path) -> int:
    """Delete temp files left by a crash (never a finished file); return how many."""
    count = 0
    for sub in (folder, folder / IMAGES_DIR, folder / SCENES_DIR):
        if sub.is_dir():
            for path in sub.rglob(f"{TMP_PREFIX}*"):
                path.unlink(missing_ok=True)
                count += 1
    return count


def auto_workers(cores: int | None = None) -> int:
    """Scene jobs at once that keep every core busy: 1 on up to 4 cores (Mitsuba then renders each
    scene on all of them, measured fastest on 2 cores), else one job per 4 cores (a small film at
    a few spp does not keep 16 render threads busy), each job rendering on its 4."""
    cores = cores or os.cpu_count() or 1
    return 1 if cores <= 4 else cores // 4


def _init_worker(threads: int) -> None:
    from rendering.backend import select_variant

    select_variant()
    import drjit as dr

    dr.set_thread_count(threads)


def _render_seconds(record: dict[str, Any]) -> float:
    return sum(v for k, v in record["timings"].items() if k.startswith("render_"))


def generate_dataset(
    folder: Path,
    cfg: DatasetConfig,
    scenes: int,
    workers: int = 1,
    make_progress: ProgressFactory | None = None,
    scheduler: SchedulerSpec | None = None,
) -> GenerateSummary:
    """Render scenes ``0..scenes-1`` of ``cfg`` into ``folder`` (skipping finished ones), on
    ``workers`` local processes (0: :func:`auto_workers`) or, with ``scheduler``, on a Dask cluster
    (``workers`` unused)."""
    if scenes < 1:
        raise DatasetError(f"--scenes must be >= 1, got {scenes}")
    if cfg.scene_files and scenes > len(cfg.scene_files):
        raise DatasetError(f"--scenes {scenes}: only {len(cfg.scene_files)} scene file(s) given")
    if workers < 0:
        raise DatasetError(f"--workers must be >= 0 (0: one job per 4 cores), got {workers}")
    workers = workers or auto_workers()
    if scheduler is None:  # a cluster's workers have memory of their own
        cfg.validate()
        check_job_memory(cfg)
    cfg = open_dataset(folder, with_runtime(cfg))
    (folder / IMAGES_DIR).mkdir(exist_ok=True)
    remove_stale_temporaries(folder)
    repair(folder)
    finished = {r["index"] for r in read_records(folder)}
    todo = (i for i in range(scenes) if i not in finished)  # made one at a time: any --scenes takes no memory
    summary = GenerateSummary(skipped=sum(1 for i in finished if 0 <= i < scenes))
    progress = make_progress(scenes - summary.skipped) if make_progress else None
    start = time.perf_counter()

    def finish(index: int, record: dict[str, Any] | None, error: BaseException | None) -> None:
        if error is not None:
            summary.failed.append(f"scene {index}: {error}")
            if progress:
                progress.write(f"scene {index} failed: {error}")
        else:
            append_record(folder, record)
            summary.done += 1
            summary.render_s += _render_seconds(record)
            summary.job_s += record["timings"]["total_s"]
            summary.samples += record["samples"]
        if progress:
            elapsed = time.perf_counter() - start
            progress.update(1)
            progress.set_postfix_str(f"{summary.samples / max(elapsed, 1e-9) / 1e6:.1f} Msamples/s")

    try:
        if scheduler is not None:
            render_on_cluster(scheduler, cfg, todo, folder, finish)
        elif workers == 1:
            for index in todo:
                try:
                    record, error = run_job(cfg, index, folder), None
                except Exception as exc:  # a broken scene must not stop the others
                    record, error = None, exc
                finish(index, record, error)
        else:
            # never 1: Dr.Jit with one thread deadlocks loading scenes with textures (measured)
            threads = max(2, (os.cpu_count() or 1) // workers)
            ctx = multiprocessing.get_context("spawn")
            with cf.ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker,
                                        initargs=(threads,)) as pool:
                futures: dict[cf.Future, int] = {}
                while True:  # at most two jobs a worker submitted at once
                    futures.update({pool.submit(run_job, cfg, i, folder): i
                                    for i in itertools.islice(todo, 2 * workers - len(futures))})
                    if not futures:
                        break
                    done, _ = cf.wait(futures, return_when=cf.FIRST_COMPLETED)
                    for fut in done:
                        exc = fut.exception()
                        finish(futures.pop(fut), None if exc else fut.result(), exc)
    finally:
        if progress:
            progress.close()
    summary.wall_s = time.perf_counter() - start
    return summary
