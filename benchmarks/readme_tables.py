"""The measured tables of README.md and docs/*.md, rendered from the result files.

A table stands in a page between ``<!-- table:NAME -->`` and ``<!-- /table -->``; its first line
names the command, the result file, the date and the machine's load as the file records them
("not recorded" where it does not). ``python -m benchmarks.readme_tables`` rewrites every table from
``benchmarks/results/*.json`` (and, for training, the shipped ``model/weights/*_log.jsonl``);
``--check`` only lists the tables that differ from what the files give (``tests/test_readme_tables.py``
runs it, so a hand-edited or stale figure fails the tests).

To add a table: write ``def NAME(results: Results) -> list[str]`` below (caption first, via
:func:`caption`), add it to ``TABLES`` and put the two markers where it should stand.
"""
from __future__ import annotations

import json
import math
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from imaging.atomic_io import write_text_atomic
from console.usage import OneLineParser

ROOT = Path(__file__).resolve().parents[1]
MARKERS = re.compile(r"(<!-- table:([a-z0-9_]+) -->\n)(.*?)(<!-- /table -->)", re.S)


class Results:
    """The result files of one checkout: ``benchmarks/results/NAME.json`` and the training records
    of the checkpoints, ``experiments/training/NAME/{log.jsonl,train_config.json}``."""

    def __init__(self, root: Path = ROOT) -> None:
        self.root = root

    def json(self, name: str) -> dict[str, Any]:
        return json.loads((self.root / "benchmarks" / "results" / f"{name}.json").read_text())

    def log(self, name: str) -> list[dict[str, Any]]:
        path = self.root / "experiments" / "training" / name / "log.jsonl"
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]

    def train_config(self, name: str) -> dict[str, Any]:
        return json.loads((self.root / "experiments" / "training" / name / "train_config.json").read_text())


def _load(data: dict[str, Any]) -> str:
    """The 1-minute load average at the start and end of a run, as the file records it."""
    machine = data.get("machine") if isinstance(data.get("machine"), dict) else {}
    cores = machine.get("cores") or machine.get("cpus") or data.get("cpus")
    pairs = [(machine.get("load_before"), machine.get("load_after")),
             (machine.get("loadavg_before"), machine.get("loadavg_after")),
             (data.get("load_average_before"), data.get("load_average_after")),
             (data.get("load_avg_before"), data.get("load_avg_after"))]
    before, after = next(((b, a) for b, a in pairs if b is not None), (None, None))
    if before is None and isinstance(data.get("machine"), str):  # "x86_64, 2 cores (load 1.3 at start)"
        found = re.search(r"load ([\d.]+)", data["machine"])
        before = float(found.group(1)) if found else None
    if before is None:
        return "load not recorded"
    first = lambda v: v[0] if isinstance(v, list) else v  # noqa: E731  (1-minute average)
    text = f"load {first(before):.1f} at the start" + (f", {first(after):.1f} at the end" if after is not None else "")
    return text + (f" on {cores} cores" if cores else "")


def caption(command: str, source: str, data: dict[str, Any] | None = None, note: str = "") -> str:
    """The line above a table: ``command`` (the file's own record of it when it has one), ``source``
    (the result file), the date and the load recorded; ``note``: what else a reader must know."""
    data = data or {}
    cmd = f"`{data['command']}`" if data.get("command") else f"`{command}` (command not recorded in the file)"
    line = f"Source: {cmd} → `{source}`; {data.get('date') or 'date not recorded'}; {_load(data)}."
    return f"{line} {note}" if note else line


def _f(value: Any, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:,.{digits}f}" if isinstance(value, float) else f"{value:,}"


def _table(header: list[str], rows: list[list[str]], right: int = 1) -> list[str]:
    """Markdown table; columns from index ``right`` on are right-aligned."""
    align = ["---" if i < right else "---:" for i in range(len(header))]
    return ["| " + " | ".join(header) + " |", "|" + "|".join(align) + "|",
            *("| " + " | ".join(r) + " |" for r in rows)]


# --- quality ---------------------------------------------------------------------------------------

def _scoreboard_path(data: dict[str, Any]) -> str:
    return (f"Path: {data['path']}." if "path" in data else
            "Measured before the scoreboard used the default path: every model's bare network on one-piece "
            "renders (no noise guard); `python -m benchmarks.evaluate` now scores the default path.")


def _aux_time(scored: dict[str, Any], spps: Any) -> str:
    """OIDN + albedo + normal's denoise seconds per megapixel over colour-only's in the scoreboard
    run, at the spp where the ratio is largest."""
    ratios = {s: scored[str(s)]["oidn_aux_s_per_mp"] / scored[str(s)]["oidn_s_per_mp"] for s in spps}
    dearest = max(ratios, key=lambda s: ratios[s])
    return f"{_f(ratios[dearest])}x at {dearest} spp"


