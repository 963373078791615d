"""``tradeoff``'s outputs: the CSV, the error-against-time plot, the equal-quality table and the
HTML report (:mod:`pipeline.viewer`'s page: plot and tables).

All read the result dict of :func:`pipeline.tradeoff.measure` (seconds, metric values as
:mod:`imaging.metrics` computes them; the plotted error is :func:`pipeline.pareto.metric_error`).
The plot and the page name OIDN's two entries (``oidn``, ``oidn_aux`` in the CSV, the JSON and the
printed table) "OIDN colour-only" and "OIDN + albedo + normal".
"""
from __future__ import annotations

import csv
import io
import math
from pathlib import Path
from typing import Any

from imaging.atomic_io import write_text_atomic
from pipeline.evaluation import OIDN_LABELS
from pipeline.pareto import ERROR_LABEL, metric_error
from pipeline.viewer import Page, Table, details, png_figure

CSV_FIELDS = ("denoiser", "spp", "render_s", "denoise_s", "total_s", "psnr", "relmse", "flip",
              "pareto", "equal_quality_raw_spp", "equal_quality_saving")


def _equal_rows(result: dict[str, Any]) -> dict[tuple[str, int], dict[str, Any]]:
    return {(r["denoiser"], r["spp"]): r for r in result["equal_quality"] if r["metric"] == result["metric"]}


def write_csv(path: Path, result: dict[str, Any]) -> None:
    """One row per (denoiser, spp): times, metrics, on the Pareto front of ``result['metric']``,
    and the equal-quality raw spp and saving (empty for the raw render)."""
    front = {tuple(p) for p in result["pareto"][result["metric"]]}
    equal = _equal_rows(result)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=CSV_FIELDS, lineterminator="\n")
    writer.writeheader()
    for p in result["points"]:
        eq = equal.get((p["denoiser"], p["spp"]), {})
        writer.writerow({**{k: p[k] for k in CSV_FIELDS[:8]},
                         "pareto": int((p["denoiser"], p["spp"]) in front),
                         "equal_quality_raw_spp": eq.get("raw_spp", ""),
                         "equal_quality_saving": eq.get("saving", "")})
    write_text_atomic(path, buf.getvalue())


