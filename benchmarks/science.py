"""The science table: denoiser designs trained for equal CPU time on the same data, side by side.

Each run trains from scratch on the same scenes (``--max-scenes``) of one dataset with the same
seed until its optimisation has used ``--cpu-minutes`` of process CPU time (``train --cpu-minutes``,
so a busy machine changes wall time, not the comparison), validating on the same held-out
scenes. The designs:

* ``flat_paper``  — Kim & Lee's flat DenseNet (k=12, L=20), 32-px patches, batch 64
* ``flat_fast``   — the flat ``flat-s`` preset (k=8, L=10), 32-px patches, batch 64
* ``unet_noise``  — the multi-scale dense network ``unet-m`` with the noise input (the variance
  averaged over 5x5 pixels), 128-px patches
* ``unet_noise_px`` — the same with each pixel's own variance estimate (``--noise-radius 0``)
* ``unet_rgb``    — the same without the noise input
* ``plain_noise`` — a plain (non-dense) U-Net of equal MACs per pixel, with the noise input
* ``unet_noise_l1`` — ``unet_noise`` trained with plain L1 instead of L1 + gradient L1

    python -m benchmarks.science commands [--data DIR --runs DIR --cpu-minutes 20 --max-scenes 60]
    python -m benchmarks.science report [--runs DIR]

A run continued past the common budget (``train --out runs/science/NAME --resume --cpu-minutes 60
--threads 1 --no-progress``) gets a second table at the longer budget.

``commands`` prints the exact ``train`` command of every run (run them in the background, two at
a time with ``--threads 1`` on a 2-core machine). ``report`` reads the runs' logs and writes
``benchmarks/results/science.json``, ``science.md`` (validation PSNR per spp at the end of the
budget, and at equal CPU minutes along the way) and ``science.png`` (validation PSNR against
CPU minutes). For the noise-input runs it also validates the final checkpoint with the noise
hidden (as ``denoise`` on a single EXR sees it), which is the price of not having the halves.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from imaging.atomic_io import write_json_atomic
from training.run_log import RunLog, validation_curve

RESULTS = Path(__file__).resolve().parent / "results"
# the recorded runs' schedule: a step schedule (train's default is a cosine over the run)
UNET = ["--preset", "unet-m", "--patch", "128", "--batch", "8", "--lr", "1e-3", "--lr-warmup", "100",
        "--lr-cosine-steps", "0"]
NOISE = ["--noise-input", "--noise-radius", "2"]  # the recorded runs fed the noise; the unet- presets do not
FLAT = ["--patch", "32", "--batch", "64", "--lr", "1e-3", "--lr-warmup", "0", "--lr-cosine-steps", "0"]
RUNS: dict[str, list[str]] = {
    "flat_paper": ["--preset", "paper", *FLAT, "--val-every", "40"],
    "flat_fast": ["--preset", "flat-s", *FLAT, "--val-every", "150"],
    "unet_noise": [*UNET, *NOISE, "--val-every", "100"],
    "unet_noise_px": [*UNET, "--noise-input", "--noise-radius", "0", "--val-every", "100"],
    "unet_rgb": [*UNET, "--no-noise-input", "--val-every", "100"],
    "plain_noise": [*UNET, *NOISE, "--arch", "plain_unet", "--val-every", "100"],
    "unet_noise_l1": [*UNET, *NOISE, "--gradient-weight", "0", "--val-every", "100"],
}
SPP_COLUMNS = ("4", "16", "128")


def commands(data: str, runs: Path, cpu_minutes: float, max_scenes: int) -> list[str]:
    """The exact train command of every run."""
    common = ["--data", data, "--max-scenes", str(max_scenes), "--cpu-minutes", f"{cpu_minutes:g}",
              "--steps", "1000000", "--seed", "0", "--threads", "1", "--log-every", "20",
              "--ckpt-every", "100", "--no-progress"]
    return [" ".join(["train", "--out", str(runs / name), *common, *flags]) for name, flags in RUNS.items()]


def _at(curve: list[dict[str, Any]], minutes: float) -> dict[str, Any] | None:
    """Validation at ``minutes`` CPU minutes: the mean of the validations made in the last quarter
    before it, ``(0.75 * minutes, minutes]`` (at a constant LR one validation scatters by ~1-2 dB
    from the next), with the step of the last of them; None when there is none. A run stops at
    the first step past its budget, so its final validation may come up to 1 % (+3 s) late and
    still counts."""
    window = [c for c in curve if 0.75 * minutes < c["cpu_min"] <= minutes * 1.01 + 0.05]
    if not window:
        return None
    mean = lambda key: float(np.mean([c[key] for c in window]))  # noqa: E731
    per_spp = {s: float(np.mean([c["per_spp"][s] for c in window])) for s in window[-1]["per_spp"]}
    return {**window[-1], "psnr": mean("psnr"), "per_spp": per_spp, "validations": len(window)}


def hidden_noise_psnr(run: Path) -> dict[str, Any]:
    """Validate the run's last checkpoint with and without its noise input on its own val scenes."""
    from model.checkpoint import load_model
    from training.dataset import load_val_images, read_manifest
    from training.validate import Validator

    model, config, meta = load_model(run / "last.ckpt")
    train = meta["train_config"]
    root = Path(train["data"])
    records = [r for r in read_manifest(root) if r.split == "val"
               and (not train.get("max_scenes") or r.index < train["max_scenes"])]
    images = load_val_images(root, records, config.aux_inputs, noise=True, normals=config.aux_normals)
    with_noise = Validator(images, use_oidn=False).run(model)
    hidden = Validator([type(i)(i.scene, i.spp, i.noisy, i.ref, i.aux, None) for i in images],
                       use_oidn=False).run(model)
    pick = {"psnr": lambda r: r["psnr"], "per_spp": lambda r: {s: v["psnr"]["ours"] for s, v in r["per_spp"].items()}}
    return {"with_noise": {k: f(with_noise) for k, f in pick.items()},
            "noise_hidden": {k: f(hidden) for k, f in pick.items()}}