def models(results: Results) -> list[str]:
    """The README's one table: each registry entry and OIDN (colour-only, and with albedo and
    normals), PSNR at the cards' spp, FLIP at 16 spp and time over OIDN colour-only's (1280x720,
    each at its dearest spp, named; OIDN + albedo + normal's from the scoreboard run)."""
    from model.registry import CARD_SPP, registry

    evaluate, inference, aov = results.json("evaluate"), results.json("inference"), results.json("aov_cost")
    scored = evaluate["summary"]["scored"]
    ratios = inference.get("ratios", {}).get("1280x720", {})
    rows = []
    for name in registry().entries:
        if any(name not in scored[str(s)]["models"] for s in CARD_SPP):
            continue
        known = {int(s): r for s, r in ratios.get(name, {}).items() if s != "unknown"}
        dearest = max(known, key=lambda s: known[s]) if known else None
        rows.append([f"`{name}`", *(_f(scored[str(s)]["models"][name]["psnr"]) for s in CARD_SPP),
                     _f(scored["16"]["models"][name]["flip"], 3),
                     f"{_f(known[dearest])}x at {dearest} spp" if dearest else "-"])
    rows.append(["OIDN colour-only", *(_f(scored[str(s)]["oidn_psnr"]) for s in CARD_SPP),
                 _f(scored["16"]["oidn_flip"], 3), "1.00x"])
    rows.append(["OIDN + albedo + normal", *(_f(scored[str(s)]["oidn_aux_psnr"]) for s in CARD_SPP),
                 _f(scored["16"]["oidn_aux_flip"], 3), _aux_time(scored, CARD_SPP)])
    pass_16 = aov["summary"]["16"]["pass_ratio"]
    header = ["model", *(f"PSNR {s} spp" for s in CARD_SPP), "FLIP 16 spp", "time / OIDN's"]
    return [*_table(header, rows), "",
            f"PSNR (dB, tonemapped) and FLIP: means over the {scored['scenes']} eval scenes with clean references "
            f"({len(evaluate['scenes'])} public Mitsuba scenes none of the models saw), `python -m benchmarks.evaluate`,",
            f"{evaluate.get('date', 'date not recorded')}. Time: one call on a 1280x720 render over OIDN's in the "
            f"same run, at the spp where the model costs most,",
            f"`python -m benchmarks.inference`, {inference.get('date', 'date not recorded')}, {_load(inference)}.",
            "OIDN + albedo + normal: its seconds over colour-only's in the scoreboard run (256 px); the albedo and normals "
            "it takes, rendered in a pass of their own,",
            f"add {_percent(pass_16['geomean'])} to the render time at 16 spp (geometric mean over {len(aov['scenes'])} "
            f"eval scenes, {_percent(pass_16['min'])} to {_percent(pass_16['max'])}; `python -m benchmarks.aov_cost`, "
            f"{aov.get('date', 'date not recorded')}). Every model and scene: [evaluate](docs/evaluate.md)."]


def _percent(ratio: float) -> str:
    """A time ratio as the share it adds: 1.07 -> '7%'."""
    return f"{100 * (ratio - 1):.0f}%"


def strip_caption(results: Results) -> list[str]:
    """The line under the README's picture: what it shows and the PSNR of each panel's whole image."""
    data = results.json("figures")["strip"]
    values = ", ".join(f"{label} {_f(value)} dB" for label, value in data["psnr_db"].items() if value is not None)
    return [f"Crops of `{data['scene']}` (an eval scene) at {data['spp']} spp; PSNR of the whole image: {values}.",
            "Made by `python -m benchmarks.figures` → benchmarks/results/figures.json."]


def unknown_spp(results: Results) -> list[str]:
    """Each model on images whose spp it is not told (no variance, no guard), per spp, beside the noisy input."""
    data = results.json("unknown_spp")
    means = data["means_psnr"]
    rows = [[spp, _f(m["noisy"]), *(_f(m[n]) for n in data["models"])] for spp, m in means.items()]
    note = (f"Mean PSNR dB over {data['source']} ({next(iter(means.values()))['images']} scored images per spp), "
            "each image denoised alone: no spp, no variance, so no noise guard, as `denoise` runs a file that "
            "does not say its spp.")
    return [caption("python -m benchmarks.unknown_spp", "benchmarks/results/unknown_spp.json", data, note), "",
            *_table(["spp", "noisy", *data["models"]], rows)]


def image_noise(results: Results) -> list[str]:
    """Per pixel filter and spp, the share of renders :mod:`denoise.image_noise` calls filtered."""
    data = results.json("image_noise")
    spps = list(next(iter(data["summary"].values())))
    rows = [[name, *(f"{100 * s[spp]['called_filtered']:.0f}% ({_f(s[spp]['ratio_min'])}-{_f(s[spp]['ratio_max'])})"
                     for spp in spps)] for name, s in data["summary"].items()]
    images = next(iter(next(iter(data["summary"].values())).values()))["images"]
    note = (f"{images} scenes each; called filtered: Nyquist ratio under {data['threshold']:g}; in brackets the "
            "ratios seen (independent pixels give about 1).")
    return [caption("python -m benchmarks.image_noise", "benchmarks/results/image_noise.json", data, note), "",
            *_table(["pixel filter", *(f"{spp} spp" for spp in spps)], rows)]


def denoise_process(results: Results) -> list[str]:
    """``denoise`` as a process on EXRs without an spp, marginal s/MP against OIDN's."""
    data = results.json("denoise_process")
    rows = []
    for kind, entry in data["results"].items():
        for name, c in entry["commands"].items():
            ratio = f"{_f(c['ratio_to_oidn'])}x" if "ratio_to_oidn" in c else "1.00x"
            rows.append([f"{kind} ({entry['spp']} spp)", f"`{name}`" if name != "oidn" else "OIDN colour-only",
                         _f(c["marginal_s_per_mp"]), ratio])
    note = (f"Marginal seconds per megapixel between {' and '.join(data['sizes'])} (start-up cancels), medians "
            "of fresh processes; the demo scene written as an EXR with no spp attribute.")
    return [caption("python -m benchmarks.denoise_process", "benchmarks/results/denoise_process.json", data, note), "",
            *_table(["input", "command", "marginal s/MP", "over OIDN"], rows)]


