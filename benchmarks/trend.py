"""Where a training run is heading: validation PSNR against CPU time, and what the trend needs to reach OIDN.

For each run log (``RUN_DIR`` or its ``log.jsonl``, or a shipped ``model/weights/<name>_log.jsonl``),
fits PSNR = a + b * log2(CPU minutes) by least squares to the validations of the later part of the
run (CPU time >= ``--from`` times the last validation's; the early rise says little about the end),
overall and at each ``--spp``: ``b`` is the gain per doubling of CPU time. Where b > 0 the fit is
extrapolated to OIDN colour-only's PSNR on the same images (logged with every validation): the
CPU-hours at which the trend would reach it. A straight line in log-time is an optimistic model of
a flattening curve, so read the projection as a lower bound; the fit's residual scatter is given
beside it, and a window with fewer than 3 validations gets no fit.

    python -m benchmarks.trend RUN [RUN ...] [--from 0.5] [--spp 4,16,128] [--offset-min M] [--out DIR]

``--offset-min``: CPU minutes spent before these logs start (the earlier stages of a warm start),
added to every point. Writes DIR/trend.json and trend.md (default DIR: benchmarks/results).
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.eval_scenes import RESULTS, run_record, save_result
from console.usage import COMMAND_ERRORS, OneLineParser, int_list, positive_float
from training.run_log import RunLog, validation_curve

MIN_POINTS = 3
FAR_HOURS = 10_000  # projections beyond this are shown as "> 10,000"


def fit(points: list[tuple[float, float]], target: float | None) -> dict[str, Any] | None:
    """Least-squares PSNR = a + b log2(minutes) over ``points`` (minutes, dB); None with fewer than
    :data:`MIN_POINTS`. ``end_db``: the fit at the last point; ``hours_to_target``: where the line
    reaches ``target`` (None when b <= 0 or no target; before the last point when it is already past)."""
    if len(points) < MIN_POINTS:
        return None
    x = np.log2([m for m, _ in points])
    y = np.array([db for _, db in points])
    if np.ptp(x) == 0:
        return None
    b, a = np.polyfit(x, y, 1)
    residual = float(np.std(y - (a + b * x)))
    end = float(a + b * x[-1])
    hours = 2.0 ** ((target - a) / b) / 60 if target is not None and b > 0 else None
    return {"db_per_doubling": float(b), "end_db": end, "scatter_db": residual, "points": len(points),
            "minutes": [points[0][0], points[-1][0]], "target_db": target, "hours_to_target": hours}


def trend(curve: list[dict[str, Any]], spps: list[int], start: float = 0.5,
          offset_min: float = 0.0) -> dict[str, Any]:
    """The fits of one run's :func:`training.run_log.validation_curve`: ``overall`` (mean over its
    spp levels, against OIDN's mean) and ``per_spp``; the window is CPU time >= ``start`` times
    the last validation's (after adding ``offset_min``)."""
    if not curve:
        raise ValueError("no validations with CPU times in this log")
    points = [{**c, "cpu_min": c["cpu_min"] + offset_min} for c in curve]
    final = points[-1]
    window = [c for c in points if c["cpu_min"] >= start * final["cpu_min"] and c["cpu_min"] > 0]

    def oidn_mean(c: dict[str, Any]) -> float | None:
        values = list(c["oidn"].values())
        return None if any(v is None for v in values) or not values else float(np.mean(values))

    overall = fit([(c["cpu_min"], c["psnr"]) for c in window], oidn_mean(final))
    per_spp = {str(spp): fit([(c["cpu_min"], c["per_spp"][str(spp)]) for c in window
                              if c["per_spp"].get(str(spp)) is not None], final["oidn"].get(str(spp)))
               for spp in spps if str(spp) in final["per_spp"]}
    return {"validations": len(curve), "last_step": final["step"], "last_cpu_min": final["cpu_min"], "overall": overall,
            "per_spp": per_spp}


def _hours(f: dict[str, Any]) -> str:
    hours = f["hours_to_target"]
    if hours is None:
        return "never (flat or falling)" if f["target_db"] is not None else "-"
    return f"> {FAR_HOURS:,}" if hours > FAR_HOURS else f"{hours:.1f}"


def note(result: dict[str, Any]) -> str:
    """What the table's figures are."""
    offset = f", {result['offset_min']:g} CPU-minutes of earlier stages added" if result.get("offset_min") else ""
    return (f"Fit PSNR = a + b log2(CPU minutes) over the validations at >= {result['from']:g}x the last one's CPU "
            f"time{offset}; b per doubling of CPU time; OIDN colour-only on the same images; hours: where the line "
            "reaches OIDN (a straight line in log-time flatters a flattening curve: a lower bound).")


def table(result: dict[str, Any]) -> list[str]:
    """One row per run and spp (``mean``: over the run's spp levels)."""
    lines = ["| run | spp | validations fitted | CPU-min | fit at end dB | dB per doubling | scatter dB | OIDN dB "
             "| CPU-hours to OIDN |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, run in result["runs"].items():
        for label, f in [("mean", run["overall"]), *run["per_spp"].items()]:
            if f is None:
                lines.append(f"| {name} | {label} | < {MIN_POINTS} |  |  |  |  |  |  |")
                continue
            lines.append(f"| {name} | {label} | {f['points']} | {f['minutes'][0]:.0f}-{f['minutes'][1]:.0f} | "
                         f"{f['end_db']:.2f} | {f['db_per_doubling']:+.2f} | {f['scatter_db']:.2f} | "
                         f"{'-' if f['target_db'] is None else format(f['target_db'], '.2f')} | {_hours(f)} |")
    return lines


def markdown(result: dict[str, Any]) -> str:
    """trend.md: the command, :func:`note` and :func:`table`."""
    return "\n".join([f"Source: `{result['command']}`; {result['date']}. {note(result)}", "", *table(result)]) + "\n"


def _log_path(run: Path) -> Path:
    path = run / "log.jsonl" if run.is_dir() else run
    if not path.exists():
        raise FileNotFoundError(2, "No such file or directory", str(path))
    return path


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="python -m benchmarks.trend", description=__doc__.splitlines()[0])
    p.add_argument("runs", type=Path, nargs="+", help="run folders or log files")
    p.add_argument("--from", dest="start", type=float, default=0.5,
                   help="fit the validations at >= this share of the last one's CPU time (0.5)")
    p.add_argument("--spp", type=int_list, default=(4, 16, 128))
    p.add_argument("--offset-min", type=positive_float, default=0.0,
                   help="CPU minutes before these logs (earlier stages of a warm start)")
    p.add_argument("--out", type=Path, default=RESULTS)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(argv)
    if not 0 <= args.start < 1:
        parser.error(f"--from must be in [0, 1), got {args.start:g}")
    try:
        runs = {}
        for run in args.runs:
            path = _log_path(run)
            try:
                runs[str(run)] = trend(validation_curve(RunLog(path).read()), list(args.spp), args.start,
                                       args.offset_min)
            except ValueError as exc:
                raise ValueError(f"{path}: {exc}") from None
    except COMMAND_ERRORS as exc:
        return parser.fail(exc)
    result = {**run_record("benchmarks.trend", argv), "from": args.start, "offset_min": args.offset_min, "runs": runs}
    text = markdown(result)
    save_result(args.out, "trend", result, text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
