"""Scale-out: scenes/hour on 1 vs 2 local Dask workers, patches/s with 1 vs 2 DDP ranks, and an
estimate of what N machines would give, from the measured per-scene and per-step costs.

    python -m benchmarks.scaleout [--quick] [--scenes 4] [--res 128] [--spp 4,16,64,128]
        [--ref-spp 4096] [--steps 30] [--warmup-steps 5] [--preset flat-s] [--batch 64]
        [--machines 1,2,4,8,16] [--link-gbps 10] [--hop-latency-us 100] [--out FILE]

Run it on an idle machine. Every setting records the CPU that other processes used meanwhile
(``foreign_cores``, cores on average); settings above 0.1 are listed under ``flagged``. A loaded
machine does not slow all settings alike: a multi-threaded torch process stalls at every OpenMP
barrier whose thread was descheduled, 1-thread DDP ranks do not.

How each setting is kept apart and fair:

- Each runs in fresh processes; before the next one starts the script waits for every child
  process to exit and stops any that did not (named under ``leftovers``).
- Dask: the scenes are first rendered once, untimed, in a throwaway process (fills Dr.Jit's
  on-disk kernel cache, so no setting pays for compiling). Then the baseline (no Dask: the path
  without ``--scheduler``) in a fresh process, then LocalClusters of 1 and 2 worker processes with
  the Mitsuba threads ``--scheduler local:N`` gives them, reached through their tcp:// address as
  a real cluster is. Every rendering process first renders one tiny scene untimed (imports, LLVM,
  plugins); cluster start-up is reported, not counted. Wall time is generate_dataset's own.
- The Dask nanny writes OMP_NUM_THREADS=1, MALLOC_TRIM_THRESHOLD_ etc. into this process's
  environment before it spawns a worker; the environment is restored after each setting, and
  every training run gets an explicit one, with ``--threads`` and OMP_NUM_THREADS equal.
- DDP (synthetic data, same global batch B): 1 process; 1 process with ``--micro-batch B/2``
  (what 2 ranks compute), on all cores and on one rank's share; ``train --nproc 2``; and 1
  process at batch B/N for the N-machine estimate (one rank's work on a machine of its own).
  Rates are total patches / total time of the steps after ``--warmup-steps`` (log line per step).

Prints a table and writes --out (default benchmarks/results/scaleout.json).
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import dataclasses
import json
import logging
import math
import multiprocessing
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

BASE_ENV = dict(os.environ)  # before anything (Dask's nanny) changes it
REPO = Path(__file__).resolve().parents[1]

from torch import nn

from dataset_gen.cluster import SchedulerSpec, local_threads
from dataset_gen.config import DatasetConfig
from dataset_gen.generate import GenerateSummary, generate_dataset
from model.config import PRESETS
from model.architectures import build_model, count_parameters
from training.synthetic import write_synthetic_dataset
from scenes.registry import FAMILIES

RESULTS = Path(__file__).resolve().parent / "results" / "scaleout.json"
FOREIGN_LIMIT = 0.1  # cores used by other processes above which a setting is flagged
DDP_FIRST_BUCKET = 1 << 20  # torch DDP gradient buckets: the first 1 MiB, then 25 MiB each
DDP_BUCKET = 25 << 20


# ---- keeping settings apart -------------------------------------------------------------------

def _busy_jiffies() -> int:
    with open("/proc/stat") as fh:
        parts = [int(x) for x in fh.readline().split()[1:]]
    return sum(parts) - parts[3] - parts[4]  # minus idle and iowait


def _own_jiffies() -> float:
    t = os.times()  # this process and every descendant it (or they) waited for
    return (t.user + t.system + t.children_user + t.children_system) * os.sysconf("SC_CLK_TCK")


def _stop_leftovers(grace_s: float = 30.0) -> list[str]:
    """Wait for this process's descendants to exit; stop, by pid, those alive after ``grace_s``
    (multiprocessing's idle resource tracker is left). Returns what had to be stopped."""
    import psutil

    def tracker(p: psutil.Process) -> bool:
        try:
            return any("resource_tracker" in part for part in p.cmdline())
        except psutil.Error:
            return False

    kids = [p for p in psutil.Process().children(recursive=True) if not tracker(p)]
    _, alive = psutil.wait_procs(kids, timeout=grace_s)
    stopped = []
    for p in alive:
        try:
            stopped.append(f"pid {p.pid}: {' '.join(p.cmdline())[:100]}")
            p.terminate()
        except psutil.Error:
            pass
    _, alive = psutil.wait_procs(alive, timeout=5)
    for p in alive:
        try:
            p.kill()
        except psutil.Error:
            pass
    return stopped


def isolated(measure: Callable[..., dict[str, Any]], *args: Any) -> dict[str, Any]:
    """``measure(*args)``'s row, plus the cores other processes used meanwhile (``foreign_cores``)
    and the processes it left behind; the environment is restored and its processes gone after."""
    busy0, own0, t0 = _busy_jiffies(), _own_jiffies(), time.perf_counter()
    try:
        row = measure(*args)
    finally:
        os.environ.clear()
        os.environ.update(BASE_ENV)
        leftovers = _stop_leftovers()
    wall = time.perf_counter() - t0
    foreign = max(0.0, (_busy_jiffies() - busy0) - (_own_jiffies() - own0)) / os.sysconf("SC_CLK_TCK")
    row.update(foreign_cores=round(foreign / wall, 2), setting_wall_s=round(wall, 1), leftovers=leftovers)
    if leftovers:
        print(f"  warning: {row['setting']} left {len(leftovers)} process(es) running; stopped them")
    return row


def _in_fresh_process(fn: Callable[..., dict[str, Any]], *args: Any) -> dict[str, Any]:
    with cf.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(fn, *args).result()


# ---- Dask dataset generation ------------------------------------------------------------------

def _warm(cfg: DatasetConfig, threads: int | None) -> None:
    """Untimed, in a rendering process: select the variant, set Mitsuba's threads (None: all
    cores) and render one tiny scene, so start-up costs stay out of the timed run."""
    from rendering.backend import select_variant

    select_variant()
    if threads:
        import drjit as dr

        dr.set_thread_count(threads)
    with tempfile.TemporaryDirectory() as tmp:
        generate_dataset(Path(tmp) / "warm", dataclasses.replace(cfg, spp=(1,), ref_spp=2), 1)


def _dask_row(setting: str, workers: int, threads: int, s: GenerateSummary, startup_s: float = 0.0) -> dict[str, Any]:
    if s.failed or not s.done:
        raise RuntimeError(f"{setting}: {len(s.failed)} scene(s) failed, first: {s.failed[:1]}")
    return {"setting": setting, "workers": workers, "threads_per_worker": threads, "scenes": s.done,
            "wall_s": s.wall_s, "scenes_per_hour": 3600 * s.done / s.wall_s, "wall_s_per_scene": s.wall_s / s.done,
            "job_s_per_scene": s.job_s / s.done, "render_s": s.render_s, "startup_s": startup_s}


def _render_pass(cfg: DatasetConfig, scenes: int, warm: bool) -> dict[str, Any]:
    """In a fresh process: render ``scenes`` scenes without Dask (all cores), into a temp folder."""
    if warm:
        _warm(cfg, None)
    with tempfile.TemporaryDirectory() as tmp:
        s = generate_dataset(Path(tmp) / "d", cfg, scenes)
        size = sum(f.stat().st_size for f in (Path(tmp) / "d").rglob("*") if f.is_file())
    row = _dask_row("no Dask, in-process", 0, os.cpu_count() or 1, s)
    row["bytes_per_scene"] = size / s.done
    return row


def measure_prerun(cfg: DatasetConfig, scenes: int) -> dict[str, Any]:
    """Untimed: render the scenes once in a throwaway process (fills Dr.Jit's kernel cache)."""
    return {**_in_fresh_process(_render_pass, cfg, scenes, False), "setting": "untimed pre-run"}


def measure_local(cfg: DatasetConfig, scenes: int) -> dict[str, Any]:
    """The path without ``--scheduler``, in a fresh warmed-up process."""
    return _in_fresh_process(_render_pass, cfg, scenes, True)


def measure_dask(cfg: DatasetConfig, scenes: int, workers: int) -> dict[str, Any]:
    """Render ``scenes`` scenes on a warmed-up LocalCluster of ``workers`` processes, each with
    the Mitsuba threads ``--scheduler local:N`` would give it, through its tcp:// address."""
    from distributed import Client, LocalCluster

    threads = local_threads(SchedulerSpec(local_workers=workers))
    t0 = time.perf_counter()
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.CRITICAL) as local, Client(local) as client:
        client.run(_warm, cfg, threads)
        startup = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            s = generate_dataset(Path(tmp) / "d", cfg, scenes, scheduler=SchedulerSpec(address=local.scheduler_address))
    return _dask_row(f"{workers} Dask worker(s)", workers, threads, s, startup)


