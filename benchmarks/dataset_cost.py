"""What generating a dataset costs here: scenes/hour, Mitsuba render time vs wall time, overhead,
and 1 vs 2 parallel scene jobs (``generate-dataset --workers``).

    python -m benchmarks.dataset_cost [--scenes 9] [--res 128] [--ref-spp 1024] [--workers 1,2]

Prints a line per setting and writes benchmarks/results/dataset_cost.json with the command, the date
and the machine's load. Each setting renders the same scenes into its own temporary folder. No
result of it is committed yet; ``benchmarks/scaleout.py`` measured the in-process and Dask rates
(results/scaleout.json).
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.eval_scenes import RESULTS, finish_record, run_record
from dataset_gen.config import DatasetConfig
from dataset_gen.generate import generate_dataset
from imaging.atomic_io import write_json_atomic
from console.usage import COMMAND_ERRORS, OneLineParser, int_list, positive_int
from scenes.registry import FAMILIES


def measure(cfg: DatasetConfig, scenes: int, workers: int) -> dict[str, Any]:
    """Generate ``scenes`` scenes of ``cfg`` with ``workers`` jobs into a temporary folder."""
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        s = generate_dataset(Path(tmp) / "d", cfg, scenes, workers)
        wall = time.perf_counter() - start
    return {"workers": workers, "scenes": s.done, "wall_s": wall, "scenes_per_hour": 3600 * s.done / wall,
            "render_s": s.render_s, "job_s": s.job_s, "overhead_pct": 100 * s.overhead(),
            "msamples_per_s": s.samples / wall / 1e6}


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m benchmarks.dataset_cost", description=__doc__.split("\n")[0])
    p.add_argument("--scenes", type=positive_int, default=len(FAMILIES))
    p.add_argument("--res", type=positive_int, default=128)
    p.add_argument("--spp", type=int_list, default=(4, 16, 64, 128))
    p.add_argument("--ref-spp", type=positive_int, default=1024)
    p.add_argument("--workers", type=int_list, default=(1, 2))
    p.add_argument("--out", type=Path, default=RESULTS)
    argv = sys.argv[1:] if argv is None else argv
    args = p.parse_args(argv)
    cfg = DatasetConfig(res=(args.res, args.res), spp=args.spp, ref_spp=args.ref_spp, families=tuple(FAMILIES),
                        seed=12345)
    record, start, rows = run_record("benchmarks.dataset_cost", argv), time.perf_counter(), []
    try:
        for workers in args.workers:
            rows.append(r := measure(cfg, args.scenes, workers))
            print(f"workers {workers}: {r['scenes']} scenes in {r['wall_s']:.1f} s = {r['scenes_per_hour']:.0f}"
                  f" scenes/h, {r['msamples_per_s']:.2f} Msamples/s; Mitsuba render {r['render_s']:.1f} s"
                  f" of {r['job_s']:.1f} s job time -> overhead {r['overhead_pct']:.1f}%")
    except COMMAND_ERRORS as exc:
        return p.fail(exc)
    args.out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(args.out / "dataset_cost.json",
                      {**finish_record(record, start), "config": cfg.to_json(), "rows": rows})
    print(f"wrote {args.out / 'dataset_cost.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