def scoreboard(results: Results) -> list[str]:
    """Scored means of every model (and its bare network), the noisy input and OIDN per spp."""
    data = results.json("evaluate")
    s = data["summary"]["scored"]
    rows = []
    for spp in data["spp"]:
        m = s[str(spp)]
        rows.append(["noisy", str(spp), _f(m["noisy_psnr"]), _f(m["noisy_relmse"], 4), _f(m["noisy_flip"], 3), "-"])
        for name, e in m["models"].items():
            rows.append([Path(name).stem, str(spp), _f(e["psnr"]), _f(e["relmse"], 4), _f(e["flip"], 3),
                         _f(e["s_per_mp"])])
            if "bare" in e:
                rows.append([f"{Path(name).stem} bare", str(spp), _f(e["bare"]["psnr"]),
                             _f(e["bare"]["relmse"], 4), _f(e["bare"]["flip"], 3), ""])
        rows.append(["OIDN 2.5 colour-only", str(spp), _f(m["oidn_psnr"]), _f(m["oidn_relmse"], 4),
                     _f(m["oidn_flip"], 3), _f(m["oidn_s_per_mp"])])
        rows.append(["OIDN 2.5 + albedo + normal", str(spp), _f(m["oidn_aux_psnr"]), _f(m["oidn_aux_relmse"], 4),
                     _f(m["oidn_aux_flip"], 3), _f(m["oidn_aux_s_per_mp"])])
    note = (f"Mean over the {s['scenes']} eval scenes whose reference ceiling is >= {data['ceiling_db']:g} dB, "
            f"seed {data['seed']}; PSNR dB (tonemapped), relMSE, FLIP against the 2048-spp references; "
            f"s/MP: denoise seconds per megapixel in this run. {_scoreboard_path(data)}")
    return [caption("python -m benchmarks.evaluate", "benchmarks/results/evaluate.json", data, note), "",
            *_table(["denoiser", "spp", "PSNR", "relMSE", "FLIP", "s/MP"], rows)]


def scoreboard_scenes(results: Results) -> list[str]:
    """Every scene and spp: PSNR of noisy / ours (/ bare) / OIDN, relMSE and FLIP of ours and OIDN."""
    data = results.json("evaluate")
    bare = any("ours_bare" in e for row in data["scenes"].values() for k, e in row.items() if k.isdigit())
    who = ["noisy", "ours", *(["ours_bare"] if bare else []), "oidn", "oidn_aux"]
    labels = {"noisy": "noisy", "ours": "ours", "ours_bare": "bare", "oidn": "OIDN colour-only",
              "oidn_aux": "OIDN + albedo + normal"}
    compared = ("ours", "oidn", "oidn_aux")
    header = ["scene", "spp", *(f"{labels[w]} PSNR" for w in who),
              *(f"{labels[w]} {m}" for m in ("relMSE", "FLIP") for w in compared)]
    rows = []
    for name, row in data["scenes"].items():
        flag = "*" if row["ceiling_db"] < data["ceiling_db"] else ""
        for spp in data["spp"]:
            e = row[str(spp)]
            rows.append([name + flag, str(spp), *(_f(e[w]["psnr"]) for w in who),
                         *(_f(e[w]["relmse"], 4) for w in compared), *(_f(e[w]["flip"], 3) for w in compared)])
    note = (f"Model `{Path(data['model']['path']).name}` (ours); * = reference ceiling below "
            f"{data['ceiling_db']:g} dB, not in the scored mean. {_scoreboard_path(data)}")
    return [caption("python -m benchmarks.evaluate", "benchmarks/results/evaluate.json", data, note), "",
            *_table(header, rows)]


def aov_cost(results: Results) -> list[str]:
    """What rendering the albedo and normals adds to the render time, per scene and spp: the AOV
    pass the commands run, and the one render of radiance and AOVs together."""
    data = results.json("aov_cost")
    rows = []
    for name, row in data["scenes"].items():
        for spp in data["spp"]:
            e = row[str(spp)]
            s = e["seconds"]
            same = "yes" if e["rgb_identical"] else f"no (up to {e['rgb_max_diff']:.1e})"
            rows.append([name, str(spp), _f(s["plain"], 3), _f(s["pass"], 3), _f(s["wrapped"], 3),
                         f"{_f(e['pass_ratio'])}x", f"{_f(e['wrapped_ratio'])}x", same])
    for spp in data["spp"]:
        m = data["summary"][str(spp)]
        rows.append(["geometric mean", str(spp), "", "", "", f"{_f(m['pass_ratio']['geomean'])}x",
                     f"{_f(m['wrapped_ratio']['geomean'])}x", ""])
    w, h = data["resolution"]
    note = (f"{w}x{h}, seed {data['seed']}, two halves as render-and-denoise renders; medians of {data['repeat']} "
            "rounds after each kernel is compiled. plain: the render the models get; pass: the AOV pass the "
            "commands add for OIDN + albedo + normal (Mitsuba's aov integrator alone, the same camera rays); "
            "wrapped: one render of radiance and AOVs (the scene's integrator inside the aov integrator).")
    return [caption("python -m benchmarks.aov_cost", "benchmarks/results/aov_cost.json", data, note), "",
            *_table(["scene", "spp", "plain s", "pass s", "wrapped s", "(plain + pass) / plain",
                     "wrapped / plain", "wrapped radiance = plain"], rows)]


def noise_guard_settings(results: Results) -> list[str]:
    """Mean PSNR of every guard setting tried, per regime and spp."""
    data = results.json("noise_guard")
    keys = [k for k in data["summary"]["noisy"][next(k for k in data["summary"]["noisy"] if k != "scenes")]
            if k.startswith("guard")]
    columns = [(regime, spp) for regime in ("noisy", "converged")
               for spp in sorted((k for k in data["summary"][regime] if k != "scenes"), key=int)]
    rows = [[k + (" (default)" if k == data["default"] else ""),
             *(_f(data["summary"][r][spp][k]["mean_psnr"]) for r, spp in columns)] for k in ["model", *keys]]
    note = ("Mean PSNR dB of the network alone (`model`) and with the guard at window radius r and pivot p "
            "(strength max(1, p/spp); p0: the plain Wiener weight), on the same renders and network output.")
    return [caption("python -m benchmarks.noise_guard", "benchmarks/results/noise_guard.json", data, note), "",
            *_table(["setting", *(f"{'eval' if r == 'noisy' else 'converged'} {spp} spp" for r, spp in columns)],
                    rows)]


