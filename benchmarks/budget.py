"""Budget mode on the eval scenes: is the denoised image ready within the time budget?

For each scene of ../shared/eval-scenes (at its reference's resolution) and each budget, runs the
library behind ``render-and-denoise scene.xml --time-budget B --model auto`` (every preset with
shipped weights is a candidate) against the scene's reference, and records the choice (model,
spp, rule), the predicted and the actual seconds (from the start of the run until the denoised
image exists, as the budget counts), and the denoised PSNR. Goal (issue 6): actual time within
20% of the budget. Run it on an idle machine: another job on the cores changes the render and
denoise speeds between the probes and the real work.

    python -m benchmarks.budget [--budgets 4,15] [--scenes a,b] [--curves tradeoff.json]

Prints a table and writes benchmarks/results/budget.json and budget.md.
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.eval_scenes import EVAL_DIR, RESULTS, EvalScene, eval_scenes, finish_record, run_record, \
    save_result
from console.usage import COMMAND_ERRORS, OneLineParser, name_list
from pipeline.run import RunConfig, run

TOLERANCE = 0.2


def budget_run(scene: EvalScene, budget_s: float, curves: str | None, work: Path) -> dict[str, Any]:
    """One budgeted render-and-denoise of ``scene``; the figures of its metrics.json."""
    cfg = RunConfig(scene.settings(), out=str(work / f"{scene.name}-{budget_s:g}"), model="auto",
                    time_budget=budget_s, curves=curves)
    metrics = run(cfg)
    plan = metrics["budget"]
    return {"scene": scene.name, "budget_s": budget_s, "model": plan["model"], "spp": plan["spp"],
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


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m benchmarks.budget", description=__doc__.split("\n")[0])
    p.add_argument("--budgets", default="4,15", help="comma-separated budgets in seconds")
    p.add_argument("--scenes", type=name_list, help="comma-separated subset of scene folder names")
    p.add_argument("--curves", help="tradeoff.json guiding the model choice (default: the shipped one, if any)")
    p.add_argument("--eval-dir", type=Path, default=EVAL_DIR)
    p.add_argument("--out", type=Path, default=RESULTS)
    argv = sys.argv[1:] if argv is None else argv
    args = p.parse_args(argv)
    try:
        budgets = [float(b) for b in args.budgets.split(",")]
    except ValueError:
        p.error(f"--budgets: expected comma-separated seconds, got {args.budgets!r}")
    rows: list[dict[str, Any]] = []
    try:
        scenes = eval_scenes(args.scenes, args.eval_dir)
        record, start = run_record("benchmarks.budget", argv), time.perf_counter()
        with tempfile.TemporaryDirectory() as work:
            for scene in scenes:
                for b in budgets:
                    rows.append(budget_run(scene, b, args.curves, Path(work)))
                    r = rows[-1]
                    print(f"{scene.name} {b:g} s: {r['model']} {r['spp']} spp, predicted {r['predicted_s']:.2f} s, "
                          f"actual {r['actual_s']:.2f} s, PSNR {r['psnr']:.2f} dB", flush=True)
    except COMMAND_ERRORS as exc:
        return p.fail(exc)
    summary = summarize(rows, budgets)
    result = {**finish_record(record, start), "tolerance": TOLERANCE, "summary": summary, "rows": rows}
    table = markdown(rows, summary)
    path = save_result(args.out, "budget", result, table)
    print(table)
    print(f"{summary['within']}/{summary['runs']} runs within 20% of the budget; wrote {path}")
    return 0


def summarize(rows: list[dict[str, Any]], budgets: list[float]) -> dict[str, Any]:
    """Per budget: runs within the tolerance, the range of actual/budget, mean PSNR, models chosen."""
    per_budget = {}
    for b in budgets:
        sel = [r for r in rows if r["budget_s"] == b]
        per_budget[f"{b:g}"] = {"runs": len(sel), "within": sum(r["within"] for r in sel),
                                "min_ratio": min(r["ratio"] for r in sel), "max_ratio": max(r["ratio"] for r in sel),
                                "mean_psnr": float(np.mean([r["psnr"] for r in sel])),
                                "models": {m: sum(r["model"] == m for r in sel) for m in {r["model"] for r in sel}}}
    return {"runs": len(rows), "within": sum(r["within"] for r in rows), "per_budget": per_budget}


if __name__ == "__main__":
    sys.exit(main())
