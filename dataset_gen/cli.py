"""``generate-dataset``: render procedural scenes at several spp plus references.

Example: ``generate-dataset --scenes 200 --out data/train --res 128 --spp 4,16,64,128 --ref-spp 4096``
Your own scenes: ``generate-dataset --scene-files my/scenes/*.xml --out data/mine --res 256 ...``
(each file one scene); your renderer's filter: ``--pixel-filter gaussian:stddev=0.5``.
On a Dask cluster: add ``--scheduler tcp://host:8786`` (or ``--scheduler local:2`` to try it here).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dataset_gen.cluster import SchedulerSpec, parse_scheduler
from dataset_gen.config import DatasetConfig, stored_filter
from dataset_gen.generate import generate_dataset
from imaging.errors import DatasetError, DenoiserError
from console.progress import tqdm_bars
from console.usage import COMMAND_ERRORS, OneLineParser, int_list, name_list
from rendering.scene_io import PIXEL_FILTERS, pixel_filter_spec


def _resolution(text: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    try:
        w, h = (int(parts[0]), int(parts[0])) if len(parts) == 1 else (int(parts[0]), int(parts[1]))
    except (ValueError, IndexError):
        raise argparse.ArgumentTypeError(f"expected N or WxH, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"resolution must be positive, got {text!r}")
    return w, h


def _scheduler(text: str) -> SchedulerSpec:
    try:
        return parse_scheduler(text)
    except DatasetError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _pixel_filter(text: str) -> dict:
    try:
        return pixel_filter_spec(text)
    except DenoiserError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def scene_files(paths: list[str]) -> tuple[str, ...]:
    """The XML files of ``--scene-files``: each path a file, or a folder whose ``*.xml`` are taken
    (sorted); absolute, in the order given. Raises :class:`DatasetError` for a missing path or none."""
    files: list[str] = []
    for text in paths:
        path = Path(text)
        if path.is_dir():
            found = sorted(path.glob("*.xml"))
            if not found:
                raise DatasetError(f"{path}: no *.xml scene files in this folder")
            files += [str(f.resolve()) for f in found]
        elif path.is_file():
            files.append(str(path.resolve()))
        else:
            raise DatasetError(f"{path}: scene file not found")
    return tuple(files)


def build_parser() -> argparse.ArgumentParser:
    from scenes.registry import DEFAULT_FAMILIES, FAMILIES

    p = OneLineParser(prog="generate-dataset", description=__doc__.split("\n")[0])
    p.add_argument("--scenes", type=int,
                   help="number of scenes (indices 0..N-1); with --scene-files, default: one per file")
    p.add_argument("--out", required=True,
                   help="dataset folder: created (or an empty one used); one holding a dataset of the same "
                        "settings is resumed (the missing scenes added, none replaced); a file, a dataset of "
                        "other settings or a folder holding anything else is refused")
    p.add_argument("--families", type=name_list,
                   default=DEFAULT_FAMILIES, help=f"comma-separated subset of: {', '.join(FAMILIES)}")
    p.add_argument("--scene-files", nargs="+", metavar="XML",
                   help="render these Mitsuba scene files (or every *.xml of a folder) instead of families")
    p.add_argument("--pixel-filter", type=_pixel_filter, default=None, metavar="NAME[:PARAM=V,...]",
                   help=f"pixel filter of every render: {', '.join(PIXEL_FILTERS)} (default box; e.g. "
                        "gaussian:stddev=0.5, Mitsuba's default); recorded in dataset.json")
    p.add_argument("--spp", type=int_list, default=(4, 16, 64, 128), help="noisy sample counts")
    p.add_argument("--ref-spp", type=int, default=4096, help="reference samples (two halves)")
    p.add_argument("--res", type=_resolution, default=(128, 128), help="N or WxH pixels")
    p.add_argument("--seed", type=int, default=0, help="dataset seed (scene i depends on seed, i)")
    p.add_argument("--val-fraction", type=float, default=0.1, help="share of scenes in split 'val'")
    p.add_argument("--aovs", type=name_list, default=(),
                   help="also write noisy albedo/normal buffers: alb,nrm")
    p.add_argument("--variance", action="store_true",
                   help="render each noisy image (>= 2 spp) in two halves and write its variance estimate")
    p.add_argument("--workers", type=int, default=0,
                   help="parallel scene jobs (default 0: 1 on up to 4 cores, where Mitsuba uses all cores per "
                        "render, measured fastest on 2; else one job per 4 cores)")
    p.add_argument("--scheduler", type=_scheduler, default=None,
                   help="Dask scheduler address (tcp://host:8786): one task per scene on its workers "
                        "(--out must be on storage they share); local:N starts N local workers")
    p.add_argument("--preview", action="store_true", help="write preview.png, a contact sheet")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from scenes.registry import FAMILIES

    unknown = [f for f in args.families if f not in FAMILIES]
    if unknown:
        parser.error(f"unknown family {unknown[0]!r} (known: {', '.join(FAMILIES)})")
    if args.scheduler is not None and args.workers not in (0, 1):
        parser.error("--workers and --scheduler exclude each other (the cluster's workers do the work)")
    if args.scenes is None and not args.scene_files:
        parser.error("--scenes is required (or --scene-files)")
    out = Path(args.out)
    try:
        files = scene_files(args.scene_files) if args.scene_files else ()
        cfg = DatasetConfig(res=args.res, spp=args.spp, ref_spp=args.ref_spp,
                            families=() if files else args.families, seed=args.seed, aovs=args.aovs,
                            val_fraction=args.val_fraction, variance=args.variance, scene_files=files,
                            filter=stored_filter(args.pixel_filter))
        args.scenes = len(files) if args.scenes is None else args.scenes
        summary = generate_dataset(out, cfg, args.scenes, args.workers or (1 if args.scheduler else 0),
                                   tqdm_bars("scene", not args.quiet), args.scheduler)
        if args.preview:
            from dataset_gen.manifest import read_records
            from dataset_gen.preview import contact_sheet

            print(f"preview: {contact_sheet(out, read_records(out))}")
    except COMMAND_ERRORS as exc:
        return parser.fail(exc)
    except KeyboardInterrupt:
        return parser.interrupted("; re-run the same command to resume")
    rate = 3600 * summary.done / summary.wall_s if summary.wall_s else 0.0
    print(f"{out}: {summary.done} scenes rendered, {summary.skipped} already there, "
          f"{len(summary.failed)} failed; {summary.wall_s:.1f} s wall ({rate:.0f} scenes/h), "
          f"Mitsuba render {summary.render_s:.1f} s, overhead {100 * summary.overhead():.1f}%")
    if summary.failed:
        print(f"generate-dataset: {len(summary.failed)} scene(s) failed, first: {summary.failed[0]}; "
              "re-run to retry", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
