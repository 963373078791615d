"""Budget mode on the eval scenes: is the denoised image ready within the time budget?

For each scene of ../shared/eval-scenes (at its reference's resolution) and each budget, runs the
library behind ``render-and-denoise scene.xml --time-budget B --model auto`` (every preset with
shipped weights is a candidate) against the scene's reference, and records the choice (model,
spp, rule), the predicted and the actual seconds (from the start of the run until the denoised
image exists, as the budget counts), and the denoised PSNR. Goal (issue 6): actual time within
20% of the budget. Run it on an idle machine: another job on the cores changes the render and
denoise speeds between the probes and the real work.

    .venv/bin/python benchmarks/budget.py [--budgets 4,15] [--scenes a,b] [--curves tradeoff.json]

Prints a table and writes benchmarks/results/budget.json and budget.md.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imaging.atomic_io import write_text_atomic  # noqa: E402
from imaging.exr import read_exr  # noqa: E402
from pipeline.run import RunConfig, run  # noqa: E402

EVAL_DIR = ROOT.parent / "shared" / "eval-scenes"
TOLERANCE = 0.2


def budget_run(folder: Path, budget_s: float, curves: str | None, work: Path) -> dict[str, Any]:
    """One budgeted render-and-denoise of ``folder/scene.xml``; the figures of its metrics.json."""
    ref = folder / "reference.exr"
    h, w = read_exr(ref).rgb.shape[:2]
    cfg = RunConfig(scene=str(folder / "scene.xml"), out=str(work / f"{folder.name}-{budget_s:g}"),
                    resolution=(w, h), seed=7, model="auto", reference=str(ref), time_budget=budget_s,
                    curves=curves)
    metrics = run(cfg)
    plan = metrics["budget"]
    return {"scene": folder.name, "budget_s": budget_s, "model": plan["model"], "spp": plan["spp"],
            "rule": plan["rule"], "spent_s": plan["spent_s"], "predicted_s": plan["predicted_s"],
            "actual_s": plan["actual_s"], "ratio": plan["actual_s"] / budget_s,
            "within": abs(plan["actual_s"] / budget_s - 1) <= TOLERANCE,
            "psnr": metrics["quality"]["denoised"]["psnr"], "noisy_psnr": metrics["quality"]["noisy"]["psnr"]}


def markdown(rows: list[dict[str, Any]], summary: dict[str, Any]) -> str:
    lines = ["| scene | budget s | model | spp | predicted s | actual s | actual/budget | PSNR dB |",
             "|---|---:|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['budget_s']:g} | {r['model']} | {r['spp']} | {r['predicted_s']:.2f} | "
                     f"{r['actual_s']:.2f} | {r['ratio']:.2f}{'' if r['within'] else ' (!)'} | {r['psnr']:.2f} |")
    for b, s in summary["per_budget"].items():
        lines.append(f"| **{s['within']}/{s['runs']} within 20%** | {b} | | | | | {s['min_ratio']:.2f}-"
                     f"{s['max_ratio']:.2f} | {s['mean_psnr']:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--budgets", default="4,15", help="comma-separated budgets in seconds")
    p.add_argument("--scenes", help="comma-separated subset of scene folder names")
    p.add_argument("--curves", help="tradeoff.json guiding the model choice (default: the shipped one, if any)")
    p.add_argument("--eval-dir", default=str(EVAL_DIR))
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    args = p.parse_args()
    eval_dir = Path(args.eval_dir)
    names = sorted(d.name for d in eval_dir.iterdir() if (d / "reference.exr").exists()) \
        if eval_dir.is_dir() else []
    if args.scenes:
        names = [n for n in names if n in args.scenes.split(",")]
    if not names:
        print(f"budget: no evaluation scenes found in {eval_dir}", file=sys.stderr)
        return 1
    budgets = [float(b) for b in args.budgets.split(",")]
    load = os.getloadavg()[0]
    rows: list[dict[str, Any]] = []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as work:
        for name in names:
            for b in budgets:
                rows.append(budget_run(eval_dir / name, b, args.curves, Path(work)))
                r = rows[-1]
                print(f"{name} {b:g} s: {r['model']} {r['spp']} spp, predicted {r['predicted_s']:.2f} s, "
                      f"actual {r['actual_s']:.2f} s, PSNR {r['psnr']:.2f} dB", flush=True)
    per_budget = {}
    for b in budgets:
        sel = [r for r in rows if r["budget_s"] == b]
        per_budget[f"{b:g}"] = {"runs": len(sel), "within": sum(r["within"] for r in sel),
                                "min_ratio": min(r["ratio"] for r in sel), "max_ratio": max(r["ratio"] for r in sel),
                                "mean_psnr": float(np.mean([r["psnr"] for r in sel])),
                                "models": {m: sum(r["model"] == m for r in sel) for m in {r["model"] for r in sel}}}
    summary = {"runs": len(rows), "within": sum(r["within"] for r in rows), "per_budget": per_budget}
    result = {"tolerance": TOLERANCE, "summary": summary, "rows": rows, "wall_s": time.perf_counter() - start,
              "machine": {"cpu": platform.machine(), "cores": len(os.sched_getaffinity(0)),
                          "load_before": load, "load_after": os.getloadavg()[0]}}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "budget.json", json.dumps(result, indent=1) + "\n")
    table = markdown(rows, summary)
    write_text_atomic(out / "budget.md", table)
    print(table)
    print(f"{summary['within']}/{summary['runs']} runs within 20% of the budget; wrote {out / 'budget.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
