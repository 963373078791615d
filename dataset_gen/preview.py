"""Contact sheet of a dataset: reference thumbnails labelled with scene and family."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from dataset_gen.jobs import IMAGES_DIR
from imaging.exr import read_exr
from imaging.naming import image_name
from imaging.png import save_png, to_display

PREVIEW_NAME = "preview.png"


def contact_sheet(folder: Path, records: list[dict[str, Any]], columns: int = 8, limit: int = 48,
                  thumb: int = 128) -> Path:
    """Write ``folder/preview.png``: up to ``limit`` scenes, noisy (lowest spp) above reference.

    Scenes are picked round-robin over families so each family shows.
    """
    if not records:
        raise ValueError("no finished scenes to preview")
    by_family: dict[str, list[dict[str, Any]]] = {}
    for rec in records:
        by_family.setdefault(rec["family"], []).append(rec)
    picked: list[dict[str, Any]] = []
    while len(picked) < min(limit, len(records)):
        for recs in by_family.values():
            if recs and len(picked) < limit:
                picked.append(recs.pop(0))
    rows = -(-len(picked) // columns)
    cell_h = 2 * thumb + 14
    sheet = Image.new("RGB", (columns * thumb, rows * cell_h), (24, 24, 24))
    draw = ImageDraw.Draw(sheet)
    for i, rec in enumerate(picked):
        x, y = (i % columns) * thumb, (i // columns) * cell_h
        low = min(rec["spp"])
        for j, spp in enumerate((low, None)):
            img = read_exr(folder / IMAGES_DIR / image_name(rec["index"], spp)).rgb
            tile = Image.fromarray(to_display(img)).resize((thumb, thumb), Image.BILINEAR)
            sheet.paste(tile, (x, y + j * thumb))
        draw.text((x + 2, y + 2 * thumb), f"{rec['scene']} {rec['family']}", fill=(230, 230, 230))
    out = folder / PREVIEW_NAME
    save_png(out, np.asarray(sheet))
    return out