def report(runs: Path) -> dict[str, Any]:
    """Read every run under ``runs``; write science.json/.md/.png; return the results."""
    results: dict[str, Any] = {"command": "python -m benchmarks.science report", "runs": {},
                               "date": time.strftime("%Y-%m-%d %H:%M")}
    for name in RUNS:
        if not (runs / name / "log.jsonl").exists():
            continue
        config = json.loads((runs / name / "train_config.json").read_text())
        curve = validation_curve(RunLog(runs / name / "log.jsonl").read())
        entry = {"config": config, "curve": curve, "budget_min": config.get("cpu_budget_s", 0) / 60}
        if config["model"].get("noise_input") and (runs / name / "last.ckpt").exists():
            entry["hidden_noise"] = hidden_noise_psnr(runs / name)
        results["runs"][name] = entry
    write_json_atomic(RESULTS / "science.json", results)
    (RESULTS / "science.md").write_text("\n".join(table(results)) + "\n")
    plot(results, RESULTS / "science.png")
    return results


def table(results: dict[str, Any]) -> list[str]:
    """Markdown: per run, validation PSNR at the end of its CPU budget and at equal minutes."""
    runs = results["runs"]
    if not runs:
        return ["no runs"]
    budget = min(r["budget_min"] for r in runs.values())
    marks = [budget / 4, budget / 2, budget]
    lines = [f"Validation PSNR (dB, tonemapped; mean over the val images) at equal CPU minutes of optimisation, "
             f"each the mean of the validations in the last quarter before that time; noisy input and OIDN "
             f"colour-only on the same images. ({results['date']})", "",
             "| run | arch | noise input | loss | steps | " + " | ".join(f"{m:.0f} min" for m in marks) + " | "
             + " | ".join(f"{s} spp" for s in SPP_COLUMNS) + " |",
             "|---|---|---|---|---:|" + "---:|" * (len(marks) + len(SPP_COLUMNS))]
    for name, r in runs.items():
        model = r["config"]["model"]
        loss = "L1" if r["config"].get("gradient_weight") == 0 else "0.9 L1 + 0.1 grad"
        cells = [_at(r["curve"], m) for m in marks]
        end = cells[-1]
        spp = [f"{end['per_spp'].get(s, float('nan')):.2f}" if end else "-" for s in SPP_COLUMNS]
        lines.append(f"| {name} | {model['arch']} | {'yes' if model.get('noise_input') else 'no'} | {loss} | "
                     f"{end['step'] if end else '-'} | "
                     + " | ".join(f"{c['psnr']:.2f}" if c else "-" for c in cells) + " | " + " | ".join(spp) + " |")
    ref = next((r["curve"][-1] for r in runs.values() if r["curve"]), None)
    if ref:
        lines.append(f"| noisy input | | | | | | | | " + " | ".join(f"{ref['noisy'].get(s, float('nan')):.2f}"
                                                                 for s in SPP_COLUMNS) + " |")
        if all(ref["oidn"].get(s) is not None for s in SPP_COLUMNS):
            lines.append(f"| OIDN colour-only | | | | | | | | " + " | ".join(f"{ref['oidn'][s]:.2f}"
                                                                         for s in SPP_COLUMNS) + " |")
    longer = {n: r for n, r in runs.items() if r["budget_min"] > budget}
    if longer:
        longest = max(r["budget_min"] for r in longer.values())
        marks = sorted({budget, (budget + longest) / 2, longest})
        lines += ["", f"Runs continued to {longest:.0f} CPU minutes (the same run resumed with a larger "
                  "`--cpu-minutes`: nothing in its schedule depends on the budget):", "",
                  "| run | steps | " + " | ".join(f"{m:.0f} min" for m in marks) + " | "
                  + " | ".join(f"{s} spp" for s in SPP_COLUMNS) + " |",
                  "|---|---:|" + "---:|" * (len(marks) + len(SPP_COLUMNS))]
        for name, r in longer.items():
            cells = [_at(r["curve"], m) for m in marks]
            end = cells[-1]
            spp = [f"{end['per_spp'].get(s, float('nan')):.2f}" if end else "-" for s in SPP_COLUMNS]
            lines.append(f"| {name} | {end['step'] if end else '-'} | "
                         + " | ".join(f"{c['psnr']:.2f}" if c else "-" for c in cells) + " | " + " | ".join(spp) + " |")
    hidden = {n: r["hidden_noise"] for n, r in runs.items() if "hidden_noise" in r}
    if hidden:
        lines += ["", "Noise input hidden (a single EXR without halves), final checkpoints:", "",
                  "| run | with noise | noise hidden | " + " | ".join(f"{s} spp hidden" for s in SPP_COLUMNS) + " |",
                  "|---|---:|---:|" + "---:|" * len(SPP_COLUMNS)]
        for name, h in hidden.items():
            lines.append(f"| {name} | {h['with_noise']['psnr']:.2f} | {h['noise_hidden']['psnr']:.2f} | "
                         + " | ".join(f"{h['noise_hidden']['per_spp'].get(s, float('nan')):.2f}"
                                      for s in SPP_COLUMNS) + " |")
    return lines


def plot(results: dict[str, Any], path: Path) -> None:
    """Validation PSNR against CPU minutes, one line per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    for name, r in results["runs"].items():
        if r["curve"]:
            ax.plot([c["cpu_min"] for c in r["curve"]], [c["psnr"] for c in r["curve"]], marker="o", ms=3, label=name)
    ax.set_xlabel("optimisation CPU minutes")
    ax.set_ylabel("validation PSNR (dB), mean over spp levels")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("what", choices=["commands", "report"])
    p.add_argument("--data", default="data/train256")
    p.add_argument("--runs", default="runs/science")
    p.add_argument("--cpu-minutes", type=float, default=20.0)
    p.add_argument("--max-scenes", type=int, default=40)
    args = p.parse_args()
    if args.what == "commands":
        print("\n".join(commands(args.data, Path(args.runs), args.cpu_minutes, args.max_scenes)))
    else:
        print("\n".join(table(report(Path(args.runs)))))


if __name__ == "__main__":
    main()