def noise_guard(results: Results) -> list[str]:
    """Mean PSNR per regime and spp: noisy, the bare network, the network + default guard, OIDN."""
    data = results.json("noise_guard")
    default = data["default"]
    rows = []
    for regime, title in (("noisy", f"eval scenes ({data['summary']['noisy']['scenes']} scored, 2048-spp refs)"),
                          ("converged", f"converged ({data['summary']['converged']['scenes']} cases, "
                                        f"{data['reference_spp_converged']}-spp refs)")):
        summary = data["summary"][regime]
        for i, spp in enumerate(sorted((k for k in summary if k != "scenes"), key=int)):
            e = summary[str(spp)]
            cells = [f"{_f(e[k]['mean_psnr'])} ({e[k]['worst_vs_noisy_db']:+.2f})" if k != "noisy"
                     else _f(e[k]["mean_psnr"]) for k in ("noisy", "model", default, "oidn")]
            rows.append([title if i == 0 else "", str(spp), *cells])
    note = (f"Model `{data['model']}`, every render in two halves; mean PSNR dB, in brackets the worst change "
            f"against the noisy render; the guard's default setting: {default}.")
    return [caption("python -m benchmarks.noise_guard", "benchmarks/results/noise_guard.json", data, note), "",
            *_table(["regime", "spp", "noisy", "network alone", "network + guard", "OIDN"], rows, right=1)]


def energy(results: Results) -> list[str]:
    """Mean PSNR without the energy correction, with each setting tried (the default first) and
    OIDN, per set and spp; the default's images made worse and worst change; radiance kept."""
    from benchmarks.energy import label  # the benchmark's own column names
    from denoise.energy import EnergySettings

    data = results.json("energy")
    labels = [label(EnergySettings(**s)) for s in data["settings"]]
    rows = []
    for key in ("validation", "eval", "one-piece"):
        for spp, row in data.get(key, {}).get("per_spp", {}).items():
            rows.append([key, spp, str(row["images"]), _f(row["none"]),
                         f"{_f(row[labels[0]])} ({row['worse ' + labels[0]]} / {row['worst ' + labels[0]]:+.2f})",
                         *(_f(row[k]) for k in labels[1:]), _f(row.get("halves")), _f(row["oidn"]),
                         " / ".join(_f(row["kept " + k], 3) for k in ("none", "default", "oidn"))])
    note = (f"Model `{data['model']}` through the noise guard as the default path; `none`: no correction; "
            f"T: clamp, r: window radius in 8-px blocks, k: significance; the default {labels[0]} "
            "(in brackets: images worse than `none` by > 0.05 dB / the worst change); halves: the default with "
            "the variance of the render's two halves in place of each block's sample variance (renders of 2+ "
            "spp). OIDN colour-only on the "
            "same images. kept: mean radiance / the reference's without the correction, with the default, "
            "OIDN. validation: held-out procedural scenes (the tuning set); eval: ../shared/eval-scenes, "
            f"ceiling >= 40 dB, seed {data['seed']}; one-piece: the same scenes rendered in one piece (no halves, "
            "no guard).")
    return [caption("python -m benchmarks.energy", "benchmarks/results/energy.json", data, note), "",
            *_table(["set", "spp", "images", "none", *labels, "halves", "OIDN", "kept"], rows, right=1)]


# --- speed -----------------------------------------------------------------------------------------

def ensemble(results: Results) -> list[str]:
    """Each member, their mean and every combination setting against OIDN, per set and spp."""
    data = results.json("ensemble")
    lines = [caption("python -m benchmarks.ensemble", "benchmarks/results/ensemble.json", data,
                     f"Members {' + '.join(data['members'])}: each alone, their plain mean, and combined with "
                     "each setting (r: window radius, lam: the regulariser, p: the power of denoise/ensemble.py); every "
                     "candidate through the noise guard as the default path; OIDN colour-only on the same "
                     "images. Mean PSNR dB; validation: held-out procedural scenes (the tuning set); eval: "
                     "../shared/eval-scenes, ceiling >= 40 dB, seed 7."), ""]
    rows = []
    for key in ("validation", "eval"):
        if key not in data:
            continue
        summary = data[key]
        columns = list(summary["mean"])
        for spp, row in summary["per_spp"].items():
            rows.append([key, spp, str(row["images"]), *(_f(row[c]) for c in columns)])
        rows.append([key, "**mean**", "", *(_f(summary["mean"][c]) for c in columns)])
    return lines + _table(["set", "spp", "images", *columns], rows, right=1)


def ratio_range(row: dict[str, Any], name: str) -> tuple[float, float] | None:
    """The lowest and highest of ``name``'s per-process time ratios to OIDN in one size's row of
    benchmarks/results/inference.json (None where fewer than two processes were recorded)."""
    mine, oidn = row[name].get("process_s_per_mp"), row.get("oidn", {}).get("process_s_per_mp")
    if not mine or not oidn or len(mine) < 2:
        return None
    ratios = [a / b for a, b in zip(mine, oidn)]
    return min(ratios), max(ratios)


def ratio_range_text(row: dict[str, Any], name: str) -> str:
    """`` (lo-hi)`` of :func:`ratio_range`, or nothing where it is None."""
    spread = ratio_range(row, name)
    return f" ({spread[0]:.2f}-{spread[1]:.2f})" if spread else ""


