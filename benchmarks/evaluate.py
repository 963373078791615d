"""The quality scoreboard: every scene of ../shared/eval-scenes, noisy vs ours vs OIDN colour-only vs
OIDN + albedo + normal.

Each scene at each spp (default 4, 16 and 128; seed 7, as the scenes' reference.json) goes through
the path ``render-and-denoise`` takes (:func:`pipeline.evaluation.evaluate`): a render in two halves,
each model with its noise input, the noise guard and the energy correction ("ours", the default
path), the same network output before the guard as extra columns ("bare"), and OIDN on the same
render: colour-only (``oidn``) and with the albedo and normals of an AOV pass at the same spp and
seed (``oidn_aux``; :func:`pipeline.evaluation.with_aovs`, its seconds ``aov_render_s``). All are
scored against the stored 2048-spp ``reference.exr``: PSNR (tonemapped x/(1+x), gamma 1/2.2),
relMSE (eps 0.01), FLIP (LDR), and denoise seconds. Scenes whose reference noise ceiling
(``reference_psnr_ceiling_db``) is below ``--ceiling-db`` are reported but flagged and left out of
the scored mean: their reference is not much cleaner than a 128-spp input.

With ``--models fast,balanced,high`` (preset names or checkpoint paths) every model denoises the
same renders; the first is "ours" in the per-scene table, and a second table compares the models'
means and denoise times (seconds per megapixel) with OIDN's.

    python -m benchmarks.evaluate [--model PATH | --models A,B,C] [--spp 4,16,128] [--scenes a,b]
        [--out DIR] [--report-spp N]

Writes DIR/evaluate.json, DIR/evaluate.md and DIR/evaluate.html (default DIR: benchmarks/results):
the scoreboard page of the report viewer, every scene's noisy / ours / bare / OIDN colour-only /
OIDN + albedo + normal / reference images at ``--report-spp`` (default: the lowest spp; about 1 MB
per 256-px scene) with FLIP maps, and the tables. The full run (17 scenes, 3 spp, 256 px, three
models) took 32 minutes on 2 cores shared with other work (load 8-12; evaluate.json records it).
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from benchmarks.eval_scenes import (CEILING_DB, EVAL_DIR, RESULTS, SEED, EvalScene, eval_scenes, finish_record,
                                   run_record)
from imaging.atomic_io import write_json_atomic, write_text_atomic
from console.usage import COMMAND_ERRORS, OneLineParser, int_list, name_list
from denoise.flips import FLIPS
from denoise.precision import PRECISIONS
from denoise.denoiser import Denoiser
from denoise.energy import settings_if
from pipeline.evaluation import BARE, OIDN, OIDN_AUX, OIDN_LABELS, evaluate
from pipeline.viewer import Page, Table, ViewerRow, ViewerSet, flip_map

METRICS = ("psnr", "relmse", "flip")
ENERGY_CHOICES = ("on", "off")  # --energy
WHO = ("noisy", "ours", "ours_bare", OIDN, OIDN_AUX)  # the columns of the per-scene table
LABELS = {"noisy": "noisy", "ours": "ours", "ours_bare": "bare", **OIDN_LABELS}
PATH = ("render in two halves at the seed; ours: each model as render-and-denoise applies it (noise "
        "input, noise guard, energy correction); bare: the same network output before the guard; OIDN 2.5 "
        "on the same render, colour-only and with the albedo and normals of an AOV pass at the same spp and seed")


def evaluate_scene(scene: EvalScene, spps: list[int], denoisers: dict[str, Denoiser],
                   keep: dict[str, np.ndarray] | None = None, keep_spp: int | None = None) -> dict[str, Any]:
    """Every spp of ``scene`` through :func:`pipeline.evaluation.evaluate`: the scores of the
    render, each model (``models``) and its bare network (``bare``), and OIDN colour-only
    (``oidn``) and with albedo and normals (``oidn_aux``); the first model's figures also as
    ``ours`` / ``ours_bare``. With ``keep``, the images at ``keep_spp`` (noisy, ours, ours_bare,
    oidn, oidn_aux) and the reference are put in it."""
    ref = scene.reference()
    settings = scene.settings(resolution=(ref.shape[1], ref.shape[0]))
    loaded = settings.load()
    first = next(iter(denoisers))
    row: dict[str, Any] = {"ceiling_db": scene.ceiling_db, "resolution": [ref.shape[1], ref.shape[0]]}
    for spp in spps:
        ev = evaluate(loaded, spp, settings, ref, denoisers, oidn=True, bare=True)
        s = ev.scores
        entry = {"render_s": ev.render.seconds, "aov_render_s": ev.aov_seconds, "noisy": s["noisy"],
                 "ours": s[first], "ours_bare": s[first + BARE], OIDN: s[OIDN], OIDN_AUX: s[OIDN_AUX],
                 "ours_s": ev.outputs[first].seconds, "oidn_s": ev.outputs[OIDN].seconds,
                 "oidn_aux_s": ev.outputs[OIDN_AUX].seconds,
                 "models": {name: {**s[name], "s": ev.outputs[name].seconds,
                                   "guard_weight": ev.outputs[name].result.guard_weight} for name in denoisers},
                 "bare": {name: s[name + BARE] for name in denoisers}}
        recorded = scene.info.get(f"spp{spp}", {}).get("noisy_psnr")
        if recorded is not None:  # one-piece render: another noise realisation than our two halves
            entry["noisy_psnr_recorded"] = recorded
        row[str(spp)] = entry
        if keep is not None and spp == keep_spp:
            keep.update(noisy=ev.render.rgb, ours=ev.outputs[first].image, ours_bare=ev.outputs[first + BARE].image,
                        oidn=ev.outputs[OIDN].image, oidn_aux=ev.outputs[OIDN_AUX].image, reference=ref)
    return row


def _mean(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else float("nan")


def _summary(rows: dict[str, Any], names: list[str], key: str) -> dict[str, Any]:
    """Means over ``names`` at spp ``key``: ``WHO_METRIC``, seconds (render, AOV pass, denoise),
    and per model (s/MP too)."""
    entries = [rows[n][key] for n in names]
    mpix = [rows[n]["resolution"][0] * rows[n]["resolution"][1] / 1e6 for n in names]
    out: dict[str, Any] = {f"{who}_{m}": _mean([e[who][m] for e in entries]) for who in WHO for m in METRICS}
    out.update({f"{k}_s": _mean([e[f"{k}_s"] for e in entries])
                for k in ("render", "aov_render", "ours", OIDN, OIDN_AUX)})
    out.update({f"{who}_s_per_mp": _mean([e[f"{who}_s"] / mp for e, mp in zip(entries, mpix)])
                for who in (OIDN, OIDN_AUX)})
    out["models"] = {model: {**{m: _mean([e["models"][model][m] for e in entries]) for m in METRICS},
                             "s_per_mp": _mean([e["models"][model]["s"] / mp for e, mp in zip(entries, mpix)]),
                             "bare": {m: _mean([e["bare"][model][m] for e in entries]) for m in METRICS}}
                     for model in entries[0]["models"]} if entries else {}
    return out


def summarize(rows: dict[str, Any], spps: list[int], ceiling_db: float) -> dict[str, Any]:
    """Means over the scenes whose reference ceiling is >= ``ceiling_db`` (``scored``) and over all."""
    out: dict[str, Any] = {}
    for subset, names in (("scored", [n for n, r in rows.items() if r["ceiling_db"] >= ceiling_db]),
                          ("all", list(rows))):
        out[subset] = {"scenes": len(names), **{str(spp): _summary(rows, names, str(spp)) for spp in spps}}
    return out


def markdown(rows: dict[str, Any], summary: dict[str, Any], spps: list[int], ceiling_db: float,
             model: str) -> str:
    """The scoreboard as a markdown table (one row per scene and spp, then the means)."""
    cols = [f"{LABELS[who]} {metric}" for metric in ("PSNR", "relMSE", "FLIP") for who in WHO]
    seconds = [f"{LABELS[who]} s" for who in ("ours", OIDN, OIDN_AUX)] + ["AOV pass s"]
    lines = [f"Model `{model}`; PSNR dB (tonemapped) / relMSE / FLIP against the 2048-spp references; "
             f"ours = the default path (halves, noise input, guard, energy correction), bare = the network before the guard; "
             f"{OIDN_LABELS[OIDN_AUX]}: with the albedo and normals of an AOV pass (its render seconds: AOV pass s); "
             f"* = reference ceiling below {ceiling_db:g} dB (not in the scored mean).", "",
             "| scene | spp | " + " | ".join(cols + seconds) + " |",
             "|---|---:|" + "---:|" * (len(cols) + len(seconds))]

    times = ("ours_s", "oidn_s", "oidn_aux_s", "aov_render_s")

    def cells(get: Any) -> str:
        return " | ".join(f"{get(who, m):.{2 if m == 'psnr' else 4 if m == 'relmse' else 3}f}"
                          for m in METRICS for who in WHO)

    for name, row in rows.items():
        flag = "*" if row["ceiling_db"] < ceiling_db else ""
        for spp in spps:
            e = row[str(spp)]
            lines.append(f"| {name}{flag} | {spp} | {cells(lambda who, m: e[who][m])} | "
                         + " | ".join(f"{e[k]:.2f}" for k in times) + " |")
    for subset in ("scored", "all"):
        for spp in spps:
            m = summary[subset][str(spp)]
            lines.append(f"| **mean, {subset} ({summary[subset]['scenes']})** | {spp} | "
                         f"{cells(lambda who, metric: m[f'{who}_{metric}'])} | "
                         + " | ".join(f"{m[k]:.2f}" for k in times) + " |")
    return "\n".join(lines) + "\n"


def models_markdown(summary: dict[str, Any], spps: list[int]) -> str:
    """Each model's scored means (default path and bare) next to the noisy input's and OIDN's,
    with seconds per megapixel."""
    s = summary["scored"]
    lines = [f"Scored mean over {s['scenes']} scenes; PSNR dB / relMSE / FLIP; s/MP = denoise seconds "
             f"per megapixel (this run; {OIDN_LABELS[OIDN_AUX]}'s AOV pass adds to the render).", "",
             "| denoiser | spp | PSNR | relMSE | FLIP | s/MP |", "|---|---:|---:|---:|---:|---:|"]
    for spp in spps:
        m = s[str(spp)]
        rows = [("noisy", {k: m[f"noisy_{k}"] for k in METRICS}, "-")]
        for name, e in m["models"].items():
            rows += [(name, e, f"{e['s_per_mp']:.2f}"), (f"{name} bare", e["bare"], "")]
        rows += [(OIDN_LABELS[who], {k: m[f"{who}_{k}"] for k in METRICS}, f"{m[f'{who}_s_per_mp']:.2f}")
                 for who in (OIDN, OIDN_AUX)]
        lines += [f"| {label} | {spp} | {e['psnr']:.2f} | {e['relmse']:.4f} | {e['flip']:.3f} | {t} |"
                  for label, e, t in rows]
    return "\n".join(lines) + "\n"


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="python -m benchmarks.evaluate", description=__doc__.split("\n")[0])
    models = p.add_mutually_exclusive_group()
    models.add_argument("--model", help="checkpoint or preset (default: the shipped default)")
    models.add_argument("--models", type=name_list, help="comma-separated presets or checkpoints, all on "
                        "the same renders")
    p.add_argument("--spp", type=int_list, default=(4, 16, 128), help="comma-separated spp (4,16,128)")
    p.add_argument("--scenes", type=name_list, help="comma-separated subset of scene folder names")
    p.add_argument("--ceiling-db", type=float, default=CEILING_DB,
                   help=f"flag scenes whose reference ceiling is below this (default {CEILING_DB:g} dB)")
    p.add_argument("--eval-dir", type=Path, default=EVAL_DIR)
    p.add_argument("--out", type=Path, default=RESULTS)
    p.add_argument("--report-spp", type=int, help="spp whose images evaluate.html shows (default: the lowest)")
    p.add_argument("--precisions", type=name_list, default=("auto",),
                   help="float formats of the networks, each model in each (denoise.precision; "
                        "default auto: what a user on this CPU gets); a model in a second format "
                        "is named MODEL@FORMAT")
    p.add_argument("--flips", type=int_list, default=(1,),
                   help="test-time flips (denoise.flips: 1, 2, 4), each model with each; a model with "
                        "N > 1 flips is named MODEL+flipsN")
    p.add_argument("--energy", type=name_list, default=("on",),
                   help="the energy correction (denoise.energy): on, off or on,off, each model with each; "
                        "a model without it is named MODEL+no-energy")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no table")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(argv)
    spps = list(args.spp)
    report_spp = args.report_spp or min(spps)
    if report_spp not in spps:
        parser.error(f"--report-spp {report_spp} is not one of --spp {','.join(map(str, spps))}")
    try:
        scenes = eval_scenes(args.scenes, args.eval_dir)
        unknown = [p for p in args.precisions if p not in PRECISIONS]
        if unknown:
            parser.error(f"--precisions: {', '.join(unknown)} is not one of {', '.join(PRECISIONS)}")
        bad_flips = [str(n) for n in args.flips if n not in FLIPS]
        if bad_flips:
            parser.error(f"--flips: {', '.join(bad_flips)} is not one of {', '.join(map(str, FLIPS))}")
        bad_energy = [e for e in args.energy if e not in ENERGY_CHOICES]
        if bad_energy:
            parser.error(f"--energy: {', '.join(bad_energy)} is not one of {', '.join(ENERGY_CHOICES)}")
        denoisers = {(spec or "default") + ("" if i == 0 else f"@{prec}") + ("" if n == 1 else f"+flips{n}")
                     + ("" if e == "on" else "+no-energy"):
                     Denoiser(spec, precision=prec, flips=n, energy=settings_if(e == "on"))
                     for spec in (args.models or [args.model]) for i, prec in enumerate(args.precisions)
                     for n in args.flips for e in args.energy}
        for d in denoisers.values():  # first calls pay one-off set-up: keep it out of the timings
            warm_up(d)
        record = run_record("benchmarks.evaluate", argv)
        start = time.perf_counter()
        rows: dict[str, Any] = {}
        images: dict[str, dict[str, np.ndarray]] = {}
        for scene in tqdm(scenes, desc="eval scenes", unit="scene", disable=args.quiet):
            images[scene.name] = {}
            rows[scene.name] = evaluate_scene(scene, spps, denoisers, images[scene.name], report_spp)
    except COMMAND_ERRORS as exc:
        return parser.fail(exc)
    write_results(args.out, rows, images, denoisers, spps, args.ceiling_db, report_spp,
                  finish_record(record, start), args.quiet)
    return 0


def warm_up(denoiser: Denoiser) -> None:
    """One small call, so that the first scene's timing does not pay the one-off set-up; a model
    with albedo and normal inputs is given flat buffers (and, for one that takes normals in the
    camera's frame, the identity as the camera's rotation)."""
    side = 64
    aux = (np.full((side, side, 3), 0.5, np.float32), np.tile(np.float32([0, 0, 1]), (side, side, 1))) \
        if denoiser.needs_aovs else (None, None)
    camera = np.eye(3, dtype=np.float32) if denoiser.needs_aovs else None
    denoiser.denoise_array(np.full((side, side, 3), 0.5, np.float32), *aux, to_camera=camera)


def write_results(out: Path, rows: dict[str, Any], images: dict[str, dict[str, np.ndarray]],
                  denoisers: dict[str, Denoiser], spps: list[int], ceiling_db: float, report_spp: int,
                  record: dict[str, Any], quiet: bool = False) -> dict[str, Any]:
    """evaluate.json, evaluate.md and evaluate.html of a run; returns evaluate.json's dict."""
    summary = summarize(rows, spps, ceiling_db)
    first = next(iter(denoisers.values()))
    models = {name: {"path": str(d.path), "sha256": d.sha256, "config": d.config.to_dict(),
                     "step": d.meta.get("step"), "precision": d.precision, "flips": d.flips,
                     "energy": d.energy is not None,
                     **d.ensemble_record()}
              for name, d in denoisers.items()}
    result = {**record, "path": PATH, "model": next(iter(models.values())), "models": models, "spp": spps,
              "seed": SEED, "ceiling_db": ceiling_db, "summary": summary, "scenes": rows}
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "evaluate.json", result)
    table = markdown(rows, summary, spps, ceiling_db, first.name)
    if len(denoisers) > 1:
        table += "\n" + models_markdown(summary, spps)
    write_text_atomic(out / "evaluate.md", table)
    scoreboard_page(result, images, report_spp).write(out / "evaluate.html")
    if not quiet:
        print(table)
        print(f"wrote {out / 'evaluate.json'}, {out / 'evaluate.md'} and {out / 'evaluate.html'}")
    return result


