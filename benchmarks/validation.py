"""Our own validation scenes: several checkpoints side by side with OIDN colour-only on the same images.

The trainer validates one model on its own run's held-out scenes, so two runs with different data
report on different images. This scores every ``--models`` checkpoint on one set: the ``val`` split
of each ``--data`` folder (scenes with index below ``--max-scenes``, at every spp the dataset has),
as the trainer's validation does (:class:`training.validate.Validator`: the network in float32, whole
images, tonemapped PSNR and relMSE), with the noisy input and OIDN 2.5 colour-only on the same
images, per spp and overall. ``--split train`` scores the scenes the networks trained on instead:
beside the held-out figures it gives the generalisation gap (what more scenes could still buy).

    python -m benchmarks.validation --data data/train256 --data data/media256 --models unet-m-k5-lowspp,flat-s-allspp

Writes benchmarks/results/validation.json and validation.md (``--out`` for another folder).
"""
from __future__ import annotations

import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchmarks.eval_scenes import RESULTS, finish_record, run_record, save_result
from imaging.errors import DatasetError
from console.usage import COMMAND_ERRORS, OneLineParser, name_list, positive_int
from model.checkpoint import load_model
from training.dataset import ValImage, load_val_images, read_manifest
from training.train import DATASET_ID_STRIDE
from training.validate import Validator
from model.registry import registry, split_member


SPLITS = ("val", "train")


def val_images(folders: list[Path], max_scenes: int | None, noise: bool,
               min_ceiling_db: float | None = None, split: str = "val") -> list[ValImage]:
    """The ``split`` scenes (``val``, or ``train``: those the networks trained on) of every folder
    (index below ``max_scenes``; with ``min_ceiling_db``, only those whose reference's noise ceiling
    is at least that), scene ids offset per folder as in training. Raises :class:`DatasetError` when
    there are none."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}, not {split!r}")
    images: list[ValImage] = []
    for k, root in enumerate(folders):
        records = [r for r in read_manifest(root) if r.split == split and (not max_scenes or r.index < max_scenes)
                   and (min_ceiling_db is None or (r.ref_ceiling_db or 0.0) >= min_ceiling_db)]
        images += load_val_images(root, records, aux=False, noise=noise, index_offset=k * DATASET_ID_STRIDE)
    if not images:
        clean = f" whose reference's noise ceiling is at least {min_ceiling_db:g} dB" if min_ceiling_db else ""
        raise DatasetError(f"no {split!r} scenes{clean} in {', '.join(map(str, folders))}")
    return images


def score(models: dict[str, Path], folders: list[Path], max_scenes: int | None,
          oidn: bool = True, min_ceiling_db: float | None = None, split: str = "val") -> dict[str, Any]:
    """Every model's :meth:`Validator.run` result on the same images, with the noisy input's and
    OIDN's (``baselines``: per spp, from the first model's run). Raises ValueError for a model
    with albedo/normal inputs (the validation sets here are colour only)."""
    loaded = {name: load_model(path) for name, path in models.items()}
    aux = [name for name, (_, config, _) in loaded.items() if config.aux_inputs]
    if aux:
        raise ValueError(f"{', '.join(aux)}: models with albedo/normal inputs are not scored here")
    images = val_images(folders, max_scenes, noise=any(c.noise_input for _, c, _ in loaded.values()),
                        min_ceiling_db=min_ceiling_db, split=split)
    validator = Validator(images, use_oidn=oidn)  # caches the noisy and OIDN scores: equal for every model
    runs = {name: validator.run(model) for name, (model, _, _) in loaded.items()}
    results = {name: {"path": str(models[name]), "config": config.to_dict(), "step": meta.get("step"),
                      "psnr": runs[name]["psnr"], "relmse": runs[name]["relmse"],
                      "per_spp": {s: {m: v[m]["ours"] for m in ("psnr", "relmse")}
                                  for s, v in runs[name]["per_spp"].items()}}
               for name, (_, config, meta) in loaded.items()}
    first = next(iter(runs.values()))["per_spp"]
    baselines = {who: {s: {m: v[m][who] for m in ("psnr", "relmse")} for s, v in first.items()}
                 for who in ("noisy", "oidn")}
    for who, per_spp in baselines.items():
        present = [v["psnr"] for v in per_spp.values() if v["psnr"] is not None]
        baselines[who] = {"per_spp": per_spp, "psnr": sum(present) / len(present) if present else None}
    return {"split": split, "images": len(images), "scenes": len({i.scene for i in images}),
            "spp": sorted(int(s) for s in first), "models": results, "baselines": baselines}


def _db(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def note(result: dict[str, Any]) -> str:
    """What the table's figures are."""
    clean = f" (references of noise ceiling >= {result['min_ceiling_db']:g} dB)" if result.get("min_ceiling_db") else ""
    scenes = "training" if result.get("split") == "train" else "held-out"
    return (f"{result['images']} images of {result['scenes']} {scenes} scenes{clean} at {result['spp'][0]}-"
            f"{result['spp'][-1]} spp; PSNR dB (tonemapped) of the network in float32, as the trainer validates "
            "it; OIDN 2.5 colour-only on the same images; the last columns: each model minus OIDN.")