def inference(results: Results) -> list[str]:
    """Seconds per megapixel of the whole chain for every measured model and OIDN, per image size,
    and each model's time as a multiple of OIDN's in the same run."""
    data = results.json("inference")
    names = [k for k, v in next(iter(data["sizes"].values())).items() if isinstance(v, dict) and "s_per_mp" in v]
    models = [n for n in names if n != "oidn"]
    rows = []
    for size, row in data["sizes"].items():
        oidn = row.get("oidn", {}).get("s_per_mp")
        ratios = [_f(row[n]["s_per_mp"] / oidn) + "x" + ratio_range_text(row, n) if oidn and n in row else "-"
                  for n in models]
        rows.append([size, *(_f(row.get(n, {}).get("s_per_mp")) for n in names), *ratios])
    macs = data.get("macs_per_pixel", {})
    processes = data.get("processes", 1)
    note = ("Seconds per megapixel of one call, median of the runs"
            + (f" of {processes} fresh processes (in brackets: the lowest and highest of the per-process "
               "ratios)" if processes > 1 else "")
            + "; OIDN 2.5 colour-only on the same image in "
            "the same run; the last columns: each model's time over OIDN's. `model@bfloat16`: the network in "
            "bfloat16 (denoise/precision.py; this CPU computes it natively: "
            f"{'yes' if data['machine'].get('native_bfloat16') else 'no'})."
            + (" MACs per pixel: " + ", ".join(f"{n} {macs[n] / 1e3:.1f}k" for n in models if n in macs) + "."
               if macs else ""))
    return [caption("python -m benchmarks.inference", "benchmarks/results/inference.json", data, note), "",
            *_table(["size", *names, *(f"{n}/OIDN" for n in models)], rows)]


def multiscale_presets(results: Results) -> list[str]:
    """The multi-scale presets' sizes, counted from the code (no measurement)."""
    from model.architectures import build_model, count_parameters, receptive_radius
    from model.config import PRESETS
    from model.unet import macs_per_pixel

    rows = []
    for name, c in PRESETS.items():
        if c.multiscale:
            rows.append([f"`{name}`", str(c.levels + 1), str(c.layers), str(c.growth), str(c.init_features),
                         f"{macs_per_pixel(c) / 1e3:.1f}k", f"{count_parameters(build_model(c)):,}",
                         f"{receptive_radius(c)} px"])
    return ["Counted from `model/config.py` by `model.unet.macs_per_pixel` (checked by a test against the "
            "convolutions run) and `model.architectures.receptive_radius` (with the noise input's window).", "",
            *_table(["preset", "resolutions", "layers a block", "k", "w0", "MACs/pixel (folded)", "parameters",
                     "receptive radius"], rows)]


def roofline(results: Results) -> list[str]:
    """Each preset's convolutions alone: s/MP at inference, patches/s of a training step."""
    data = results.json("roofline")
    rows = [[f"`{name}`", _f(p["macs_per_pixel"]), _f(p["infer_conv_s_per_mp"]), _f(p["infer_conv_gflops"], 1),
             _f(p["train_patches_per_s_bound"], 0), _f(data["goals"]["naive_patches_per_s"].get(name))]
            for name, p in data["presets"].items()]
    note = (f"Every convolution of a preset timed alone (its shape, channels_last, warm) and summed: a lower "
            f"bound for our code. torch.mm peak on this machine: {data['matmul_peak_gflops']:.0f} GFLOP/s.")
    return [caption("python -m benchmarks.roofline", "benchmarks/results/roofline.json", data, note), "",
            *_table(["preset", "MACs/pixel", "inference convs s/MP", "GFLOP/s", "train-step convs patches/s",
                     "naive train patches/s"], rows)]


def budget(results: Results) -> list[str]:
    """Budget mode on the eval scenes: runs within 20 %, range of actual/budget, mean PSNR."""
    data = results.json("budget")
    rows = [[b, f"{s['within']}/{s['runs']}", f"{s['min_ratio']:.2f}–{s['max_ratio']:.2f}", _f(s["mean_psnr"]),
             ", ".join(f"{m} {n}" for m, n in sorted(s["models"].items()))]
            for b, s in data["summary"]["per_budget"].items()]
    note = (f"render-and-denoise --time-budget B --model auto on every eval scene; within: actual time within "
            f"{100 * data['tolerance']:.0f}% of the budget.")
    return [caption("python -m benchmarks.budget --budgets 10", "benchmarks/results/budget.json", data, note), "",
            *_table(["budget s", "within", "actual / budget", "mean PSNR dB", "models chosen"], rows)]


# --- training --------------------------------------------------------------------------------------

TRAINED = ("flat-s-allspp", "flat-s-lowspp", "unet-m-k5-lowspp", "unet-m-k5-lowspp-b", "unet-l-allspp")
TRAIN_COMMAND = "train --recipe NAME --out runs/NAME (docs/training.md)"


def presets(results: Results) -> list[str]:
    """The shipped checkpoints: network size, best validation and when it was reached."""
    rows = []
    for preset in TRAINED:
        log, cfg = results.log(preset), results.train_config(preset)
        val = [r for r in log if r["type"] == "val"]
        best = max(val, key=lambda r: r["psnr"])
        train_s = next((r["train_s"] for r in log if r["type"] == "train" and r["step"] == best["step"]), None)
        m = cfg["model"]
        rows.append([f"`{preset}`", f"{m.get('arch', 'densenet')}: k {m['growth']}, L {m['layers']}",
                     _f(best["step"]), _f(log[-1]["step"]),
                     _f(train_s / 60 if train_s else None, 1), str(best["images"]), _f(best["psnr"])])
    note = ("Validation: whole images of each run's held-out scenes (`images`: their count; the sets differ "
            "between runs); wall minutes: the last run's optimisation to its best step, by the clock (its CPU "
            "time: the recipes' table in docs/training.md).")
    return [caption(TRAIN_COMMAND, "experiments/training/NAME/log.jsonl, train_config.json", None, note), "",
            *_table(["checkpoint", "network", "best step", "steps run", "wall minutes to best", "images",
                     "val PSNR dB"], rows)]