def scoreboard_page(result: dict[str, Any], images: dict[str, dict[str, np.ndarray]],
                    report_spp: int) -> Page:
    """The scoreboard in the report viewer: one set per scene (noisy / ours / bare / OIDN
    colour-only / OIDN + albedo + normal / reference at ``report_spp``, FLIP maps against the
    reference; n / p flip scenes), the scored means, every scene's row and, with several models,
    their comparison. ``result``: evaluate.json's dict; ``images``: scene -> {noisy, ours,
    ours_bare, oidn, oidn_aux, reference} HxWx3 linear radiance."""
    spps, ceiling = result["spp"], result["ceiling_db"]
    model = Path(result["model"]["path"]).name
    page = Page(f"Scoreboard: {len(result['scenes'])} evaluation scenes",
                f"model {model}; images at {report_spp} spp (seed {result['seed']}) against the "
                f"2048-spp references; {result['path']}; {result['machine']['cores']} cores, "
                f"{result['wall_s']:.0f} s")
    for name, imgs in images.items():
        if not imgs:
            continue
        ref = page.radiance(imgs["reference"])
        rows = [ViewerRow(LABELS[key], page.radiance(imgs[key]), page.scalar(flip_map(imgs[key], imgs["reference"])))
                for key in WHO]
        e = result["scenes"][name][str(report_spp)]
        psnrs = " / ".join(f"{LABELS[who]} {e[who]['psnr']:.2f}" for who in WHO)
        note = f"{report_spp} spp, PSNR {psnrs} dB"
        page.add_set(ViewerSet(name, [*rows, ViewerRow("reference", ref)], ref, note))
    cols = ["PSNR dB", "relMSE", "FLIP"]
    better = {"PSNR dB": "high", "relMSE": "low", "FLIP": "low"}
    means = Table(["denoiser", "spp", *cols, "s"], better=better)
    for spp in spps:
        m = result["summary"]["scored"][str(spp)]
        for who in WHO:
            label = f"{LABELS[who]} ({model})" if who in ("ours", "ours_bare") else LABELS[who]
            means.rows.append([label, spp, m[f"{who}_psnr"], m[f"{who}_relmse"], m[f"{who}_flip"],
                               m.get(f"{who}_s")])
    page.add_section(f"Scored means ({result['summary']['scored']['scenes']} scenes, reference ceiling "
                     f">= {ceiling:g} dB)", means.html())
    compared = ("ours", OIDN, OIDN_AUX)
    per_scene = Table(["scene", "spp", *(f"{LABELS[w]} PSNR" for w in WHO),
                       *(f"{LABELS[w]} {metric}" for metric in ("relMSE", "FLIP") for w in compared),
                       *(f"{LABELS[w]} s" for w in compared), "AOV pass s"])
    for name, row in result["scenes"].items():
        for spp in spps:
            e = row[str(spp)]
            per_scene.rows.append([name + ("*" if row["ceiling_db"] < ceiling else ""), spp,
                                   *(e[w]["psnr"] for w in WHO), *(e[w][m] for m in ("relmse", "flip") for w in compared),
                                   *(e[f"{w}_s"] for w in compared), e["aov_render_s"]])
    page.add_section("Every scene", f"<p class='note'>* reference ceiling below {ceiling:g} dB (not in "
                     "the scored mean)</p>" + per_scene.html())
    if len(result["models"]) > 1:
        table = Table(["model", "spp", *cols, "s/MP"], better=better)
        for spp in spps:
            for label, e in result["summary"]["scored"][str(spp)]["models"].items():
                table.rows.append([label, spp, e["psnr"], e["relmse"], e["flip"], e["s_per_mp"]])
                table.rows.append([f"{label} bare", spp, *(e["bare"][m] for m in METRICS), None])
        page.add_section("Models", table.html())
    return page


if __name__ == "__main__":
    sys.exit(main())
