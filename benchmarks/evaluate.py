"""The quality scoreboard: every scene of ../shared/eval-scenes, noisy vs ours vs OIDN colour-only.

For each scene and spp (default 16 and 128, seed 7 as in the scenes' reference.json): render with
the box filter, denoise with our model and with OIDN (``pyoidn``, colour only, hdr) side by side,
and compare with the stored 2048-spp ``reference.exr``: PSNR (tonemapped x/(1+x), gamma 1/2.2),
relMSE (eps 0.01), FLIP (LDR), and denoise seconds. Our noisy PSNR is checked against the one
recorded in reference.json (same renderer, same seed: it must match). Scenes whose reference noise
ceiling (``reference_psnr_ceiling_db``) is below ``--ceiling-db`` are reported but flagged: at
128 spp their reference is not much cleaner than the input, so no denoiser can be scored there.

With ``--models fast,balanced,high`` (preset names or checkpoint paths) every model denoises the
same renders; the first is "ours" in the per-scene table, and a second table compares the models'
means and denoise times (seconds per megapixel) with OIDN's.

Usage: python benchmarks/evaluate.py [--model PATH | --models A,B,C] [--spp 16,128] [--scenes a,b]
       [--out DIR] [--report-spp N]
Writes DIR/evaluate.json, DIR/evaluate.md and DIR/evaluate.html (default DIR: benchmarks/results):
the scoreboard page of the report viewer, every scene's noisy / ours / OIDN / reference images at
``--report-spp`` (default: the lowest spp; about 1 MB per 256-px scene) with FLIP maps, and the tables.
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imaging.atomic_io import write_text_atomic  # noqa: E402
from imaging.errors import DenoiserError  # noqa: E402
from imaging.exr import read_exr  # noqa: E402
from imaging.metrics import flip, psnr, relmse  # noqa: E402
from imaging.render import load_scene, prepare, render_loaded  # noqa: E402
from pipeline.denoise import Denoiser  # noqa: E402
from pipeline.oidn import oidn_denoise  # noqa: E402
from pipeline.viewer import Page, Table, ViewerRow, ViewerSet, flip_map  # noqa: E402

EVAL_DIR = ROOT.parent / "shared" / "eval-scenes"
SEED = 7


def _scores(img: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    return {"psnr": psnr(img, ref), "relmse": relmse(img, ref), "flip": flip(img, ref)}


def evaluate_scene(folder: Path, spps: list[int], denoisers: dict[str, Denoiser],
                   keep: dict[str, np.ndarray] | None = None, keep_spp: int | None = None) -> dict[str, Any]:
    """Render ``folder/scene.xml`` at each spp; score noisy, each model and OIDN against its reference.

    The first model's figures are also stored as ``ours``; every model's under ``models``. With
    ``keep``, the images at ``keep_spp`` (noisy, ours, oidn) and the reference are put in it.
    """
    info = json.loads((folder / "reference.json").read_text())
    ref = read_exr(folder / "reference.exr").rgb
    h, w = ref.shape[:2]
    scene = load_scene(prepare(folder / "scene.xml", (w, h)))
    row: dict[str, Any] = {"ceiling_db": info["reference_psnr_ceiling_db"], "resolution": [w, h]}
    for spp in spps:
        noisy = render_loaded(scene, spp, SEED)
        models, ours_image = {}, None
        for name, denoiser in denoisers.items():
            result = denoiser.denoise_array(noisy.rgb)
            models[name] = {**_scores(result.image, ref), "s": result.seconds}
            ours_image = result.image if ours_image is None else ours_image
        oidn, oidn_s = oidn_denoise(noisy.rgb)
        if keep is not None and spp == keep_spp:
            keep.update(noisy=noisy.rgb, ours=ours_image, oidn=oidn, reference=ref)
        first = models[next(iter(models))]
        entry = {"render_s": noisy.seconds, "ours_s": first["s"], "oidn_s": oidn_s,
                 "noisy": _scores(noisy.rgb, ref), "ours": {k: v for k, v in first.items() if k != "s"},
                 "oidn": _scores(oidn, ref), "models": models}
        recorded = info.get(f"spp{spp}", {}).get("noisy_psnr")
        if recorded is not None:
            entry["noisy_psnr_recorded"] = recorded
        row[str(spp)] = entry
    return row


def _mean(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def summarize(rows: dict[str, Any], spps: list[int], ceiling_db: float) -> dict[str, Any]:
    """Means over the scenes whose reference ceiling is >= ``ceiling_db`` (and over all), for the
    first model (``ours_*``) and, under ``models``, for each model (seconds per megapixel too)."""
    out: dict[str, Any] = {}
    for subset, names in (("scored", [n for n, r in rows.items() if r["ceiling_db"] >= ceiling_db]),
                          ("all", list(rows))):
        out[subset] = {"scenes": len(names)}
        for spp in spps:
            key = str(spp)
            out[subset][key] = {
                f"{who}_{metric}": _mean([rows[n][key][who][metric] for n in names])
                for who in ("noisy", "ours", "oidn") for metric in ("psnr", "relmse", "flip")}
            out[subset][key]["ours_s"] = _mean([rows[n][key]["ours_s"] for n in names])
            out[subset][key]["oidn_s"] = _mean([rows[n][key]["oidn_s"] for n in names])
            mpix = [rows[n]["resolution"][0] * rows[n]["resolution"][1] / 1e6 for n in names]
            out[subset][key]["oidn_s_per_mp"] = _mean([rows[n][key]["oidn_s"] / mp for n, mp in zip(names, mpix)])
            out[subset][key]["models"] = {
                model: {**{metric: _mean([rows[n][key]["models"][model][metric] for n in names])
                           for metric in ("psnr", "relmse", "flip")},
                        "s_per_mp": _mean([rows[n][key]["models"][model]["s"] / mp for n, mp in zip(names, mpix)])}
                for model in rows[names[0]][key]["models"]} if names else {}
    return out


def markdown(rows: dict[str, Any], summary: dict[str, Any], spps: list[int], ceiling_db: float,
             model: str) -> str:
    """The scoreboard as a markdown table (one row per scene and spp, then the means)."""
    lines = [f"Model `{model}`; PSNR dB (tonemapped) / relMSE / FLIP against the 2048-spp "
             f"references; * = reference ceiling below {ceiling_db:g} dB (not in the scored mean).", "",
             "| scene | spp | noisy PSNR | ours PSNR | OIDN PSNR | noisy relMSE | ours relMSE | "
             "OIDN relMSE | ours FLIP | OIDN FLIP | ours s | OIDN s |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, row in rows.items():
        flag = "*" if row["ceiling_db"] < ceiling_db else ""
        for spp in spps:
            e = row[str(spp)]
            lines.append(
                f"| {name}{flag} | {spp} | {e['noisy']['psnr']:.2f} | {e['ours']['psnr']:.2f} | "
                f"{e['oidn']['psnr']:.2f} | {e['noisy']['relmse']:.4f} | {e['ours']['relmse']:.4f} | "
                f"{e['oidn']['relmse']:.4f} | {e['ours']['flip']:.3f} | {e['oidn']['flip']:.3f} | "
                f"{e['ours_s']:.2f} | {e['oidn_s']:.2f} |")
    for subset in ("scored", "all"):
        s = summary[subset]
        for spp in spps:
            m = s[str(spp)]
            lines.append(
                f"| **mean, {subset} ({s['scenes']})** | {spp} | {m['noisy_psnr']:.2f} | "
                f"{m['ours_psnr']:.2f} | {m['oidn_psnr']:.2f} | {m['noisy_relmse']:.4f} | "
                f"{m['ours_relmse']:.4f} | {m['oidn_relmse']:.4f} | {m['ours_flip']:.3f} | "
                f"{m['oidn_flip']:.3f} | {m['ours_s']:.2f} | {m['oidn_s']:.2f} |")
    return "\n".join(lines) + "\n"


def models_markdown(summary: dict[str, Any], spps: list[int]) -> str:
    """Each model's scored means next to the noisy input's and OIDN's, with seconds per megapixel."""
    s = summary["scored"]
    lines = [f"Scored mean over {s['scenes']} scenes; PSNR dB / relMSE / FLIP; s/MP = denoise seconds "
             "per megapixel (this run, 256-px images).", "",
             "| denoiser | spp | PSNR | relMSE | FLIP | s/MP |", "|---|---:|---:|---:|---:|---:|"]
    for spp in spps:
        m = s[str(spp)]
        lines.append(f"| noisy | {spp} | {m['noisy_psnr']:.2f} | {m['noisy_relmse']:.4f} | "
                     f"{m['noisy_flip']:.3f} | - |")
        for name, e in m["models"].items():
            lines.append(f"| {name} | {spp} | {e['psnr']:.2f} | {e['relmse']:.4f} | {e['flip']:.3f} | "
                         f"{e['s_per_mp']:.2f} |")
        lines.append(f"| OIDN | {spp} | {m['oidn_psnr']:.2f} | {m['oidn_relmse']:.4f} | "
                     f"{m['oidn_flip']:.3f} | {m['oidn_s_per_mp']:.2f} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--model", help="checkpoint (default: the shipped weights)")
    p.add_argument("--models", help="comma-separated preset names or checkpoints, all on the same renders")
    p.add_argument("--spp", default="16,128")
    p.add_argument("--scenes", help="comma-separated subset of scene folder names")
    p.add_argument("--ceiling-db", type=float, default=40.0,
                   help="flag scenes whose reference ceiling is below this (default 40 dB)")
    p.add_argument("--eval-dir", default=str(EVAL_DIR))
    p.add_argument("--out", default=str(ROOT / "benchmarks" / "results"))
    p.add_argument("--report-spp", type=int, help="spp whose images evaluate.html shows (default: the lowest)")
    args = p.parse_args()
    eval_dir = Path(args.eval_dir)
    if not eval_dir.is_dir():
        print(f"evaluate: {eval_dir}: evaluation scenes not found", file=sys.stderr)
        return 1
    spps = [int(s) for s in args.spp.split(",")]
    names = sorted(d.name for d in eval_dir.iterdir() if (d / "reference.exr").exists())
    if args.scenes:
        wanted = args.scenes.split(",")
        missing = sorted(set(wanted) - set(names))
        if missing:
            print(f"evaluate: unknown scene(s): {', '.join(missing)}", file=sys.stderr)
            return 1
        names = [n for n in names if n in wanted]
    if args.model and args.models:
        print("evaluate: give --model or --models, not both", file=sys.stderr)
        return 2
    try:
        specs = args.models.split(",") if args.models else [args.model]
        denoisers = {spec if spec else "default": Denoiser(spec) for spec in specs}
    except DenoiserError as exc:
        print(f"evaluate: {exc}", file=sys.stderr)
        return 1
    for d in denoisers.values():  # first calls pay one-off set-up: keep it out of the timings
        d.denoise_array(np.full((64, 64, 3), 0.5, dtype=np.float32))
    denoiser = next(iter(denoisers.values()))
    report_spp = args.report_spp or min(spps)
    if report_spp not in spps:
        print(f"evaluate: --report-spp {report_spp} is not one of --spp {args.spp}", file=sys.stderr)
        return 2
    start = time.perf_counter()
    rows: dict[str, Any] = {}
    images: dict[str, dict[str, np.ndarray]] = {}
    for name in tqdm(names, desc="eval scenes", unit="scene"):
        images[name] = {}
        rows[name] = evaluate_scene(eval_dir / name, spps, denoisers, images[name], report_spp)
    summary = summarize(rows, spps, args.ceiling_db)
    result = {"model": {"path": str(denoiser.path), "sha256": denoiser.sha256,
                        "config": denoiser.config.to_dict(), "step": denoiser.meta.get("step")},
              "models": {name: {"path": str(d.path), "sha256": d.sha256, "config": d.config.to_dict(),
                                "step": d.meta.get("step")} for name, d in denoisers.items()},
              "spp": spps, "seed": SEED, "ceiling_db": args.ceiling_db, "summary": summary,
              "scenes": rows, "wall_s": time.perf_counter() - start,
              "machine": {"cpu": platform.processor() or platform.machine(), "cores": _cores()}}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "evaluate.json", json.dumps(result, indent=1, default=_json_default) + "\n")
    table = markdown(rows, summary, spps, args.ceiling_db, denoiser.name)
    if len(denoisers) > 1:
        table += "\n" + models_markdown(summary, spps)
    write_text_atomic(out / "evaluate.md", table)
    scoreboard_page(result, images, report_spp).write(out / "evaluate.html")
    print(table)
    print(f"wrote {out / 'evaluate.json'}, {out / 'evaluate.md'} and {out / 'evaluate.html'}")
    return 0