def recipe_runs(results: Results) -> list[str]:
    """What each shipped recipe's stages took and the two totals, from the stages' logs
    (:mod:`benchmarks.training_records`)."""
    from benchmarks.training_records import recipe_record
    from training.recipe import load_recipe

    stages, totals = [], []
    for name in TRAINED:
        record = recipe_record(load_recipe(name), results.root)
        for i, stage in enumerate(record.recipe.stages):
            run = record.stages[stage.name]
            start = f"stage {stage.init_from}" if stage.init_from else "scratch"
            stages.append([f"`{name}`" if i == 0 else "", stage.name, start,
                           *((_f(run.steps), _f(run.best_step), _f(run.best_psnr), _f(run.cpu_min_to_best, 1),
                              _f(run.cpu_min, 1)) if run else ("-",) * 5)])
        totals.append([f"`{name}`", _f(record.hours_to_file), _f(record.hours_whole_run)])
    note = ("Held-out dB: the best validation PSNR, at the best step. CPU-min to best: the stage's CPU time up "
            "to its best step, the checkpoint the next stage starts from (or the shipped file); in all: to its "
            "last step. A stage another recipe's run trained is read from that run's log. CPU-hours to the "
            "shipped file: the stages that lead to it, each to its best step (its card's figure, "
            "`denoise --list-models`); the whole run: every stage to its last step, what `train --recipe NAME` takes.")
    return [caption(TRAIN_COMMAND, "experiments/training/NAME/log.jsonl, NAME/stage-STAGE/log.jsonl", None, note),
            "", *_table(["recipe", "stage", "starts from", "steps run", "best step", "held-out dB", "CPU-min to best",
                         "CPU-min in all"], stages, right=3),
            "", *_table(["recipe", "CPU-hours to the shipped file", "CPU-hours of the whole run"], totals)]


def validation(results: Results) -> list[str]:
    """The default model's best validation per spp next to the noisy input and OIDN."""
    best = max((r for r in results.log("flat-s-allspp") if r["type"] == "val"), key=lambda r: r["psnr"])
    rows = [[spp, *(_f(e["psnr"][w]) for w in ("ours", "noisy", "oidn")),
             *(_f(e["relmse"][w], 4) for w in ("ours", "noisy", "oidn"))] for spp, e in best["per_spp"].items()]
    note = (f"`flat-s-allspp` (the flat network every entry runs on clean renders) at its best step "
            f"({best['step']}); PSNR dB tonemapped / relMSE; OIDN colour-only.")
    return [caption(TRAIN_COMMAND, "experiments/training/flat-s-allspp/log.jsonl", None, note), "",
            *_table(["spp", "ours PSNR", "noisy PSNR", "OIDN PSNR", "ours relMSE", "noisy relMSE",
                     "OIDN relMSE"], rows, right=0)]


def val_scenes(results: Results) -> list[str]:
    """Checkpoints side by side with OIDN on the same held-out scenes of our datasets."""
    from benchmarks.validation import note, table  # imports torch: only where this table is drawn

    data = results.json("validation")
    return [caption("python -m benchmarks.validation", "benchmarks/results/validation.json", data, note(data)), "",
            *table(data)]


def trend(results: Results) -> list[str]:
    """Validation PSNR per doubling of CPU time late in each run, and the trend's CPU-hours to OIDN."""
    from benchmarks.trend import note, table

    data = results.json("trend")
    return [caption("python -m benchmarks.trend", "benchmarks/results/trend.json", data, note(data)), "",
            *table(data)]


def ablations(results: Results) -> list[str]:
    """Each ablation run's final validation PSNR, overall and per spp."""
    data = results.json("train_ablations")
    spps = list(data["runs"][0]["final_per_spp"])
    rows = [[r["name"], _f(r["final_step"]), _f(r["train_s"], 0), _f(r["final_psnr"]),
             *(_f(r["final_per_spp"][s]["ours"]) for s in spps), _f(r.get("steps_to_target"))] for r in data["runs"]]
    first = data["runs"][0]["final_per_spp"]
    rows.append(["noisy / OIDN", "", "", "", *(f"{_f(first[s]['noisy'])} / {_f(first[s]['oidn'])}" for s in spps),
                 ""])
    note = (f"Same data and seed for every run; val PSNR dB; steps to target: first validation at >= "
            f"{data['target_psnr']:.2f} dB.")
    return [caption("python -m benchmarks.train_ablations --data data/train", "benchmarks/results/train_ablations.json",
                    data, note), "",
            *_table(["run", "steps", "train s", "val PSNR", *(f"{s} spp" for s in spps), "steps to target"], rows)]


def train_throughput(results: Results) -> list[str]:
    """Patches per second of every measured training-step variant of each preset."""
    data = results.json("train_throughput")
    names = list(next(iter(data["presets"].values()))["variants"])
    rows = [[f"`{p}`", *(_f(v["variants"].get(n, {}).get("patches_per_s_median"), 1) for n in names)]
            for p, v in data["presets"].items()]
    s = data["settings"]
    note = f"Patches/s ({s['patch']}x{s['patch']} patches, batch {s['batch']}), median of the rounds."
    return [caption("python -m benchmarks.train_throughput", "benchmarks/results/train_throughput.json", data,
                    note), "",
            *_table(["preset", *names], rows)]


# --- scale-out, robustness, memory -------------------------------------------------------------------

def scaleout(results: Results) -> list[str]:
    """Scenes/h with and without Dask workers, patches/s with 1 and 2 DDP ranks, and the estimate."""
    data = results.json("scaleout")
    rows = [[r["setting"], _f(r["scenes_per_hour"], 0), ""] for r in data["dask"]]
    rows += [[r["setting"], "", _f(r["patches_per_s"], 1)] for r in data["ddp"]]
    rows += [[f"estimate: {r['machines']} machine(s)", _f(r["scenes_per_hour"], 0), _f(r["patches_per_s"], 0)]
             for r in data["estimate"]["rows"]]
    note = (f"Dataset: 128-px scenes with a 4096-spp reference, {data['estimate']['per_scene_s']:.1f} s per scene on "
            f"1 worker; training: `{data['train']['preset']}`, global batch {data['train']['batch']}. The estimate "
            "rows scale these measured costs to N machines like this one (its assumptions are in the file).")
    return [caption("python -m benchmarks.scaleout", "benchmarks/results/scaleout.json", data, note), "",
            *_table(["setting", "scenes/h", "patches/s"], rows)]


