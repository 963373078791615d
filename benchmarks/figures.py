"""The README's two pictures, made from a run and the result files.

* ``strip``: one eval scene rendered as ``render-and-denoise`` renders it (two halves, ``--spp``,
  seed 7), denoised by the default model, by OIDN colour-only and by OIDN with the albedo and normals
  of an AOV pass (:func:`pipeline.evaluation.with_aovs`); a crop of the noisy render, ours, both
  OIDNs' and the 2048-spp reference side by side, each labelled with its PSNR on the whole image
  (``docs/figures/strip.png``; the figures in ``benchmarks/results/figures.json``).
* ``tradeoff``: PSNR on the eval scenes at 4, 16 and 128 spp against time as a multiple of OIDN's
  at that spp, one point per registry entry and OIDN colour-only, and OIDN + albedo + normal's PSNR as a
  dashed line (its time is not in the inference benchmark; ``docs/figures/quality_time.png``), from
  ``benchmarks/results/evaluate.json`` and ``benchmarks/results/inference.json`` (its 1280x720 row).

    python -m benchmarks.figures [strip|tradeoff|all] [--scene NAME] [--spp N] [--crop X,Y,SIZE]
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.eval_scenes import EVAL_DIR, RESULTS, eval_scenes, finish_record, run_record
from console.usage import COMMAND_ERRORS, OneLineParser, int_list, positive_int
from imaging.atomic_io import write_json_atomic
from imaging.metrics import psnr, tonemap
from model.registry import CARD_SPP, registry

ROOT = Path(__file__).resolve().parents[1]
FIGURES = ROOT / "docs" / "figures"
STRIP = FIGURES / "strip.png"
TRADEOFF = FIGURES / "quality_time.png"
TIME_SIZE = "1280x720"
OIDN_AUX_LABEL = "OIDN + alb + nrm"


def strip(scene_name: str, spp: int, crop: tuple[int, int, int], out: Path = STRIP) -> dict[str, Any]:
    """Render, denoise, crop and label (see the module docstring); returns the figures."""
    from PIL import Image, ImageDraw

    from denoise.denoiser import Denoiser
    from pipeline.evaluation import denoise_output, oidn_output, render_input, with_aovs

    scene = eval_scenes([scene_name], EVAL_DIR)[0]
    settings = scene.settings()
    loaded = settings.load()
    render, _ = with_aovs(render_input(loaded, spp, settings), loaded, settings)
    reference = scene.reference()
    denoiser = Denoiser(None)
    ours = denoise_output(render, denoiser).image
    panels = [("noisy", render.rgb), (f"ours ({denoiser.name})", ours), ("OIDN", oidn_output(render).image),
              (OIDN_AUX_LABEL, oidn_output(render, aux=True).image), ("reference", reference)]
    x, y, size = crop
    scale = max(1, 256 // size)
    tiles, figures = [], {}
    for label, image in panels:
        value = psnr(image, reference) if label != "reference" else None
        figures[label] = value
        rgb = (tonemap(image[y:y + size, x:x + size]) * 255 + 0.5).clip(0, 255).astype(np.uint8)
        tile = Image.fromarray(rgb).resize((size * scale, size * scale), Image.NEAREST)
        draw = ImageDraw.Draw(tile)
        text = label if value is None else f"{label} {value:.2f} dB"
        draw.rectangle((0, 0, tile.width, 14), fill=(0, 0, 0))
        draw.text((3, 2), text, fill=(255, 255, 255))
        tiles.append(tile)
    sheet = Image.new("RGB", (sum(t.width for t in tiles) + 4 * (len(tiles) - 1), tiles[0].height), (255, 255, 255))
    left = 0
    for tile in tiles:
        sheet.paste(tile, (left, 0))
        left += tile.width + 4
    out.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(out)
    return {"scene": scene_name, "spp": spp, "crop": list(crop), "model": denoiser.name, "psnr_db": figures,
            "file": str(out.relative_to(ROOT))}


def tradeoff_points(evaluate: dict[str, Any], inference: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Per registry entry (and OIDN colour-only): PSNR and time over OIDN's at 1280x720, at each card
    spp; OIDN + albedo + normal ("OIDN + alb + nrm"): its PSNR only."""
    scored = evaluate["summary"]["scored"]
    ratios = inference["ratios"][TIME_SIZE]
    points = {}
    for name in registry().entries:
        if any(str(s) not in ratios.get(name, {}) or name not in scored[str(s)]["models"] for s in CARD_SPP):
            continue
        points[name] = {"psnr": {str(s): scored[str(s)]["models"][name]["psnr"] for s in CARD_SPP},
                        "time_ratio": {str(s): ratios[name][str(s)] for s in CARD_SPP}}
    points["OIDN"] = {"psnr": {str(s): scored[str(s)]["oidn_psnr"] for s in CARD_SPP},
                      "time_ratio": {str(s): 1.0 for s in CARD_SPP}}
    if all("oidn_aux_psnr" in scored[str(s)] for s in CARD_SPP):
        points[OIDN_AUX_LABEL] = {"psnr": {str(s): scored[str(s)]["oidn_aux_psnr"] for s in CARD_SPP}}
    return points


