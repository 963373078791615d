"""What generating a dataset costs here: scenes/hour, Mitsuba render time vs wall time, overhead,
and 1 vs 2 parallel scene jobs.

Usage: python benchmarks/dataset_cost.py [--scenes 4] [--res 128] [--ref-spp 1024] [--workers 1,2]
Prints a table and writes benchmarks/results/dataset_cost.json. Each setting renders the same scenes
into its own temporary folder.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

from dataset_gen.config import DatasetConfig
from dataset_gen.generate import generate_dataset
from scenes.registry import FAMILIES


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenes", type=int, default=len(FAMILIES))
    p.add_argument("--res", type=int, default=128)
    p.add_argument("--spp", default="4,16,64,128")
    p.add_argument("--ref-spp", type=int, default=1024)
    p.add_argument("--workers", default="1,2")
    args = p.parse_args()
    cfg = DatasetConfig(res=(args.res, args.res), spp=tuple(int(s) for s in args.spp.split(",")),
                        ref_spp=args.ref_spp, families=tuple(FAMILIES), seed=12345)
    rows = []
    for workers in (int(w) for w in args.workers.split(",")):
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            s = generate_dataset(Path(tmp) / "d", cfg, args.scenes, workers)
            wall = time.perf_counter() - start
        rows.append({"workers": workers, "scenes": s.done, "wall_s": wall,
                     "scenes_per_hour": 3600 * s.done / wall, "render_s": s.render_s,
                     "job_s": s.job_s, "overhead_pct": 100 * s.overhead(),
                     "msamples_per_s": s.samples / wall / 1e6})
        r = rows[-1]
        print(f"workers {workers}: {r['scenes']} scenes in {wall:.1f} s = {r['scenes_per_hour']:.0f}"
              f" scenes/h, {r['msamples_per_s']:.2f} Msamples/s; Mitsuba render {s.render_s:.1f} s"
              f" of {s.job_s:.1f} s job time -> overhead {r['overhead_pct']:.1f}%")
    result = {"config": cfg.to_json(), "cpus": os.cpu_count(), "machine": platform.machine(),
              "rows": rows}
    out = Path(__file__).resolve().parent / "results" / "dataset_cost.json"
    out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