def extremes(results: Results) -> list[str]:
    """Energy kept by the shipped model, converged renders through the default path, the 8K run."""
    full = results.json("extremes")["full"]
    rows = [[f"energy: {name}", f"{e['ratio']:.3f}", f"{e['ratio_at_mean_0.0001']:.3f}",
             f"{e['ratio_at_mean_1000']:.3f}"] for name, e in full["energy"]["scenes"].items()]
    rows += [[f"demo at {px} px, 4096 spp: PSNR noisy / network / default path",
              f"{c['psnr_noisy_db']:.2f}", f"{c['psnr_denoised_db']:.2f}", f"{c['psnr_guarded_db']:.2f}"]
             for px, c in full["converged"].items()]
    m = full["memory"]
    note = (f"Model `{full['model']}`. Energy: mean radiance denoised / noisy at the scene's own scale and "
            f"scaled to mean 1e-4 and 1e3. Memory: a {m['width']}x{m['height']} image under --max-memory-mb "
            f"{m['max_memory_mb']:g} peaked at {m['peak_rss_mb']:,.0f} MiB RSS ({m['over_base_mb']:,.0f} MiB over "
            f"the process before the call), {m['tiles']} tiles, {m['seconds']:.0f} s.")
    return [caption("python -m benchmarks.extremes", "benchmarks/results/extremes.json", full, note), "",
            *_table(["case", "as rendered", "mean 1e-4", "mean 1e3"], rows)]


def render_memory(results: Results) -> list[str]:
    """Peak RSS of a render per film size, before the memory budget and under two budgets."""
    data = results.json("render_memory")
    rows = [[f"{s['res'][0]}x{s['res'][1]}", s["setting"], _f(s["peak_mb"], 0), _f(s["scratch_mb"], 0),
             str(s["crops"]), _f(s["seconds"], 1)] for s in data["sizes"]]
    note = (f"{data['scene']} at {data['spp']} spp in two halves; 'before': the render before --max-memory-mb "
            f"({data['before_rev']}).")
    return [caption("python -m benchmarks.render_memory", "benchmarks/results/render_memory.json", data, note), "",
            *_table(["film", "setting", "peak MB", "render scratch MB", "crops", "s"], rows, right=2)]


def denoise_memory(results: Results) -> list[str]:
    """Scratch of the denoise step of both commands per size, budget and code, beside the render's
    own peak and the largest of the other stages."""
    data = results.json("denoise_memory")["commands"]
    rows = []
    for r in data["rows"]:
        stages = {s["stage"]: s for s in r["stages"]}
        d = stages["denoise"]
        rest = [s for s in r["stages"] if s["stage"] not in ("denoise", "render") and not s["stage"].startswith("setup")]
        worst = max(rest, key=lambda s: s["scratch_mb"])
        render = r.get("render_memory") or {}
        rows.append([f"{r['res'][0]}x{r['res'][1]}", f"`{r['command']}`", r["setting"], f"{r['budget_mb']:g}",
                     _f(d["scratch_mb"], 0), f"{d['scratch_mb'] / r['budget_mb']:.2f}", _f(d["images_mb"], 0),
                     _f(render.get("peak_mb"), 0), f"{worst['stage']}: {worst['scratch_mb']:,.0f}",
                     _f(r["peak_mb"], 0), _f(d["seconds"], 0)])
    note = (f"{data['scene']} at {data['spp']} spp in two halves (`render-and-denoise --no-compare`), then `denoise` "
            "of an EXR with that render's colour and variance layers; a fresh process per row, each stage's "
            "peak exact (high-water mark reset before it). Scratch = the stage's peak - RSS at its start - the "
            "images it makes (denoise: the output and the guard's weight map)"
            + (f"; 'before': the code of {data['before_rev']}" if data.get("before_rev") else "")
            + ". Render peak: metrics.json's render_memory (the render step's own peak RSS).")
    return [caption("python -m benchmarks.denoise_memory", "benchmarks/results/denoise_memory.json", data, note), "",
            *_table(["image", "command", "code", "budget MB", "denoise scratch MB", "x budget", "its images MB",
                     "render peak MB", "largest other stage MB", "process peak MB", "denoise s"], rows, right=3)]


def denoise_path_memory(results: Results) -> list[str]:
    """The whole ``denoise`` command per registry entry, spp and budget: scratch as a person counts it."""
    data = results.json("denoise_memory")["path"]
    rows = [[f"{r['res'][0]}x{r['res'][1]}", f"`{r['entry']}`", str(r["spp"]), " + ".join(r["models"]),
             f"{r['budget_mb']:g}", _f(r["scratch_mb"], 0), f"{r['x_budget']:.2f}", _f(r["peak_mb"], 0),
             _f(r["base_mb"], 0), _f(r["images_mb"], 0), _f(r["seconds"], 0)] for r in data["rows"]]
    note = (f"`denoise` of an EXR of {data['scene']} rendered at {data['render_spp']} spp in two halves (colour and a "
            "`variance` layer), told the spp of the row (which networks run), in a fresh process. Scratch = the peak "
            "RSS from just before the file is read to the end of writing - the RSS then (the loaded process) - the "
            "images (the input's colour and variance as float32, the output). s: reading, denoising and writing.")
    return [caption("python -m benchmarks.denoise_memory", "benchmarks/results/denoise_memory.json", data, note), "",
            *_table(["image", "entry", "spp", "networks", "budget MB", "scratch MB", "x budget", "peak MB",
                     "process MB", "images MB", "s"], rows, right=4)]


