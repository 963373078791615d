"""Person-readable outputs of a denoising run: report.html (the interactive viewer of
:mod:`pipeline.viewer` with the metrics, timings and settings), comparison PNG with zoomed crops.

The comparison shows the images side by side (noisy | ours | OIDN colour-only | OIDN + albedo +
normal | reference, each labelled with its file name) and below them
zoomed crops of the regions where our result has the largest error against the reference (or,
without a reference, where it differs most from the noisy input). It is made and written a band
of rows at a time (:func:`write_comparison`), the file the whole sheet gives: the sheet is never
whole in memory, the error map one band of crop-size rows at a time (float64, about 2 bytes per
image pixel with the default crop of a quarter of the shorter side).
"""
from __future__ import annotations

import html
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from imaging.blocks import DEFAULT_BLOCK_BYTES, row_blocks
from imaging.metrics import tonemap
from imaging.png import DISPLAY_BYTES_PER_VALUE, FILTER_BYTES_PER_VALUE, save_png, to_display, write_png_bands
from pipeline.evaluation import OIDN, OIDN_AUX, OIDN_LABELS
from pipeline.viewer import Page, Table, ViewerRow, ViewerSet, details, flip_map

LABEL_H = 16
BACKGROUND, LABEL_COLOUR, BOX_COLOUR = (20, 20, 20), (235, 235, 235), (255, 80, 40)
ERROR_BYTES_PER_PIXEL = 128  # error_rows: float64 tonemaps of two RGB images (96 measured)
SHEET_BYTES_PER_PIXEL = 8 + 3 * FILTER_BYTES_PER_VALUE  # a band: Pillow's RGB, its array, the PNG filter
_FONT = ImageFont.load_default()  # what ImageDraw.text uses when given none