def plot_tradeoff(path: Path, result: dict[str, Any]) -> None:
    """Log-log error (``result['metric']``) against total seconds: one curve per denoiser, spp
    written beside the raw curve's points, the Pareto frontier drawn as a dashed black staircase."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    metric = result["metric"]
    fig, ax = plt.subplots(figsize=(7.5, 5.0), dpi=120)
    names = list(dict.fromkeys(p["denoiser"] for p in result["points"]))
    for name in names:
        pts = sorted((p for p in result["points"] if p["denoiser"] == name), key=lambda p: p["spp"])
        xy = [(p["total_s"], metric_error(metric, p[metric]), p["spp"]) for p in pts]
        xy = [(x, y, s) for x, y, s in xy if x > 0 and y > 0 and math.isfinite(y)]
        if not xy:
            continue
        style = dict(color="0.45", linestyle=":") if name == "none" else {}
        ax.plot([v[0] for v in xy], [v[1] for v in xy], marker="o", ms=4,
                label="raw render" if name == "none" else OIDN_LABELS.get(name, name), **style)
        if name == "none":
            for x, y, s in xy:
                ax.annotate(f"{s}", (x, y), textcoords="offset points", xytext=(3, 3), fontsize=7,
                            color="0.35")
    lookup = {(p["denoiser"], p["spp"]): p for p in result["points"]}
    front = [lookup[(d, s)] for d, s in result["pareto"][metric]]
    fx = [p["total_s"] for p in front]
    fy = [metric_error(metric, p[metric]) for p in front]
    keep = [(x, y) for x, y in zip(fx, fy) if x > 0 and y > 0]
    if keep:
        ax.step([k[0] for k in keep], [k[1] for k in keep], where="post", color="black",
                linestyle="--", linewidth=1, label="Pareto frontier")
        ax.scatter([k[0] for k in keep], [k[1] for k in keep], s=70, facecolors="none",
                   edgecolors="black", linewidths=1.2, zorder=5)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("total time: render + denoise (s, median)")
    ax.set_ylabel(ERROR_LABEL[metric])
    w, h = result["resolution"]
    ax.set_title(f"{Path(result['scene']).parent.name or Path(result['scene']).stem} "
                 f"({Path(result['scene']).name}, {w}x{h}): error against time", fontsize=9)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    tmp.replace(path)


def _num(value: float | None, fmt: str) -> str:
    return "-" if value is None or not math.isfinite(value) else format(value, fmt)


def saving_table(result: dict[str, Any]) -> list[str]:
    """The equal-quality table: for each denoised point, the raw spp of the same error, its time
    and the ratio of times ('~': extrapolated beyond the measured raw spp)."""
    metric = result["metric"]
    lines = [f"equal-quality saving ({ERROR_LABEL[metric]}; ~ = extrapolated beyond the measured spp)",
             f"{'denoiser':12}{'spp':>6}{'time s':>9}{metric:>10}{'raw spp':>11}{'raw s':>9}{'saving':>9}"]
    points = {(p["denoiser"], p["spp"]): p for p in result["points"]}
    for eq in _equal_rows(result).values():
        p = points[(eq["denoiser"], eq["spp"])]
        mark = "~" if eq["extrapolated"] else ""
        value = p[metric]
        lines.append(f"{eq['denoiser']:12}{eq['spp']:>6}{p['total_s']:>9.3f}"
                     f"{_num(value, '.4g'):>10}{mark + _num(eq['raw_spp'], '.0f'):>11}"
                     f"{_num(eq['raw_s'], '.3f'):>9}{_num(eq['saving'], '.2f') + 'x':>9}")
    return lines


def recommendation(result: dict[str, Any]) -> dict[str, Any] | None:
    """The one choice a run recommends: of the denoised points (ours and OIDN) on the Pareto front
    of the run's metric, the one with the largest equal-quality saving (the render alone would take
    the most times as long for that error); None when no denoised point is on the front."""
    metric = result["metric"]
    front = {tuple(p) for p in result["pareto"][metric]}
    rows = [r for r in _equal_rows(result).values()
            if (r["denoiser"], r["spp"]) in front and r["saving"] is not None and math.isfinite(r["saving"])]
    if not rows:
        return None
    best = max(rows, key=lambda r: (r["saving"], -r["spp"]))
    point = next(p for p in result["points"] if (p["denoiser"], p["spp"]) == (best["denoiser"], best["spp"]))
    return {"denoiser": best["denoiser"], "spp": best["spp"], "total_s": point["total_s"], metric: point[metric],
            "raw_spp": best["raw_spp"], "saving": best["saving"], "extrapolated": best["extrapolated"]}


def recommendation_line(result: dict[str, Any]) -> str:
    """:func:`recommendation` as one sentence."""
    rec = recommendation(result)
    if rec is None:
        return "recommended: the raw render (no denoised point is on the Pareto front)"
    metric = result["metric"]
    raw = f"{'~' if rec['extrapolated'] else ''}{rec['raw_spp']:.0f}"
    return (f"recommended: {rec['denoiser']} at {rec['spp']} spp ({rec['total_s']:.2f} s, {metric} "
            f"{_num(rec[metric], '.4g')}): the render alone needs {raw} spp for that, {rec['saving']:.1f}x the time")


def tradeoff_page(result: dict[str, Any], plot_png: bytes) -> Page:
    """The HTML report of a tradeoff run (the report viewer's page): the plot, the equal-quality
    table and every measured point (Pareto points marked, best value per column highlighted)."""
    metric = result["metric"]
    w, h = result["resolution"]
    ref = result.get("reference") or {}
    page = Page(f"{Path(result['scene']).name}: error against time",
                f"{w}x{h}; reference {ref.get('spp', '')} spp {ref.get('file') or ''}; "
                f"Mitsuba {result.get('mitsuba', '')} ({result.get('variant', '')}); "
                f"times are medians of repeated runs")
    page.add_section("Recommended", f"<p>{recommendation_line(result)}</p>")
    page.add_section("Error against time", png_figure(plot_png, f"{ERROR_LABEL[metric]} against "
                                                      "render + denoise seconds, Pareto frontier dashed"))
    points = {(p["denoiser"], p["spp"]): p for p in result["points"]}
    saving = Table(["denoiser", "spp", "time s", metric, "raw spp of equal error", "raw s", "saving x"],
                   better={"saving x": "high"})
    for eq in _equal_rows(result).values():
        raw = f"~{eq['raw_spp']:.0f}" if eq["extrapolated"] and eq["raw_spp"] is not None else eq["raw_spp"]
        point = points[(eq["denoiser"], eq["spp"])]
        saving.rows.append([OIDN_LABELS.get(eq["denoiser"], eq["denoiser"]), eq["spp"], point["total_s"],
                            point[metric], raw, eq["raw_s"], eq["saving"]])
    page.add_section(f"Equal-quality saving ({ERROR_LABEL[metric]})",
                     "<p class='note'>the raw render's spp (and time) that reaches each denoised point's "
                     "error; ~ = extrapolated beyond the measured spp</p>" + saving.html())
    front = {tuple(p) for p in result["pareto"][metric]}
    table = Table(["denoiser", "spp", "render s", "denoise s", "total s", "PSNR dB", "relMSE", "FLIP",
                   "Pareto"], better={"PSNR dB": "high", "relMSE": "low", "FLIP": "low"})
    for p in result["points"]:
        table.rows.append([OIDN_LABELS.get(p["denoiser"], p["denoiser"]), p["spp"], p["render_s"], p["denoise_s"],
                           p["total_s"], p["psnr"], p["relmse"], p["flip"],
                           "yes" if (p["denoiser"], p["spp"]) in front else ""])
    page.add_section("Every measurement", table.html())
    page.add_section("Run", details({k: v for k, v in result.items()
                                     if k not in ("points", "pareto", "equal_quality")}))
    return page


def write_report(path: Path, result: dict[str, Any], plot: Path) -> None:
    """Write the tradeoff run's ``report.html`` beside its plot (embedded, self-contained)."""
    tradeoff_page(result, plot.read_bytes()).write(path)