def denoise_tile_memory(results: Results) -> list[str]:
    """One tile of each preset: measured scratch against the planner's estimate, per side."""
    data = results.json("denoise_memory")["calibrate"]
    sides = sorted({r["side"] for r in data["rows"]})
    cells: dict[tuple[str, str], dict[int, str]] = {}
    for r in data["rows"]:
        cells.setdefault((r["preset"], r["setting"]), {})[r["side"]] = \
            f"{r['scratch_mb']:,.0f} / {r['estimate_mb']:,.0f}"
    rows = [[preset, setting, *(by_side.get(s, "") for s in sides)] for (preset, setting), by_side in cells.items()]
    note = ("One window of the whole chain (denoise.chain.denoise_image on an SxS image, random weights, the "
            "variance given to the models that take it) in a fresh process: resident scratch beyond the output / "
            "the tile planner's estimate (denoise.chain.tile_bytes_per_pixel x pixels + TILE_FIXED_BYTES), MB. "
            "'glibc default': without denoise/allocator.py's fixed mmap threshold.")
    return [caption("python -m benchmarks.denoise_memory", "benchmarks/results/denoise_memory.json", data, note), "",
            *_table(["preset", "setting", *(f"{s}x{s}" for s in sides)], rows, right=2)]


def fuzz(results: Results) -> list[str]:
    """Mutated inputs per reader over the fuzz campaign's lifetime, their outcomes, the failures."""
    data = results.json("fuzz")
    last = data["runs"][-1] if data.get("runs") else {}
    rows = []
    for name, t in data["targets"].items():
        open_failures = sum(1 for f in t["failures"] if not f.get("fixed_by"))
        rows.append([name, _f(t["inputs"]), _f(t["statuses"].get("ok", 0)), _f(t["statuses"].get("error", 0)),
                     _f(len(t["failures"])), _f(open_failures)])
    earlier = "; ".join(f"{r['date']} `{r['command']}` (code of {r.get('commit', 'an unrecorded commit')})"
                        for r in data.get("runs", []))
    note = (f"Lifetime totals over the campaigns: {earlier}. A result: exit 0; an error: exit 1 or 2 with one "
            "line `PROG: error: ...`; anything else is a failure (a traceback, other output, a crash or hang, "
            "> 5 s, > 1 GB, an input changed); open: not yet fixed with a regression test.")
    return [caption("make fuzz", "benchmarks/results/fuzz.json", last, note), "",
            *_table(["reader", "inputs", "results", "one-line errors", "failures found", "open"], rows)]


def mutation(results: Results) -> list[str]:
    """Mutation score of each core module against its tests, and its surviving mutants."""
    data = results.json("mutation")
    rows = [[f"`{m['module']}`" + (" (reading)" if m["module"].endswith("checkpoint.py") else
                                    " (layer choice)" if m["module"].endswith("exr_layers.py") else ""),
             ", ".join(f"`{t}`" for t in m["tests"]), _f(m["mutants"]), _f(m["killed"]), _f(len(m["survived"])),
             f"{m['score']:.2f}", m.get("commit", "-")] for m in data["modules"].values()]
    note = ("A mutant is killed when the module's tests fail on it; score = killed / mutants; code: the commit "
            "each module was mutated at (the last run's date and load above); the survivors are listed in "
            "the result file.")
    return [caption("make mutation", "benchmarks/results/mutation.json", data, note), "",
            *_table(["module", "tests", "mutants", "killed", "survived", "score", "code"], rows, right=2)]


TABLES: dict[str, Callable[[Results], list[str]]] = {
    f.__name__: f for f in (models, strip_caption, unknown_spp, image_noise, denoise_process, scoreboard, scoreboard_scenes, aov_cost, noise_guard, noise_guard_settings, energy, ensemble, inference,
                            multiscale_presets, roofline, budget, presets, recipe_runs, validation, val_scenes, trend, ablations,
                            train_throughput, scaleout, extremes, render_memory, denoise_memory, denoise_path_memory,
                            denoise_tile_memory,
                            fuzz, mutation)}


def pages(root: Path = ROOT) -> list[Path]:
    """README.md and every docs page."""
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def render_page(text: str, results: Results, where: str = "page") -> str:
    """``text`` with every marked table rendered anew; raises ValueError for an unknown table."""
    def table(m: re.Match[str]) -> str:
        name = m.group(2)
        if name not in TABLES:
            raise ValueError(f"{where}: unknown table {name!r} (known: {', '.join(TABLES)})")
        return m.group(1) + "\n".join(TABLES[name](results)) + "\n" + m.group(4)

    return MARKERS.sub(table, text)


def stale_tables(root: Path = ROOT) -> list[str]:
    """``PAGE: table NAME`` for every table that differs from what the result files give."""
    results, stale = Results(root), []
    for page in pages(root):
        text = page.read_text()
        fresh = render_page(text, results, str(page.relative_to(root)))
        old, new = MARKERS.findall(text), MARKERS.findall(fresh)
        stale += [f"{page.relative_to(root)}: table {a[1]}" for a, b in zip(old, new) if a != b]
    return stale


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m benchmarks.readme_tables", description=__doc__.split("\n")[0])
    p.add_argument("--check", action="store_true", help="change nothing; exit 1 if a table is stale")
    p.add_argument("--root", type=Path, default=ROOT, help="the checkout (default: this one)")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        if args.check:
            stale = stale_tables(args.root)
            for line in stale:
                print(f"stale: {line}")
            return 1 if stale else 0
        results = Results(args.root)
        for page in pages(args.root):
            text = page.read_text()
            fresh = render_page(text, results, str(page.relative_to(args.root)))
            if fresh != text:
                write_text_atomic(page, fresh)
                print(f"rewrote tables in {page.relative_to(args.root)}")
    except (OSError, ValueError, KeyError) as exc:
        return p.fail(exc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
