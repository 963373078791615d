"""How well one image tells its own pixel filter: :mod:`denoise.image_noise` on renders through a
box, a Gaussian and a tent filter.

Every scene of a ``generate-dataset`` folder (its ``scenes/*/scene.xml``; ``--eval``: the eval
scenes) is rendered at each ``--spp`` through each filter (Mitsuba's defaults: Gaussian stddev
0.5, tent radius 1) at ``--res``; for each image the Nyquist ratio and noise level are recorded,
and per filter and spp the share called filtered (ratio below
:data:`denoise.image_noise.FILTERED_BELOW`): for the box, the false alarms; for the others, the
renders the warning catches.

    python -m benchmarks.image_noise (--data DIR | --eval) [--scenes N] [--spp 4,16,128] [--res 128]
"""
from __future__ import annotations

import dataclasses
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.eval_scenes import EVAL_DIR, RESULTS, eval_scenes, finish_record, run_record
from console.usage import COMMAND_ERRORS, OneLineParser, int_list, positive_int
from denoise.image_noise import FILTERED_BELOW, noise_stats
from imaging.atomic_io import write_json_atomic
from rendering.render import prepare, render_loaded
from rendering.scene_io import PreparedScene

FILTERS = ("box", "gaussian", "tent")
_BOX = re.compile(r'<rfilter type="box"[^>]*/>')


def with_filter(prepared: PreparedScene, name: str) -> PreparedScene:
    """The prepared scene (box filter forced) with its film's filter replaced by ``name``."""
    if name == "box":
        return prepared
    xml, count = _BOX.subn(f'<rfilter type="{name}"/>', prepared.xml or "")
    if not count:
        raise ValueError(f"{prepared.source}: no box filter to replace")
    return dataclasses.replace(prepared, xml=xml)


def load_any_filter(prepared: PreparedScene) -> Any:
    """``mi.load_string`` of a prepared XML scene whatever its filter (the project's loader
    refuses anything but a box, which is what this benchmark needs to get past)."""
    import mitsuba as mi

    from rendering.backend import select_variant

    select_variant()
    resolver = mi.file_resolver()
    for folder in prepared.search_paths:
        resolver.prepend(str(folder))
    return mi.load_string(prepared.xml, **prepared.params)


def scene_files(args: Any) -> list[Path]:
    if args.eval:
        return [s.folder / "scene.xml" for s in eval_scenes(None, EVAL_DIR)]
    return sorted((args.data / "scenes").glob("*/scene.xml"))[:args.scenes]


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m benchmarks.image_noise", description=__doc__.split("\n")[0])
    source = p.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", type=Path, help="a generate-dataset folder (its scenes/*/scene.xml)")
    source.add_argument("--eval", action="store_true", help="the eval scenes")
    p.add_argument("--scenes", type=positive_int, default=12, help="the first N scenes of --data")
    p.add_argument("--spp", type=int_list, default=(4, 16, 128))
    p.add_argument("--res", type=positive_int, default=128)
    p.add_argument("--out", type=Path, default=RESULTS / "image_noise.json")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    record = run_record("benchmarks.image_noise", sys.argv[1:] if argv is None else argv)
    start = time.perf_counter()
    rows = []
    try:
        for path in scene_files(args):
            prepared = prepare(path, (args.res, args.res))
            for name in FILTERS:
                scene = load_any_filter(with_filter(prepared, name))
                for spp in args.spp:
                    stats = noise_stats(render_loaded(scene, spp, seed=5).rgb)
                    rows.append({"scene": path.parent.name, "filter": name, "spp": spp, "ratio": stats.ratio,
                                 "level": stats.level, "filtered": stats.filtered})
            print(f"... {path.parent.name}", file=sys.stderr, flush=True)
    except COMMAND_ERRORS as exc:
        return p.fail(exc)
    summary = {name: {str(spp): {"images": len(sel), "called_filtered": float(np.mean([r["filtered"] for r in sel])),
                                 "ratio_min": float(np.nanmin([r["ratio"] for r in sel])),
                                 "ratio_max": float(np.nanmax([r["ratio"] for r in sel]))}
                      for spp in args.spp
                      for sel in [[r for r in rows if r["filter"] == name and r["spp"] == spp]]}
               for name in FILTERS}
    for name, per_spp in summary.items():
        print(f"{name:9}" + "  ".join(f"{spp} spp: {s['called_filtered']:.0%} called filtered, ratio "
                                      f"{s['ratio_min']:.2f}-{s['ratio_max']:.2f}" for spp, s in per_spp.items()))
    record.update({"source": "eval-scenes" if args.eval else str(args.data), "threshold": FILTERED_BELOW,
                   "summary": summary, "images": rows})
    write_json_atomic(args.out, finish_record(record, start))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
