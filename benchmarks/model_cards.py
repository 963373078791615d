"""Fill the model cards of ``model/weights/manifest.json`` from the files they describe.

Per checkpoint: its file's SHA-256, the pixel filter of its training renders and a summary of its
last training run (steps, CPU-minutes, data, warm start) and, where recorded, the recipe stage that
made it and the hours and hardware of its whole lineage, all read from the checkpoint's own header.
Per registry entry: PSNR at 4/16/128 spp and FLIP at 16 spp (scored mean over the eval scenes,
``benchmarks/results/evaluate.json``, rows named by the entry) and its time as a ratio to OIDN's
(``benchmarks/results/inference.json``: the median of the per-process ratios, at each size the
dearest spp measured; ``time_ratio`` the largest over sizes; ``time_by_spp`` at each spp the largest
over sizes, what ``auto`` compares). ``sources`` names each results file's command and date.
Nothing here is typed by hand: ``--check`` lists what differs and tests/test_model_cards.py runs it.

    python -m benchmarks.model_cards [--check]
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

from console.usage import OneLineParser
from imaging.atomic_io import write_text_atomic
from imaging.hashing import file_sha256
from model.checkpoint import checkpoint_meta, read_checkpoint
from model.registry import CARD_SPP, MANIFEST, split_member
from training.recipe import FINETUNE

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def _summary_row(evaluate: dict[str, Any], name: str, spp: int) -> dict[str, Any] | None:
    return (evaluate.get("summary", {}).get("scored", {}).get(str(spp)) or {}).get("models", {}).get(name)


def _same_files(recorded: str | None, shas: set[str]) -> bool:
    """True when a result file's ``+``-joined SHA-256s are those of the entry's checkpoints now."""
    return bool(recorded) and set(recorded.split("+")) == shas


def training_summary(path: Path) -> dict[str, Any]:
    """What a checkpoint's header says of its last training run and, where it records them
    (``meta``, :func:`model.checkpoint.checkpoint_meta`), the recipe stage that made it and the
    hours and hardware of every run up to it."""
    header = read_checkpoint(path).header
    meta = checkpoint_meta(header)
    train = header.get("train_config") or {}
    data = header.get("data_config") or {}
    extra = header.get("extra") or {}
    scenes = data.get("scenes") or {}
    spp = data.get("spp") or []
    res = data.get("res") or []
    summary = {"steps": header.get("step"),
               "cpu_minutes": round(float(extra["cpu_s"]) / 60, 1) if extra.get("cpu_s") else None,
               "warm_start": warm_start_name(train.get("init_from"), (meta.get("recipe") or {}).get("stage")),
               "data": ", ".join(part for part in (
                   f"{scenes['train']} scenes" if scenes.get("train") else "", "x".join(map(str, res)),
                   f"{min(spp)}-{max(spp)} spp" if spp else "",
                   f"{data['ref_spp']}-spp references" if data.get("ref_spp") else "") if part) or None,
               "recipe_stage": (meta.get("recipe") or {}).get("stage"),
               "hours": {k: round(float(v), 2) for k, v in meta["hours"].items()} if meta.get("hours") else None,
               "hardware": list(meta["hardware"]) if meta.get("hardware") else None}
    return {k: v for k, v in summary.items() if v is not None}


def warm_start_name(init_from: str | None, stage: str | None) -> str | None:
    """What a run started from: inside a recipe the earlier stage (``RUN/first/best.ckpt`` ->
    ``stage first``), a fine-tune's or a plain run's file by its stem; None from scratch."""
    if not init_from:
        return None
    path = Path(init_from)
    if stage and stage != FINETUNE and path.stem in ("best", "last"):
        return f"stage {path.parent.name}"
    return path.stem


def entry_figures(name: str, shas: set[str], evaluate: dict[str, Any], inference: dict[str, Any]) -> dict[str, Any]:
    """An entry's card figures from the two result files, where they measured this entry's
    checkpoints (``shas``): PSNR per card spp, FLIP at 16, and per image size the time ratio to
    OIDN at the dearest known spp (``time``) and with the spp unknown (``time_unknown_spp``); per
    known spp the largest ratio over sizes (``time_by_spp``)."""
    figures: dict[str, Any] = {}
    rows = {spp: _summary_row(evaluate, name, spp) for spp in CARD_SPP}
    if all(rows.values()) and _same_files((evaluate.get("models", {}).get(name) or {}).get("sha256"), shas):
        figures["psnr"] = {str(spp): round(float(r["psnr"]), 2) for spp, r in rows.items()}
        figures["flip"] = {"16": round(float(rows[16]["flip"]), 3)}
    if not _same_files((inference.get("sha256") or {}).get(name), shas):
        return figures
    times, unknown, by_spp = {}, {}, {}
    for size, per_model in (inference.get("ratios") or {}).items():
        ratios = per_model.get(name, {})
        known = {int(s): r for s, r in ratios.items() if s != "unknown"}
        if known:
            dearest = max(known, key=lambda s: known[s])
            times[size] = {"spp": dearest, "ratio": round(float(known[dearest]), 2)}
        for spp, ratio in sorted(known.items()):
            by_spp[str(spp)] = max(by_spp.get(str(spp), 0.0), round(float(ratio), 2))
        if "unknown" in ratios:
            unknown[size] = round(float(ratios["unknown"]), 2)
    if times:
        figures["time"] = times
        figures["time_ratio"] = max(t["ratio"] for t in times.values())
        figures["time_by_spp"] = by_spp
    if unknown:
        figures["time_unknown_spp"] = unknown
    return figures


def fill(manifest: dict[str, Any], root: Path = ROOT) -> dict[str, Any]:
    """The manifest with every generated field rewritten from the files."""
    weights = root / "model" / "weights"
    evaluate = _read(root / "benchmarks" / "results" / "evaluate.json")
    inference = _read(root / "benchmarks" / "results" / "inference.json")
    out = json.loads(json.dumps(manifest))
    for card in out["checkpoints"].values():
        path = weights / card["file"]
        card["sha256"] = file_sha256(path)
        card["pixel_filter"] = (read_checkpoint(path).header.get("data_config") or {}).get("filter") or "box"
        card["training"] = training_summary(path)
    for name, entry in out["entries"].items():
        members = "+".join((entry["members"], *(tier["run"] for tier in entry["unknown_spp"]))).split("+")
        shas = {out["checkpoints"][split_member(m.strip())[0]]["sha256"] for m in members}
        entry["figures"] = entry_figures(name, shas, evaluate, inference)
    out["sources"] = {key: f"`{data['command']}`, {data.get('date', 'date not recorded')}"
                      for key, data in (("scoreboard", evaluate), ("inference", inference)) if data.get("command")}
    return out


def _read(path: Path) -> dict[str, Any]:
    return json.loads(path.read_text()) if path.is_file() else {}


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="python -m benchmarks.model_cards", description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true", help="list what differs; write nothing")
    args = parser.parse_args(argv)
    current = json.loads(MANIFEST.read_text())
    filled = fill(current)
    if args.check:
        if filled != current:
            print(f"{MANIFEST}: model cards differ from the files they describe; run python -m benchmarks.model_cards")
            return 1
        return 0
    write_text_atomic(MANIFEST, json.dumps(filled, indent=2) + "\n")
    print(f"wrote {MANIFEST}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
