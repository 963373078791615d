"""Person-readable outputs of a denoising run: comparison PNG with zoomed crops, report.html.

The comparison shows the images side by side (noisy | ours | OIDN | reference) and below them
zoomed crops of the regions where our result has the largest error against the reference (or,
without a reference, where it differs most from the noisy input).
"""
from __future__ import annotations

import base64
import html
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from pipeline.atomic_io import write_text_atomic
from pipeline.metrics import tonemap
from pipeline.png import save_png, to_display

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


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return "inf" if math.isinf(value) else f"{value:.4g}"
    return html.escape(str(value))


def _png_data_uri(path: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(path.read_bytes()).decode("ascii")


def write_report(out: Path, metrics: dict[str, Any], pngs: list[Path]) -> Path:
    """Write ``out/report.html``: the metrics table and the PNGs embedded (self-contained)."""
    rows = ""
    quality = metrics.get("quality") or {}
    keys = sorted({k for m in quality.values() for k in m})
    if quality:
        rows += "<tr><th>image</th>" + "".join(f"<th>{html.escape(k)}</th>" for k in keys) + "</tr>"
        for name, vals in quality.items():
            rows += f"<tr><td>{html.escape(name)}</td>" + "".join(
                f"<td>{_fmt(vals.get(k, ''))}</td>" for k in keys) + "</tr>"
    pictures = "".join(
        f"<figure><img src='{_png_data_uri(p)}' alt='{html.escape(p.name)}'>"
        f"<figcaption>{html.escape(p.name)}</figcaption></figure>" for p in pngs)
    details = html.escape(json.dumps({k: v for k, v in metrics.items() if k != "quality"},
                                     indent=1, default=str))
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{html.escape(str(metrics.get('scene', 'report')))}</title>
<style>body{{font-family:sans-serif;background:#111;color:#ddd;margin:1.5em}}table{{border-collapse:collapse}}
td,th{{border:1px solid #444;padding:3px 8px;text-align:right}}img{{image-rendering:pixelated;max-width:100%}}
figure{{margin:1em 0}}pre{{background:#1b1b1b;padding:1em;overflow:auto}}</style></head><body>
<h1>{html.escape(str(metrics.get('scene', '')))}</h1>
<p>{html.escape(str(metrics.get('note', '')))}</p>
<table>{rows}</table>{pictures}<h2>Run details</h2><pre>{details}</pre></body></html>"""
    path = out / "report.html"
    write_text_atomic(path, page)
    return path


def write_previews(out: Path, images: dict[str, np.ndarray]) -> list[Path]:
    """Tonemapped PNG of each image: ``out/<name>.png``."""
    paths = []
    for name, img in images.items():
        path = out / f"{name}.png"
        save_png(path, img)
        paths.append(path)
    return paths