def scoreboard_page(result: dict[str, Any], images: dict[str, dict[str, np.ndarray]],
                    report_spp: int) -> Page:
    """The scoreboard in the report viewer: one set per scene (noisy / ours / OIDN / reference at
    ``report_spp``, FLIP maps against the reference; n / p flip scenes), the scored means, every
    scene's row and, with several models, their comparison. ``result``: evaluate.json's dict;
    ``images``: scene -> {noisy, ours, oidn, reference} HxWx3 linear radiance."""
    spps, ceiling = result["spp"], result["ceiling_db"]
    model = Path(result["model"]["path"]).name
    page = Page(f"Scoreboard: {len(result['scenes'])} evaluation scenes",
                f"model {model}; images at {report_spp} spp (seed {result['seed']}) against the "
                f"2048-spp references; {result['machine']['cores']} cores, {result['wall_s']:.0f} s")
    for name, imgs in images.items():
        if not imgs:
            continue
        ref = page.radiance(imgs["reference"])
        rows = [ViewerRow(label, page.radiance(imgs[key]), page.scalar(flip_map(imgs[key], imgs["reference"])))
                for key, label in (("noisy", "noisy"), ("ours", "ours"), ("oidn", "OIDN"))]
        e = result["scenes"][name][str(report_spp)]
        note = (f"{report_spp} spp, PSNR noisy {e['noisy']['psnr']:.2f} / ours {e['ours']['psnr']:.2f} / "
                f"OIDN {e['oidn']['psnr']:.2f} dB")
        page.add_set(ViewerSet(name, [*rows, ViewerRow("reference", ref)], ref, note))
    cols = ["PSNR dB", "relMSE", "FLIP"]
    means = Table(["denoiser", "spp", *cols, "s"], better={"PSNR dB": "high", "relMSE": "low", "FLIP": "low"})
    for spp in spps:
        m = result["summary"]["scored"][str(spp)]
        for who, label in (("noisy", "noisy"), ("ours", f"ours ({model})"), ("oidn", "OIDN")):
            means.rows.append([label, spp, m[f"{who}_psnr"], m[f"{who}_relmse"], m[f"{who}_flip"],
                               m.get(f"{who}_s")])
    page.add_section(f"Scored means ({result['summary']['scored']['scenes']} scenes, reference ceiling "
                     f">= {ceiling:g} dB)", means.html())
    per_scene = Table(["scene", "spp", "noisy PSNR", "ours PSNR", "OIDN PSNR", "ours relMSE", "OIDN relMSE",
                       "ours FLIP", "OIDN FLIP", "ours s", "OIDN s"])
    for name, row in result["scenes"].items():
        for spp in spps:
            e = row[str(spp)]
            per_scene.rows.append([name + ("*" if row["ceiling_db"] < ceiling else ""), spp,
                                   e["noisy"]["psnr"], e["ours"]["psnr"], e["oidn"]["psnr"],
                                   e["ours"]["relmse"], e["oidn"]["relmse"], e["ours"]["flip"],
                                   e["oidn"]["flip"], e["ours_s"], e["oidn_s"]])
    page.add_section("Every scene", f"<p class='note'>* reference ceiling below {ceiling:g} dB (not in "
                     "the scored mean)</p>" + per_scene.html())
    if len(result["models"]) > 1:
        table = Table(["model", "spp", *cols, "s/MP"], better={"PSNR dB": "high", "relMSE": "low", "FLIP": "low"})
        for spp in spps:
            for label, e in result["summary"]["scored"][str(spp)]["models"].items():
                table.rows.append([label, spp, e["psnr"], e["relmse"], e["flip"], e["s_per_mp"]])
        page.add_section("Models", table.html())
    return page


def _cores() -> int:
    import os

    return len(os.sched_getaffinity(0))


def _json_default(value: Any) -> Any:
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


if __name__ == "__main__":
    sys.exit(main())
