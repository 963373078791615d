"""Person-readable outputs of a denoising run: report.html (the interactive viewer of
:mod:`pipeline.viewer` with the metrics, timings and settings), comparison PNG with zoomed crops.

The comparison shows the images side by side (noisy | ours | OIDN | reference) and below them
zoomed crops of the regions where our result has the largest error against the reference (or,
without a reference, where it differs most from the noisy input).
"""
from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from imaging.metrics import tonemap
from imaging.png import save_png, to_display
from pipeline.viewer import Page, Table, ViewerRow, ViewerSet, details, flip_map

LABEL_H = 16


def worst_regions(error: np.ndarray, size: int, count: int = 2) -> list[tuple[int, int]]:
    """Top-left corners (y, x) of ``count`` non-overlapping ``size``² windows with the largest
    summed ``error`` (HxW), found on a grid of half-window steps."""
    h, w = error.shape
    size = max(1, min(size, h, w))
    step = max(1, size // 2)
    cand = []
    for y in range(0, max(1, h - size + 1), step):
        for x in range(0, max(1, w - size + 1), step):
            cand.append((float(error[y:y + size, x:x + size].sum()), y, x))
    cand.sort(reverse=True)
    picked: list[tuple[int, int]] = []
    for _, y, x in cand:
        if all(abs(y - py) >= size or abs(x - px) >= size for py, px in picked):
            picked.append((y, x))
        if len(picked) == count:
            break
    return picked


def comparison_image(images: dict[str, np.ndarray], focus: str, against: str,
                     crop: int = 0, zoom_width: int = 0) -> np.ndarray:
    """HxWx3 uint8 sheet: labelled images in a row, then a row of zoomed crops per region.

    ``focus``/``against`` name the two images whose tonemapped difference picks the regions.
    """
    names = list(images)
    h, w = next(iter(images.values())).shape[:2]
    crop = crop or max(8, min(h, w) // 4)
    error = np.abs(tonemap(images[focus]) - tonemap(images[against])).mean(axis=2)
    regions = worst_regions(error, crop)
    zoom = max(1, (zoom_width or w) // max(crop, 1))
    zh = min(crop, h) * zoom
    sheet = Image.new("RGB", (w * len(names), LABEL_H + h + len(regions) * zh), (20, 20, 20))
    draw = ImageDraw.Draw(sheet)
    for i, name in enumerate(names):
        tile = Image.fromarray(to_display(images[name]))
        sheet.paste(tile, (i * w, LABEL_H))
        draw.text((i * w + 3, 2), name, fill=(235, 235, 235))
        for j, (y, x) in enumerate(regions):
            box = (x, y, x + min(crop, w), y + min(crop, h))
            patch = tile.crop(box)
            zoomed = patch.resize((patch.width * zoom, patch.height * zoom), Image.NEAREST)
            sheet.paste(zoomed.crop((0, 0, min(w, zoomed.width), zh)), (i * w, LABEL_H + h + j * zh))
            draw.rectangle((i * w + x, LABEL_H + y, i * w + box[2] - 1, LABEL_H + box[3] - 1),
                           outline=(255, 80, 40))
    return np.asarray(sheet)


LABELS = {"noisy": "noisy", "denoised": "ours", "oidn": "OIDN", "reference": "reference"}
METRIC_COLUMNS = [("psnr", "PSNR dB", "high"), ("ssim", "SSIM", "high"), ("relmse", "relMSE", "low"),
                  ("smape", "SMAPE", "low"), ("flip", "FLIP", "low"), ("hdr_flip", "HDR-FLIP", "low")]


def run_page(metrics: dict[str, Any], images: dict[str, np.ndarray],
             guard_map: np.ndarray | None = None) -> Page:
    """The report of one render-and-denoise run: the viewer over noisy / ours / OIDN / reference
    (+ FLIP maps against the reference, + the noise guard's weight map), the metrics table, the
    run's timings, model and settings. ``images``: name -> HxWx3 linear radiance, names as in
    :data:`LABELS`; ``metrics``: the run's metrics.json dict."""
    w, h = metrics["resolution"]
    model = metrics["model"]
    page = Page(f"{Path(str(metrics['scene'])).name}: denoising report",
                f"{w}x{h} at {metrics['spp']} spp, model {model['name']}, Mitsuba {metrics['mitsuba']} "
                f"({metrics['variant']})")
    reference = images.get("reference")
    ids = {name: page.radiance(img) for name, img in images.items()}
    rows = [ViewerRow(LABELS.get(name, name), ids[name],
                      page.scalar(flip_map(img, reference)) if reference is not None and name != "reference"
                      else None)
            for name, img in images.items()]
    if guard_map is not None:
        rows.append(ViewerRow("noise guard weight", page.scalar(guard_map), kind="weight"))
    page.add_set(ViewerSet(Path(str(metrics["scene"])).stem, rows, ids.get("reference"),
                           "" if reference is not None else "no reference: no error maps"))
    _quality_section(page, metrics)
    _run_section(page, metrics)
    return page


def _quality_section(page: Page, metrics: dict[str, Any]) -> None:
    quality, timings = metrics.get("quality"), metrics["timings"]
    seconds = {"denoised": timings.get("denoise_s"), "oidn": timings.get("oidn_s")}
    note = f"<p class='note'>{html.escape(str(metrics.get('note', '')))}. {html.escape(_oidn_note(metrics))}</p>"
    if not quality:
        stats = metrics.get("stats", {})
        table = Table(["image", "mean", "min", "max", "p99"],
                      [[LABELS.get(n, n), s["mean"], s["min"], s["max"], s["p99"]] for n, s in stats.items()])
        page.add_section("Images (no reference)", note + table.html())
        return
    table = Table(["image", *(label for _, label, _ in METRIC_COLUMNS), "denoise s"],
                  better={label: sense for _, label, sense in METRIC_COLUMNS})
    for name, values in quality.items():
        table.rows.append([LABELS.get(name, name),
                           *(_inf(values.get(key)) for key, _, _ in METRIC_COLUMNS), seconds.get(name)])
    page.add_section("Quality against the reference", note + table.html())


def _inf(value: Any) -> Any:
    return float("inf") if value is None else value  # metrics.json writes an infinite PSNR as null


def _oidn_note(metrics: dict[str, Any]) -> str:
    oidn = metrics.get("oidn") or {}
    return oidn.get("note", "")


def _run_section(page: Page, metrics: dict[str, Any]) -> None:
    model = metrics["model"]
    timings = Table(["step", "seconds"], [[k.removesuffix("_s").replace("_", " "), v]
                                          for k, v in metrics["timings"].items()])
    guard = metrics.get("noise_guard")
    settings = [["scene", metrics["scene"]], ["resolution", "x".join(map(str, metrics["resolution"]))],
                ["spp", metrics["spp"]], ["seed", metrics["seed"]],
                ["reference", _reference_text(metrics.get("reference"))],
                ["model", f"{model['name']} (sha256 {model['sha256'][:12]})"],
                ["Mitsuba", f"{metrics['mitsuba']} {metrics['variant']}"],
                ["noise guard", "off (one-piece render)" if not guard else
                 f"mean weight {guard['mean_weight']:.3f}, strength {guard['strength']:g}, "
                 f"window {2 * guard['radius'] + 1}x{2 * guard['radius'] + 1}"]]
    if metrics.get("budget"):
        b = metrics["budget"]
        settings.append(["time budget", f"{b['budget_s']:g} s: {b['model']} at {b['spp']} spp, "
                                        f"actual {b['actual_s']:.2f} s"])
    body = Table(["setting", "value"], settings).html() + timings.html()
    body += details({"model config": model.get("config"), "sanitized": metrics.get("sanitized"),
                     "render memory": metrics.get("render_memory")})
    page.add_section("Run", body)


def _reference_text(reference: dict[str, Any] | None) -> str:
    if not reference:
        return "none"
    return reference["file"] if "file" in reference else f"rendered at {reference['spp']} spp"


def write_report(out: Path, metrics: dict[str, Any], images: dict[str, np.ndarray],
                 guard_map: np.ndarray | None = None) -> Path:
    """Write ``out/report.html`` (:func:`run_page`), self-contained."""
    return run_page(metrics, images, guard_map).write(out / "report.html")


def write_previews(out: Path, images: dict[str, np.ndarray]) -> list[Path]:
    """Tonemapped PNG of each image: ``out/<name>.png``."""
    paths = []
    for name, img in images.items():
        path = out / f"{name}.png"
        save_png(path, img)
        paths.append(path)
    return paths