# ---- DDP training -----------------------------------------------------------------------------

def _train(setting: str, data: Path, out: Path, batch: int, threads: int, args: argparse.Namespace,
           extra: tuple[str, ...] = ()) -> dict[str, Any]:
    """One ``train`` run (``python -m training.cli``) with ``threads`` torch threads per process."""
    cmd = [sys.executable, "-m", "training.cli", "--data", str(data), "--out", str(out), "--preset", args.preset,
           "--batch", str(batch), "--patch", "28", "--steps", str(args.steps), "--threads", str(threads), "--log-every", "1",
           "--val-every", "0", "--ckpt-every", str(args.steps), "--no-progress", *extra]
    env = {**BASE_ENV, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    start = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {done.stderr.strip()[-500:]}")
    lines = [r for r in map(json.loads, (out / "log.jsonl").read_text().splitlines())
             if r.get("type") == "train" and r.get("patches_per_s")]
    rates = [r["patches_per_s"] for r in lines if r["step"] > args.warmup_steps]
    if len(rates) < 3:
        raise RuntimeError(f"{setting}: {len(rates)} steps after the warm-up; raise --steps")
    seconds = [batch / r for r in rates]  # one log line per step
    return {"setting": setting, "batch": batch, "threads_per_process": threads, "steps": args.steps,
            "timed_steps": len(rates), "patches_per_s": batch * len(rates) / sum(seconds),
            "s_per_step": sum(seconds) / len(rates), "patches_per_s_median": statistics.median(rates),
            "patches_per_s_min": min(rates), "patches_per_s_max": max(rates), "wall_s": wall}


def ddp_settings(args: argparse.Namespace) -> list[tuple[str, int, int, tuple[str, ...]]]:
    """(name, batch, torch threads per process, extra flags) of every training setting."""
    cores, b = os.cpu_count() or 1, args.batch
    half, share = b // 2, max(1, cores // 2)
    micro = ("--micro-batch", str(half))
    rows = [("1 process", b, cores, ()),
            (f"1 process, micro-batch {half}", b, cores, micro),
            (f"1 process, micro-batch {half}, {share} thread(s)", b, share, micro),
            ("2 DDP ranks", b, share, ("--nproc", "2"))]
    rows += [(f"1 process, batch {b // n} (one of {n} ranks)", b // n, cores, ())
             for n in args.machines if n > 1 and b % n == 0]
    return rows


def measure_ddp(args: argparse.Namespace) -> list[dict[str, Any]]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        data = write_synthetic_dataset(Path(tmp) / "ds", scenes=4, res=(96, 96), spp=(4, 16), val_scenes=())
        for i, (name, batch, threads, extra) in enumerate(ddp_settings(args)):
            row = isolated(_train, name, data, Path(tmp) / f"run{i}", batch, threads, args, extra)
            rows.append(row)
            print(f"  {name:<44} x{threads} thr {row['patches_per_s']:7.1f} patches/s  {row['s_per_step']:6.3f} s/step"
                  f"  (median {row['patches_per_s_median']:.1f}; other processes {row['foreign_cores']:.2f} cores)")
    return rows


# ---- N-machine estimate -----------------------------------------------------------------------

def _allreduce_s(nbytes: float, n: int, args: argparse.Namespace) -> float:
    """Ring all-reduce: 2(n-1) hops of latency, 2(n-1)/n of the data over the link."""
    if n == 1:
        return 0.0
    return 2 * (n - 1) * args.hop_latency_us * 1e-6 + 2 * (n - 1) / n * nbytes * 8 / (args.link_gbps * 1e9)


def estimate(dask_rows: list[dict[str, Any]], ddp_rows: list[dict[str, Any]], cfg: DatasetConfig,
             args: argparse.Namespace) -> dict[str, Any]:
    """What N machines like this one would give, from the measured costs (assumptions stated)."""
    one = next(r for r in dask_rows if r["workers"] == 1)
    per_scene = one["wall_s_per_scene"]
    bytes_per_scene = next(r for r in dask_rows if r["workers"] == 0)["bytes_per_scene"]
    model = build_model(PRESETS[args.preset])
    params = count_parameters(model)
    bn = sum(m.running_mean.numel() for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm))
    grad_bytes = 4 * params
    buckets = 1 + max(0, math.ceil((grad_bytes - DDP_FIRST_BUCKET) / DDP_BUCKET))
    collectives = [grad_bytes / buckets] * buckets + [8 * 2 * bn, 8]  # gradients, BN statistics, loss
    step_at = {r["batch"]: r["s_per_step"] for r in ddp_rows
               if r["setting"] == "1 process" or r["setting"].startswith("1 process, batch ")}
    rows = []
    for n in args.machines:
        if args.batch % n or args.batch // n not in step_at:
            continue
        comm = sum(_allreduce_s(b, n, args) for b in collectives)
        t_step = step_at[args.batch // n] + comm
        rows.append({"machines": n, "scenes_per_hour": n * 3600 / per_scene, "patches_per_s": args.batch / t_step,
                     "s_per_step": t_step, "rank_compute_s": step_at[args.batch // n], "allreduce_s": comm,
                     "patches_per_rank": args.batch // n})
    families = sorted({cfg.families[i % len(cfg.families)] for i in range(one["scenes"])})
    return {
        "assumptions": (
            f"machines like this one ({os.cpu_count()} cores) with nothing else running. Dataset: one Dask worker "
            f"per machine (--nworkers 1 --nthreads 1, Mitsuba on all cores), {per_scene:.1f} s wall per scene as "
            f"measured on 1 local worker ({cfg.res[0]}x{cfg.res[1]} px, spp {','.join(map(str, cfg.spp))}, "
            f"reference {cfg.ref_spp} spp; families {', '.join(families)} only); the client appends one manifest "
            f"line per scene; the shared folder takes {bytes_per_scene / 1e6:.2f} MB per scene, assumed not the "
            f"bottleneck. Training: a rank's step is the measured 1-process step at batch {args.batch}/N on all "
            f"cores (its micro_batch is {args.batch}/N: one chunk), plus {len(collectives)} ring all-reduces per "
            f"step, not overlapped with compute (gradients {grad_bytes} B in {buckets} bucket(s), BatchNorm "
            f"statistics {16 * bn} B, the loss 8 B), each 2(N-1) hops of {args.hop_latency_us:g} us plus "
            f"2(N-1)/N of its bytes over {args.link_gbps:g} Gbit/s; every rank also samples the whole global "
            f"batch (prefetch thread), not counted. BatchNorm per rank normalises {args.batch}/N patches: "
            f"keep it >= 8 or raise the batch"),
        "per_scene_s": per_scene, "bytes_per_scene": bytes_per_scene, "parameters": params,
        "batchnorm_channels": bn, "rows": rows}


# ---- main -------------------------------------------------------------------------------------

def _parse() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="tiny settings: a smoke test of the script, no figures")
    p.add_argument("--scenes", type=int, default=4)
    p.add_argument("--res", type=int, default=128)
    p.add_argument("--spp", default="4,16,64,128")
    p.add_argument("--ref-spp", type=int, default=4096, help="default: the dataset command of docs/training.md")
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--warmup-steps", type=int, default=5, help="first steps of each run left out of the rates")
    p.add_argument("--preset", default="flat-s", choices=sorted(PRESETS))
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--machines", default="1,2,4,8,16", help="machine counts of the estimate")
    p.add_argument("--link-gbps", type=float, default=10.0, help="network assumed for the N-machine estimate")
    p.add_argument("--hop-latency-us", type=float, default=100.0, help="latency per all-reduce hop assumed")
    p.add_argument("--out", type=Path, default=RESULTS, help=f"JSON written (default {RESULTS})")
    args = p.parse_args()
    if args.quick:
        args.scenes, args.res, args.spp, args.ref_spp = 2, 32, "1,4", 16
        args.steps, args.warmup_steps, args.batch, args.machines = 6, 2, 16, "1,2,4"
    args.machines = tuple(int(n) for n in args.machines.split(","))
    if args.steps - args.warmup_steps < 3:
        p.error("--steps must exceed --warmup-steps by at least 3")
    if args.batch % 2:
        p.error("--batch must be even (2 DDP ranks)")
    return args


def _print_dask(r: dict[str, Any]) -> None:
    print(f"  {r['setting']:<20} x{r['threads_per_worker']} thr: {r['scenes_per_hour']:7.1f} scenes/h "
          f"({r['wall_s']:.1f} s for {r['scenes']} scenes, {r['job_s_per_scene']:.1f} s job time per scene, "
          f"start-up {r['startup_s']:.0f} s not counted; other processes {r['foreign_cores']:.2f} cores)")


def main() -> int:
    args = _parse()
    cfg = DatasetConfig(res=(args.res, args.res), spp=tuple(int(s) for s in args.spp.split(",")),
                        ref_spp=args.ref_spp, families=tuple(FAMILIES), seed=12345)
    load = os.getloadavg()[0]
    if load > 0.5:
        print(f"warning: load average {load:.1f}: other processes are running; the settings they slow get flagged")
    print(f"Dask dataset generation, {args.scenes} scenes at {args.res}px (load average before: {load:.1f})")
    prerun = isolated(measure_prerun, cfg, args.scenes)
    print(f"  untimed pre-run (kernel cache): {prerun['wall_s']:.1f} s")
    dask_rows = [isolated(measure_local, cfg, args.scenes)]
    _print_dask(dask_rows[-1])
    for workers in (1, 2):
        dask_rows.append(isolated(measure_dask, cfg, args.scenes, workers))
        _print_dask(dask_rows[-1])
    print(f"DDP training, preset {args.preset}, global batch {args.batch}, {args.steps} steps "
          f"({args.warmup_steps} warm-up)")
    ddp_rows = measure_ddp(args)
    est = estimate(dask_rows, ddp_rows, cfg, args)
    print("Estimate for N machines like this one (" + est["assumptions"] + "):")
    print("  machines  scenes/h  patches/s  s/step  all-reduce s")
    for r in est["rows"]:
        print(f"  {r['machines']:8d}  {r['scenes_per_hour']:8.0f}  {r['patches_per_s']:9.1f}  {r['s_per_step']:6.3f}"
              f"  {r['allreduce_s']:.4f}")
    flagged = [r["setting"] for r in [*dask_rows, *ddp_rows] if r["foreign_cores"] > FOREIGN_LIMIT]
    if flagged:
        print(f"warning: other processes used > {FOREIGN_LIMIT} cores during {len(flagged)} setting(s) "
              f"({', '.join(flagged)}): these figures are not the machine's")
    if args.quick:
        print("--quick: a smoke test of the script; its figures mean nothing")
    result = {"quick": args.quick, "cpus": os.cpu_count(), "machine": platform.machine(),
              "load_average_before": load, "load_average_after": os.getloadavg()[0],
              "foreign_limit_cores": FOREIGN_LIMIT, "flagged": flagged,
              "dataset_config": cfg.to_json(), "prerun_wall_s": prerun["wall_s"],
              "train": {"preset": args.preset, "batch": args.batch, "steps": args.steps,
                        "warmup_steps": args.warmup_steps},
              "dask": dask_rows, "ddp": ddp_rows, "estimate": est}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
