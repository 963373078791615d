"""What ``denoise`` gives a render that does not say its spp: each model on one image, no variance.

A file from elsewhere often carries no spp and no halves: the Denoiser then runs a model's choice
for an unknown spp, without the noise guard. This scores that path per image, beside what the
image tells of its own noise (:mod:`denoise.image_noise`), on

* a dataset folder written by ``generate-dataset`` (``--data DIR``: every scene at every noisy spp
  against its reference; scenes of our own families, none of them in any training set when the
  seed differs), or
* the eval scenes (``--eval``: rendered at their seed 7 in one piece, against the 2048-spp
  references; the scored mean leaves out the scenes whose reference ceiling is below 40 dB).

Models are registry names, checkpoint files or expert specs, ``NAME@PRECISION`` for one float
format (default: each in ``auto``). Writes ``--out`` (JSON: per image the spp, the noise
statistics and each model's PSNR, relMSE and FLIP; per spp the means) and prints the means.

    python -m benchmarks.unknown_spp (--data DIR | --eval) --models A,B@bfloat16 [--spp 4,16,128]
        [--scenes N] [--out FILE]
"""
from __future__ import annotations

import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.eval_scenes import CEILING_DB, EVAL_DIR, RESULTS, eval_scenes, finish_record, run_record
from console.usage import COMMAND_ERRORS, OneLineParser, int_list, name_list, positive_int
from denoise.denoiser import Denoiser
from denoise.image_noise import noise_stats
from imaging.atomic_io import write_json_atomic
from imaging.exr import read_exr
from imaging.metrics import all_metrics
from imaging.naming import parse_image_name
from pipeline.evaluation import render_input

METRICS = ("psnr", "relmse", "flip")


def dataset_images(folder: Path, spps: list[int] | None, scenes: int | None):
    """(name, spp, noisy, reference) of every noisy image of a generate-dataset folder."""
    images = folder / "images"
    refs = sorted(p for p in images.glob("*_ref.hdr.exr"))
    for ref_path in refs[:scenes]:
        scene = ref_path.name.split("_")[0]
        ref = read_exr(ref_path).rgb
        for path in sorted(images.glob(f"{scene}_*spp.hdr.exr")):
            spp = parse_image_name(path.name).spp
            if spps is None or spp in spps:
                yield scene, spp, read_exr(path).rgb, ref, True


def eval_images(spps: list[int], names: list[str] | None):
    """(name, spp, noisy, reference, scored) of the eval scenes, rendered in one piece at seed 7."""
    for scene in eval_scenes(names, EVAL_DIR):
        settings = scene.settings(noise_guard=False)  # one piece: a file from elsewhere has no halves
        loaded = settings.load()
        ref = scene.reference()
        for spp in spps:
            yield scene.name, spp, render_input(loaded, spp, settings).rgb, ref, scene.ceiling_db >= CEILING_DB


def build_parser() -> OneLineParser:
    p = OneLineParser(prog="python -m benchmarks.unknown_spp", description=__doc__.split("\n")[0])
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", type=Path, help="a generate-dataset folder")
    source.add_argument("--eval", action="store_true", help="the eval scenes (../shared/eval-scenes)")
    p.add_argument("--models", type=name_list, required=True, help="comma-separated models, NAME@PRECISION")
    p.add_argument("--spp", type=int_list, help="spp to score (default: all of the dataset; 4,16,128 with --eval)")
    p.add_argument("--scenes", type=positive_int, help="the first N scenes of --data")
    p.add_argument("--eval-scenes", type=name_list, help="a subset of the eval scenes")
    p.add_argument("--out", type=Path, default=RESULTS / "unknown_spp.json")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    record = run_record("benchmarks.unknown_spp", sys.argv[1:] if argv is None else argv)
    start = time.perf_counter()
    try:
        models = {}
        for entry in args.models:
            name, _, precision = entry.partition("@")
            models[entry] = Denoiser(name, precision=precision or "auto")
        images = eval_images(list(args.spp or (4, 16, 128)), args.eval_scenes) if args.eval else \
            dataset_images(args.data, list(args.spp) if args.spp else None, args.scenes)
        rows = []
        for scene, spp, noisy, ref, scored in images:
            stats = noise_stats(noisy)
            row: dict[str, Any] = {"scene": scene, "spp": spp, "scored": scored, "level": stats.level,
                                   "ratio": stats.ratio, "noisy": _metrics(noisy, ref), "models": {}}
            for name, den in models.items():
                row["models"][name] = _metrics(den.denoise_array(noisy).image, ref)
            rows.append(row)
            print(f"... {scene} {spp} spp: level {stats.level:.3f}, " + ", ".join(
                f"{n} {m['psnr']:.2f}" for n, m in row["models"].items()), file=sys.stderr, flush=True)
    except COMMAND_ERRORS as exc:
        return parser.fail(exc)
    means = summarise(rows, list(models))
    for spp, m in means.items():
        print(f"{spp:>5} spp ({m['images']} images): noisy {m['noisy']:.2f}, "
              + ", ".join(f"{n} {m[n]:.2f}" for n in models) + " dB")
    record.update({"source": str(args.data) if args.data else "eval-scenes", "models": list(models),
                   "means_psnr": means, "images": rows})
    write_json_atomic(args.out, finish_record(record, start))
    print(f"wrote {args.out}")
    return 0


def _metrics(img: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    m = all_metrics(img, ref)
    return {k: m[k] for k in METRICS}


def summarise(rows: list[dict[str, Any]], models: list[str]) -> dict[str, dict[str, float]]:
    """Mean PSNR per spp over the scored images: the noisy input and each model."""
    by_spp: dict[int, list[dict[str, Any]]] = defaultdict(list)
    for row in rows:
        if row["scored"]:
            by_spp[row["spp"]].append(row)
    return {str(spp): {"images": len(r), "noisy": float(np.mean([x["noisy"]["psnr"] for x in r])),
                       **{n: float(np.mean([x["models"][n]["psnr"] for x in r])) for n in models}}
            for spp, r in sorted(by_spp.items())}


if __name__ == "__main__":
    sys.exit(main())