def worst_regions(error: np.ndarray, size: int, count: int = 2) -> list[tuple[int, int]]:
    """Top-left corners (y, x) of ``count`` non-overlapping ``size``² windows with the largest
    summed ``error`` (HxW), found on a grid of half-window steps."""
    h, w = error.shape
    size = max(1, min(size, h, w))
    step = max(1, size // 2)
    cand = [(float(error[y:y + size, x:x + size].sum()), y, x)
            for y in range(0, max(1, h - size + 1), step) for x in range(0, max(1, w - size + 1), step)]
    return _pick(cand, size, count)


def _pick(cand: list[tuple[float, int, int]], size: int, count: int) -> list[tuple[int, int]]:
    cand.sort(reverse=True)
    picked: list[tuple[int, int]] = []
    for _, y, x in cand:
        if all(abs(y - py) >= size or abs(x - px) >= size for py, px in picked):
            picked.append((y, x))
        if len(picked) == count:
            break
    return picked


def error_rows(image: np.ndarray, other: np.ndarray, rows: slice) -> np.ndarray:
    """``rows`` of the comparison's error map: |tonemap(image) - tonemap(other)| averaged over the
    channels, float64 (each pixel's value does not depend on the rows computed with it)."""
    return np.abs(tonemap(image[rows]) - tonemap(other[rows])).mean(axis=2)


def worst_regions_of(image: np.ndarray, other: np.ndarray, size: int, count: int = 2,
                     max_bytes: float = DEFAULT_BLOCK_BYTES) -> list[tuple[int, int]]:
    """:func:`worst_regions` of the error map of ``image`` against ``other`` (:func:`error_rows`)
    without the whole map: one band of ``size`` rows at a time, each window summed over the same
    values with the same shape and strides as in the whole map (so the same sums, bit for bit),
    the band's rows computed in blocks within ``max_bytes``."""
    h, w = image.shape[:2]
    size = max(1, min(size, h, w))
    step = max(1, size // 2)
    band = np.empty((size, w))
    cand, start = [], None
    for y in range(0, max(1, h - size + 1), step):
        keep = 0 if start is None else max(0, start + size - y)  # rows shared with the last band
        band[:keep] = band[size - keep:]
        for rows in row_blocks(size - keep, w, ERROR_BYTES_PER_PIXEL, max_bytes):
            band[keep + rows.start:keep + rows.stop] = error_rows(
                image, other, slice(y + keep + rows.start, y + keep + rows.stop))
        cand += [(float(band[:, x:x + size].sum()), y, x) for x in range(0, max(1, w - size + 1), step)]
        start = y
    return _pick(cand, size, count)


@dataclass(frozen=True)
class _Sheet:
    """Where everything goes on a comparison sheet (:func:`comparison_bands`)."""

    names: list[str]
    h: int
    w: int
    crop: int
    zoom: int
    regions: list[tuple[int, int]]

    @property
    def zh(self) -> int:
        return min(self.crop, self.h) * self.zoom

    @property
    def size(self) -> tuple[int, int]:
        return self.w * len(self.names), LABEL_H + self.h + len(self.regions) * self.zh


def _zoom_rows(image: np.ndarray, sheet: _Sheet, region: tuple[int, int], z0: int, z1: int) -> np.ndarray:
    """Rows ``z0..z1`` of a region's zoomed crop: its pixels repeated ``zoom`` times each way
    (nearest neighbour), black beyond the image, at most ``w`` wide."""
    y, x = region
    zoom, cw = sheet.zoom, min(sheet.crop, sheet.w)
    p0, p1 = z0 // zoom, (z1 - 1) // zoom + 1  # rows of the crop
    patch = np.zeros((p1 - p0, cw, 3), np.uint8)
    inside = image[y + p0:min(sheet.h, y + p1), x:min(sheet.w, x + cw)]
    patch[:len(inside), :inside.shape[1]] = to_display(inside)
    zoomed = np.repeat(np.repeat(patch, zoom, axis=0), zoom, axis=1)
    return zoomed[z0 - p0 * zoom:z1 - p0 * zoom, :min(sheet.w, cw * zoom)]


def _band(images: dict[str, np.ndarray], sheet: _Sheet, r0: int, r1: int) -> np.ndarray:
    """Rows ``r0..r1`` of the sheet: the whole sheet's drawing, in its order, clipped to them
    (what cannot reach them is skipped)."""
    h, w, crop = sheet.h, sheet.w, sheet.crop
    band = Image.new("RGB", (sheet.size[0], r1 - r0), BACKGROUND)
    draw = ImageDraw.Draw(band)
    for i, name in enumerate(sheet.names):
        t0, t1 = max(r0, LABEL_H), min(r1, LABEL_H + h)
        if t0 < t1:
            band.paste(Image.fromarray(to_display(images[name][t0 - LABEL_H:t1 - LABEL_H])), (i * w, t0 - r0))
        _, top, _, bottom = draw.textbbox((i * w + 3, 2), name, font=_FONT)
        if top - 1 < r1 and bottom + 1 > r0:
            draw.text((i * w + 3, 2 - r0), name, fill=LABEL_COLOUR, font=_FONT)
        for j, (y, x) in enumerate(sheet.regions):
            top = LABEL_H + h + j * sheet.zh
            z0, z1 = max(r0, top), min(r1, top + sheet.zh)
            if z0 < z1:
                zoomed = _zoom_rows(images[name], sheet, (y, x), z0 - top, z1 - top)
                band.paste(Image.fromarray(zoomed), (i * w, z0 - r0))
            if LABEL_H + y - 1 < r1 and LABEL_H + y + min(crop, h) + 1 > r0:  # a 1-row box draws 3
                draw.rectangle((i * w + x, LABEL_H + y - r0, i * w + x + min(crop, w) - 1,
                                LABEL_H + y + min(crop, h) - 1 - r0), outline=BOX_COLOUR)
    return np.asarray(band)


def comparison_bands(images: dict[str, np.ndarray], focus: str, against: str, crop: int = 0,
                     zoom_width: int = 0, max_bytes: float = DEFAULT_BLOCK_BYTES
                     ) -> tuple[tuple[int, int], Iterator[np.ndarray]]:
    """The comparison sheet (:func:`comparison_image`) as its (width, height) and its rows, a
    band of uint8 rows at a time in order, each band's temporaries within ``max_bytes`` (at least
    one row): the sheet is never whole in memory. The regions are found first
    (:func:`worst_regions_of`: its band of the error map besides)."""
    names = list(images)
    h, w = next(iter(images.values())).shape[:2]
    crop = crop or max(8, min(h, w) // 4)
    regions = worst_regions_of(images[focus], images[against], crop, max_bytes=max_bytes)
    sheet = _Sheet(names, h, w, crop, max(1, (zoom_width or w) // max(crop, 1)), regions)
    width, height = sheet.size
    per_pixel = SHEET_BYTES_PER_PIXEL + DISPLAY_BYTES_PER_VALUE * 3 / len(names)
    return sheet.size, (_band(images, sheet, rows.start, rows.stop)
                        for rows in row_blocks(height, width, per_pixel, max_bytes))


def comparison_image(images: dict[str, np.ndarray], focus: str, against: str,
                     crop: int = 0, zoom_width: int = 0) -> np.ndarray:
    """HxWx3 uint8 sheet: labelled images in a row, then a row of zoomed crops per region.

    ``focus``/``against`` name the two images whose tonemapped difference picks the regions.
    Whole in memory: :func:`write_comparison` writes it a band of rows at a time.
    """
    _, bands = comparison_bands(images, focus, against, crop, zoom_width)
    return np.concatenate(list(bands))


def write_comparison(path: Path, images: dict[str, np.ndarray], focus: str, against: str,
                     crop: int = 0, zoom_width: int = 0, max_bytes: float = DEFAULT_BLOCK_BYTES) -> Path:
    """Write :func:`comparison_image` as a PNG atomically, a band of rows at a time (the bytes
    :func:`imaging.png.save_png` writes for the whole sheet)."""
    (width, height), bands = comparison_bands(images, focus, against, crop, zoom_width, max_bytes)
    write_png_bands(path, width, height, bands)
    return path


LABELS = {"noisy": "noisy", "denoised": "ours", **OIDN_LABELS, "reference": "reference"}
METRIC_COLUMNS = [("psnr", "PSNR dB", "high"), ("ssim", "SSIM", "high"), ("relmse", "relMSE", "low"),
                  ("smape", "SMAPE", "low"), ("flip", "FLIP", "low"), ("hdr_flip", "HDR-FLIP", "low")]


def run_page(metrics: dict[str, Any], images: dict[str, np.ndarray],
             guard_map: np.ndarray | None = None, max_bytes: float = DEFAULT_BLOCK_BYTES) -> Page:
    """The report of one render-and-denoise run: the viewer over noisy / ours / OIDN colour-only /
    OIDN + albedo + normal / reference (+ FLIP maps against the reference, + the noise guard's
    weight map), the metrics table, the run's timings, model and settings. ``images``: name ->
    HxWx3 linear radiance, names as in :data:`LABELS`; ``metrics``: the run's metrics.json dict.
    Images are embedded a block of rows at a time within ``max_bytes``; the FLIP maps are computed
    on whole images."""
    w, h = metrics["resolution"]
    model = metrics["model"]
    page = Page(f"{Path(str(metrics['scene'])).name}: denoising report",
                f"{w}x{h} at {metrics['spp']} spp, model {model['name']}, Mitsuba {metrics['mitsuba']} "
                f"({metrics['variant']})", max_bytes)
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
    if metrics.get("notes"):
        page.add_section("Notes", "".join(f"<p class='note'>{html.escape(n)}</p>" for n in metrics["notes"]))
    _quality_section(page, metrics)
    _run_section(page, metrics)
    return page


def _quality_section(page: Page, metrics: dict[str, Any]) -> None:
    quality, timings = metrics.get("quality"), metrics["timings"]
    seconds = {"denoised": timings.get("denoise_s"), OIDN: timings.get("oidn_s"),
               OIDN_AUX: timings.get("oidn_aux_s")}
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
                ["model", f"{model['name']} (sha256 {model['sha256'][:12]})"
                          + (f"; ran: {' + '.join(model['models_run'])}" if len(model.get("members", ())) > 1 else "")],
                ["Mitsuba", f"{metrics['mitsuba']} {metrics['variant']}"],
                ["noise guard", "off (one-piece render)" if not guard else
                 f"mean weight {guard['mean_weight']:.3f}, strength {guard['strength']:g}, "
                 f"window {2 * guard['radius'] + 1}x{2 * guard['radius'] + 1}"],
                ["energy correction", "off" if not metrics.get("energy") else
                 f"mean factor {metrics['energy']['mean_factor']:.3f} (1: unchanged)"]]
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
                 guard_map: np.ndarray | None = None, max_bytes: float = DEFAULT_BLOCK_BYTES) -> Path:
    """Write ``out/report.html`` (:func:`run_page`), self-contained."""
    return run_page(metrics, images, guard_map, max_bytes).write(out / "report.html")


def write_previews(out: Path, images: dict[str, np.ndarray],
                   max_bytes: float = DEFAULT_BLOCK_BYTES) -> list[Path]:
    """Tonemapped PNG of each image: ``out/<name>.png`` (:func:`imaging.png.save_png`, a block of
    rows at a time within ``max_bytes``)."""
    paths = []
    for name, img in images.items():
        path = out / f"{name}.png"
        save_png(path, img, max_bytes)
        paths.append(path)
    return paths
