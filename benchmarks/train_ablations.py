"""What buys quality per CPU-minute: short training runs that differ in one choice each.

Runs (same data, same seed, ``flat-s`` preset sizes unless noted, equal steps):
  baseline        log transfer, residual output, densenet, lr 1e-3
  pu              PU transfer instead of log
  direct          direct output instead of residual
  plaincnn        plain CNN of equal parameter count instead of the dense block
  paper-lr        the paper's lr 0.01
Each run is the ``train`` command itself (its run folder under ``--runs``, resumable); this script
then reads every run's log.jsonl and reports the final and best validation PSNR (mean over the
val images and per spp), training seconds, and the steps/seconds each run needed to reach the
PSNR that both the DenseNet baseline and the plain CNN reach ("time to the same validation
quality", the paper's central claim).

Usage: python -m benchmarks.train_ablations --data data/train [--steps 800] [--runs runs/ablations]
       [--only baseline,pu] [--report-only]
Writes benchmarks/results/train_ablations.json and .md.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from imaging.atomic_io import write_text_atomic
from training.run_log import RunLog

ROOT = Path(__file__).resolve().parents[1]

# the settings of the recorded runs: the paper's batch, crops and step schedule, no warm-up
BASE = ["--preset", "flat-s", "--transfer", "log", "--output", "residual", "--lr", "0.001", "--batch", "64",
        "--patch", "28", "--lr-warmup", "0", "--lr-cosine-steps", "0"]
RUNS: dict[str, list[str]] = {
    "baseline": [],
    "pu": ["--transfer", "pu"],
    "direct": ["--output", "direct"],
    "plaincnn": ["--arch", "plaincnn"],
    "paper-lr": ["--lr", "0.01"],
}


def run_training(name: str, data: str, runs: Path, steps: int, val_every: int) -> None:
    """Start (or resume) one ablation run through the ``train`` CLI."""
    out = runs / name
    # later options win in argparse: the variant's flags override the base ones
    args = [sys.executable, "-m", "training.cli", "--data", data, "--out", str(out), "--steps", str(steps),
            "--val-every", str(val_every), "--log-every", "50", "--no-progress", *BASE, *RUNS[name]]
    if (out / "last.ckpt").exists():
        args.append("--resume")
    print(f"== {name}: {' '.join(args[3:])}", flush=True)
    subprocess.run(args, cwd=ROOT, check=True)


def summarize(name: str, records: list[dict[str, Any]]) -> dict[str, Any]:
    """Validation curve and timings of one run from its log records."""
    vals = [r for r in records if r["type"] == "val" and r.get("psnr") is not None]
    trains = [r for r in records if r["type"] == "train"]
    seconds = {r["step"]: r.get("train_s") for r in trains}
    if not vals:
        return {"name": name, "curve": []}
    curve = [{"step": v["step"], "train_s": seconds.get(v["step"]), "psnr": v["psnr"],
              "per_spp": {spp: row["psnr"]["ours"] for spp, row in v["per_spp"].items()}} for v in vals]
    last = vals[-1]
    return {"name": name, "args": RUNS[name], "curve": curve, "final_psnr": last["psnr"],
            "best_psnr": max(v["psnr"] for v in vals), "final_step": last["step"],
            "train_s": seconds.get(last["step"]),
            "final_per_spp": {spp: row["psnr"] for spp, row in last["per_spp"].items()}}


def time_to_reach(summary: dict[str, Any], target: float) -> tuple[int | None, float | None]:
    """First validation step (and its training seconds) whose PSNR is >= ``target``."""
    for point in summary["curve"]:
        if point["psnr"] >= target:
            return point["step"], point["train_s"]
    return None, None


def report(runs: Path, names: list[str]) -> dict[str, Any]:
    """Read every run's log and build the comparison (also as markdown)."""
    rows = [summarize(n, RunLog(runs / n / "log.jsonl").read()) for n in names if (runs / n).exists()]
    rows = [r for r in rows if r["curve"]]
    if not rows:
        raise SystemExit("train_ablations: no finished validation in any run")
    # The paper's claim is about DenseNet vs a plain CNN: the target is the PSNR both of them reach.
    pair = [r["best_psnr"] for r in rows if r["name"] in ("baseline", "plaincnn")]
    target = min(pair) if len(pair) == 2 else min(r["best_psnr"] for r in rows)
    for r in rows:
        r["steps_to_target"], r["seconds_to_target"] = time_to_reach(r, target)
    spps = sorted({spp for r in rows for spp in r["final_per_spp"]}, key=int)
    lines = [f"'to target': first validation at >= {target:.2f} dB val PSNR (the best PSNR that both "
             "baseline and plaincnn reach); '-' = not reached. Train seconds exclude validation.", "",
             "| run | steps | train s | final val PSNR | best | " +
             " | ".join(f"{s} spp (noisy / OIDN)" for s in spps) + " | steps to target | s to target |",
             "|---|---:|---:|---:|---:|" + "---:|" * len(spps) + "---:|---:|"]
    for r in rows:
        cells = [f"{r['final_per_spp'][s]['ours']:.2f} ({r['final_per_spp'][s]['noisy']:.2f} / "
                 f"{_fmt(r['final_per_spp'][s].get('oidn'))})" for s in spps]
        lines.append(f"| {r['name']} | {r['final_step']} | {_fmt(r['train_s'], 0)} | {r['final_psnr']:.2f} | "
                     f"{r['best_psnr']:.2f} | " + " | ".join(cells) +
                     f" | {r['steps_to_target'] or '-'} | {_fmt(r['seconds_to_target'], 0)} |")
    return {"target_psnr": target, "runs": rows, "markdown": "\n".join(lines) + "\n"}


def _fmt(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", default="data/train")
    p.add_argument("--runs", default="runs/ablations")
    p.add_argument("--steps", type=int, default=800)
    p.add_argument("--val-every", type=int, default=200)
    p.add_argument("--only", help=f"comma-separated subset of {', '.join(RUNS)}")
    p.add_argument("--report-only", action="store_true", help="only summarise existing runs")
    args = p.parse_args()
    names = args.only.split(",") if args.only else list(RUNS)
    unknown = sorted(set(names) - set(RUNS))
    if unknown:
        print(f"train_ablations: unknown run(s) {', '.join(unknown)}", file=sys.stderr)
        return 1
    runs = Path(args.runs)
    runs.mkdir(parents=True, exist_ok=True)
    if not args.report_only:
        for name in names:
            run_training(name, args.data, runs, args.steps, args.val_every)
    result = report(runs, list(RUNS))
    out = ROOT / "benchmarks" / "results"
    write_text_atomic(out / "train_ablations.json", json.dumps(result, indent=1) + "\n")
    write_text_atomic(out / "train_ablations.md", result["markdown"])
    print(result["markdown"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
