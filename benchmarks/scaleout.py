"""Scale-out: scenes/hour on 1 vs 2 local Dask workers, patches/s with 1 vs 2 DDP ranks, and an
estimate of what N machines would give, from the measured per-scene and per-step costs.

    .venv/bin/python benchmarks/scaleout.py [--quick] [--scenes 4] [--res 128] [--steps 30]
        [--preset fast] [--batch 64] [--link-gbps 10]

Dask: the scenes are first rendered once untimed (this fills Dr.Jit's on-disk kernel cache, so no
setting pays for compiling), then in this process without Dask (the baseline), then on a
LocalCluster of N worker processes, started and warmed up (Mitsuba imported, Dr.Jit given
max(2, cores/N) threads) before the clock starts, through its tcp:// address as on a real cluster.
DDP: ``train --nproc 2`` (each rank one share of the cores) against one process with
``--micro-batch batch/2`` — the same computation — and one process without micro-batching, all
on a synthetic dataset; patches/s is the median of the log lines after the first (warm-up). On one machine the ranks share its cores, so this shows
overhead, not speed-up: the N-machine estimate is printed beside it with its assumptions.
Prints a table and writes benchmarks/results/scaleout.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dataset_gen.cluster import SchedulerSpec  # noqa: E402
from dataset_gen.config import DatasetConfig  # noqa: E402
from dataset_gen.generate import generate_dataset  # noqa: E402
from model.config import PRESETS  # noqa: E402
from model.network import build_model, count_parameters  # noqa: E402
from model.synthetic import write_synthetic_dataset  # noqa: E402
from scenes.registry import FAMILIES  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "scaleout.json"


def _warm_worker(threads: int) -> str:
    from pipeline.backend import select_variant

    variant = select_variant()
    import drjit as dr

    dr.set_thread_count(threads)
    return variant


def measure_local(cfg: DatasetConfig, scenes: int) -> dict[str, Any]:
    """Render ``scenes`` scenes in this process (the path without ``--scheduler``)."""
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        s = generate_dataset(Path(tmp) / "d", cfg, scenes)
        wall = time.perf_counter() - start
    return {"workers": 0, "threads_per_worker": os.cpu_count(), "scenes": s.done, "failed": len(s.failed),
            "startup_s": 0.0, "wall_s": wall, "scenes_per_hour": 3600 * s.done / wall,
            "job_s_per_scene": s.job_s / max(s.done, 1), "render_s": s.render_s}


def measure_dask(cfg: DatasetConfig, scenes: int, workers: int) -> dict[str, Any]:
    """Render ``scenes`` scenes on a warmed-up LocalCluster of ``workers`` processes."""
    from distributed import Client, LocalCluster
    import logging

    threads = max(2, (os.cpu_count() or 1) // workers)
    t0 = time.perf_counter()
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.CRITICAL) as local, Client(local) as client:
        client.run(_warm_worker, threads)
        startup = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            s = generate_dataset(Path(tmp) / "d", cfg, scenes, scheduler=SchedulerSpec(address=local.scheduler_address))
            wall = time.perf_counter() - start
    return {"workers": workers, "threads_per_worker": threads, "scenes": s.done, "failed": len(s.failed),
            "startup_s": startup, "wall_s": wall, "scenes_per_hour": 3600 * s.done / wall,
            "job_s_per_scene": s.job_s / max(s.done, 1), "render_s": s.render_s}


def _train(data: Path, out: Path, steps: int, args: argparse.Namespace, extra: list[str]) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "model.cli", "--data", str(data), "--out", str(out), "--preset", args.preset,
           "--batch", str(args.batch), "--steps", str(steps), "--log-every", "1", "--val-every", "0",
           "--ckpt-every", str(steps), "--no-progress", *extra]
    start = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed: {done.stderr.strip()[-500:]}")
    rates = [r["patches_per_s"] for r in map(json.loads, (out / "log.jsonl").read_text().splitlines())
             if r.get("type") == "train" and r.get("patches_per_s")]
    steady = rates[1:] or rates
    rate = statistics.median(steady)
    return {"patches_per_s": rate, "s_per_step": args.batch / rate, "wall_s": wall, "steps": steps}


def measure_ddp(args: argparse.Namespace) -> list[dict[str, Any]]:
    """1 process (plain, and with micro_batch = batch/2) vs 2 DDP ranks, same global batch."""
    cores = os.cpu_count() or 1
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        data = write_synthetic_dataset(Path(tmp) / "ds", scenes=4, res=(96, 96), spp=(4, 16), val_scenes=())
        for name, extra in (("1 process", []),
                            (f"1 process, micro-batch {args.batch // 2}", ["--micro-batch", str(args.batch // 2)]),
                            ("2 DDP ranks", ["--nproc", "2"])):
            row = _train(data, Path(tmp) / name.replace(" ", "_").replace(",", ""), args.steps, args, extra)
            row.update(setting=name, threads_per_process=cores if "DDP" not in name else max(1, cores // 2))
            rows.append(row)
            print(f"  {name:<28} {row['patches_per_s']:7.1f} patches/s  {row['s_per_step']:6.2f} s/step "
                  f"({row['wall_s']:.0f} s wall incl. start-up)")
    return rows


def estimate(dask_rows: list[dict[str, Any]], ddp_rows: list[dict[str, Any]], args: argparse.Namespace,
             machines: tuple[int, ...] = (1, 2, 4, 8, 16)) -> dict[str, Any]:
    """What N machines like this one would give, from the measured costs (assumptions stated)."""
    per_scene = next(r for r in dask_rows if r["workers"] == 1)["job_s_per_scene"]  # all cores
    step = next(r for r in ddp_rows if "micro" in r["setting"])["s_per_step"]  # same maths as DDP
    params = count_parameters(build_model(PRESETS[args.preset]))
    grad_bytes = 4 * params
    link = args.link_gbps * 1e9 / 8
    rows = []
    for n in machines:
        comm = 0.0 if n == 1 else 2 * (n - 1) / n * grad_bytes / link + 2e-3  # ring all-reduce + latency
        t_step = step / n + comm
        rows.append({"machines": n, "scenes_per_hour": n * 3600 / per_scene,
                     "patches_per_s": args.batch / t_step, "s_per_step": t_step, "allreduce_s": comm})
    return {
        "assumptions": (
            f"machines like this one ({os.cpu_count()} cores), one Dask worker each (--nthreads 1, Mitsuba on "
            f"all cores) and one DDP rank each; rendering is embarrassingly parallel (the client only appends "
            f"a manifest line per scene), so scenes/hour = N x 3600 / {per_scene:.1f} s per scene; a DDP step "
            f"is the 1-process step split N ways ({step:.2f} s / N, same global batch {args.batch}) plus a ring "
            f"all-reduce of {params} float32 gradients over a {args.link_gbps:g} Gbit/s link plus 2 ms latency; "
            f"BatchNorm per rank then works on {args.batch}/N patches, so keep batch/N >= 8 or raise the batch"),
        "per_scene_s": per_scene, "step_s_1process": step, "parameters": params, "rows": rows}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="tiny settings: a smoke test of the benchmark")
    p.add_argument("--scenes", type=int, default=4)
    p.add_argument("--res", type=int, default=128)
    p.add_argument("--spp", default="4,16,64,128")
    p.add_argument("--ref-spp", type=int, default=1024)
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--preset", default="fast", choices=sorted(PRESETS))
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--link-gbps", type=float, default=10.0, help="network assumed for the N-machine estimate")
    args = p.parse_args()
    if args.quick:
        args.scenes, args.res, args.spp, args.ref_spp, args.steps, args.batch = 2, 32, "1,4", 16, 4, 16
    cfg = DatasetConfig(res=(args.res, args.res), spp=tuple(int(s) for s in args.spp.split(",")),
                        ref_spp=args.ref_spp, families=tuple(FAMILIES), seed=12345)
    load = os.getloadavg()[0]
    print(f"Dask dataset generation, {args.scenes} scenes at {args.res}px (load average before: {load:.1f})")
    measure_local(cfg, args.scenes)  # untimed: compiles and caches Dr.Jit's kernels
    dask_rows = [measure_local(cfg, args.scenes)]
    dask_rows += [measure_dask(cfg, args.scenes, workers) for workers in (1, 2)]
    for r in dask_rows:
        name = f"{r['workers']} Dask worker(s)" if r["workers"] else "no Dask, in-process"
        print(f"  {name:<20} x {r['threads_per_worker']} threads: {r['scenes_per_hour']:7.0f} scenes/h "
              f"({r['wall_s']:.1f} s for {r['scenes']} scenes, {r['job_s_per_scene']:.1f} s job time per scene; "
              f"cluster start-up {r['startup_s']:.0f} s not counted)")
    print(f"DDP training, preset {args.preset}, global batch {args.batch}, {args.steps} steps")
    ddp_rows = measure_ddp(args)
    est = estimate(dask_rows, ddp_rows, args)
    print("Estimate for N machines like this one (" + est["assumptions"] + "):")
    print("  machines  scenes/h  patches/s  s/step  all-reduce s")
    for r in est["rows"]:
        print(f"  {r['machines']:8d}  {r['scenes_per_hour']:8.0f}  {r['patches_per_s']:9.1f}  {r['s_per_step']:6.3f}"
              f"  {r['allreduce_s']:.4f}")
    result = {"quick": args.quick, "cpus": os.cpu_count(), "machine": platform.machine(),
              "load_average_before": load, "load_average_after": os.getloadavg()[0],
              "dataset_config": cfg.to_json(), "dask": dask_rows, "ddp": ddp_rows, "estimate": est}
    RESULTS.parent.mkdir(exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {RESULTS}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