def table(result: dict[str, Any]) -> list[str]:
    """PSNR per spp and overall of the noisy input, every model and OIDN, and each model's lead over OIDN."""
    models, noisy, oidn = result["models"], result["baselines"]["noisy"], result["baselines"]["oidn"]
    head = ["spp", "noisy", *models, "OIDN", *(f"{m} - OIDN" for m in models)]
    lines = ["| " + " | ".join(head) + " |", "|" + "---:|" * len(head)]

    def row(label: str, pick: Callable[[dict[str, Any]], float | None]) -> str:
        ours = [pick(m) for m in models.values()]
        target = pick(oidn)
        lead = ["-" if v is None or target is None else f"{v - target:+.2f}" for v in ours]
        return "| " + " | ".join([label, _db(pick(noisy)), *map(_db, ours), _db(target), *lead]) + " |"

    for spp in result["spp"]:
        lines.append(row(str(spp), lambda e, s=str(spp): e["per_spp"][s]["psnr"]))
    lines.append(row("**mean**", lambda e: e["psnr"]))
    return lines


def markdown(result: dict[str, Any]) -> str:
    """validation.md: the command, :func:`note` and :func:`table`."""
    return "\n".join([f"Source: `{result['command']}`; {result['date']}. {note(result)}", "", *table(result)]) + "\n"


def model_specs(entries: tuple[str, ...]) -> dict[str, Path]:
    """``--models`` entries -> {column name: checkpoint}: ``NAME=CHECKPOINT`` names a column, a preset
    or path names itself."""
    specs = {}
    for entry in entries:
        name, _, spec = entry.partition("=") if "=" in entry else (entry, "=", entry)
        specs[name] = registry().member(spec).path
    return specs


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="python -m benchmarks.validation", description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, action="append", required=True,
                   help="dataset folder (repeatable): its --split scenes are scored")
    p.add_argument("--split", choices=SPLITS, default="val",
                   help="the held-out scenes (val, the default) or those the networks trained on (train)")
    default = registry().entries[registry().default].members
    members = tuple(dict.fromkeys(split_member(m)[0] for m in default.split("+")))  # each once, on every spp
    p.add_argument("--models", type=name_list, default=members,
                   help="comma-separated registry checkpoints, files or NAME=CHECKPOINT, each scored alone "
                        f"(default: the default entry's checkpoints, {','.join(members)})")
    p.add_argument("--max-scenes", type=positive_int, help="only scenes with index below this")
    p.add_argument("--min-ceiling-db", type=float, metavar="DB",
                   help="only scenes whose reference is clean enough: its noise ceiling (from its halves, "
                        "in the manifest) at least DB")
    p.add_argument("--no-oidn", action="store_true", help="skip the OIDN baseline")
    p.add_argument("--out", type=Path, default=RESULTS)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    argv = sys.argv[1:] if argv is None else argv
    args = parser.parse_args(argv)
    try:
        models = model_specs(args.models)
        record = run_record("benchmarks.validation", argv)
        start = time.perf_counter()
        result = score(models, args.data, args.max_scenes, oidn=not args.no_oidn, min_ceiling_db=args.min_ceiling_db,
                       split=args.split)
    except COMMAND_ERRORS as exc:
        return parser.fail(exc)
    result = {**finish_record(record, start), "data": [str(d) for d in args.data],
              "max_scenes": args.max_scenes, "min_ceiling_db": args.min_ceiling_db, **result}
    text = markdown(result)
    path = save_result(args.out, "validation", result, text)
    print(text, end="")
    print(f"wrote {path} and validation.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