def plot_tradeoff(points: dict[str, dict[str, Any]], out: Path = TRADEOFF) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(CARD_SPP), figsize=(9, 2.8), constrained_layout=True)
    for ax, spp in zip(axes, CARD_SPP):
        # models that run the same networks at this spp (the same PSNR) share a point at their mean time
        groups: dict[float, list[str]] = {}
        for name, p in points.items():
            if "time_ratio" not in p:  # quality only: a level line across the panel
                ax.axhline(p["psnr"][str(spp)], color="0.4", linestyle="--", linewidth=0.8)
                ax.annotate(name, (0, p["psnr"][str(spp)]), xycoords=("axes fraction", "data"),
                            textcoords="offset points", xytext=(3, 3), fontsize=7, color="0.3")
                continue
            groups.setdefault(round(p["psnr"][str(spp)], 4), []).append(name)
        for psnr_db, names in groups.items():
            oidn = names == ["OIDN"]
            xy = (float(np.mean([points[n]["time_ratio"][str(spp)] for n in names])), psnr_db)
            ax.plot(*xy, "s" if oidn else "o", color="0.4" if oidn else f"C{list(points).index(names[0])}")
            ax.annotate(" = ".join(names), xy, textcoords="offset points", xytext=(4, 3), fontsize=8)
        ax.set_title(f"{spp} spp", fontsize=9)
        ax.set_xlabel(f"time / OIDN's ({TIME_SIZE})", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.margins(0.25)
    axes[0].set_ylabel("PSNR dB (eval scenes)", fontsize=8)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = OneLineParser(prog="python -m benchmarks.figures", description=__doc__.split("\n")[0])
    p.add_argument("which", nargs="?", choices=("strip", "tradeoff", "all"), default="all")
    p.add_argument("--scene", default="bitterli_veach_mis",  # CC0: the picture may ship under our licence
                   help="eval scene of the strip")
    p.add_argument("--spp", type=positive_int, default=16)
    p.add_argument("--crop", type=int_list, default=(80, 40, 96), help="X,Y,SIZE of the strip's crop")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if len(args.crop) != 3:
        p.error("--crop takes X,Y,SIZE")
    record = run_record("benchmarks.figures", sys.argv[1:] if argv is None else argv)
    start = time.perf_counter()
    try:
        if args.which in ("strip", "all"):
            record["strip"] = strip(args.scene, args.spp, tuple(args.crop))
        if args.which in ("tradeoff", "all"):
            points = tradeoff_points(json.loads((RESULTS / "evaluate.json").read_text()),
                                     json.loads((RESULTS / "inference.json").read_text()))
            plot_tradeoff(points)
            record["tradeoff"] = {"points": points, "file": str(TRADEOFF.relative_to(ROOT))}
    except COMMAND_ERRORS as exc:
        return p.fail(exc)
    out = RESULTS / "figures.json"
    if out.is_file():  # keep the other picture's record when one is remade
        record = {**json.loads(out.read_text()), **record}
    write_json_atomic(out, finish_record(record, start))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
