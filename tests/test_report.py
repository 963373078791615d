"""The comparison sheet made a band of rows at a time: the regions and the pixels the whole-image
sheet has, the PNG bytes Pillow writes for it, numpy's allocations within the bands."""
from __future__ import annotations

import io
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageDraw

from imaging.metrics import tonemap
from pipeline.report import (LABEL_H, comparison_bands, comparison_image, worst_regions, worst_regions_of,
                             write_comparison)


def whole_sheet(images: dict[str, np.ndarray], focus: str, against: str, crop: int = 0,
                zoom_width: int = 0) -> np.ndarray:
    """The sheet drawn whole, as comparison_image did before it was made in bands."""
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
        x = np.clip(np.nan_to_num(images[name], nan=0.0, posinf=0.0).astype(np.float64), 0.0, None)
        tile = Image.fromarray(np.round((x / (1.0 + x)) ** (1.0 / 2.2) * 255.0).astype(np.uint8))
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


def run_images(rng: np.random.Generator, h: int, w: int, count: int = 2) -> dict[str, np.ndarray]:
    base = (rng.random((h, w, 3)) * 3).astype(np.float32)
    images = {"noisy": base + rng.random((h, w, 3)).astype(np.float32) * 2}
    for name in ("denoised", "oidn", "reference")[:count - 1]:
        images[name] = base + rng.random((h, w, 3)).astype(np.float32) * 0.1
    return images


CASES = [(40, 64, 2, {}), (33, 17, 4, {}), (1, 1, 2, {}),
         (6, 4, 2, {}), (4, 6, 3, {}),  # crop wider than the image: black beyond it, as Pillow crops
         (50, 50, 2, {"crop": 7}), (30, 90, 2, {"crop": 40}), (64, 48, 3, {"zoom_width": 20})]


@pytest.mark.parametrize("h, w, count, options", CASES)
def test_sheet_in_bands_is_the_whole_sheet(tmp_path: Path, rng: np.random.Generator, h: int, w: int,
                                           count: int, options: dict) -> None:
    images = run_images(rng, h, w, count)
    expected = whole_sheet(images, "denoised", "noisy", **options)
    error = np.abs(tonemap(images["denoised"]) - tonemap(images["noisy"])).mean(axis=2)
    crop = options.get("crop") or max(8, min(h, w) // 4)
    assert worst_regions_of(images["denoised"], images["noisy"], crop, max_bytes=1) == worst_regions(error, crop)
    for max_bytes in (1, 20000, 16 * 2**20):  # one row per band, a few, the whole sheet
        (width, height), bands = comparison_bands(images, "denoised", "noisy", max_bytes=max_bytes, **options)
        assert np.array_equal(np.concatenate(list(bands)), expected)
        assert (height, width) == expected.shape[:2]
        write_comparison(tmp_path / "c.png", images, "denoised", "noisy", max_bytes=max_bytes, **options)
        png = io.BytesIO()
        Image.fromarray(expected).save(png, format="PNG")
        assert (tmp_path / "c.png").read_bytes() == png.getvalue()
    assert np.array_equal(comparison_image(images, "denoised", "noisy", **options), expected)


def test_sheet_scratch_stays_within_its_bands(tmp_path: Path, rng: np.random.Generator) -> None:
    """numpy's allocations while writing the sheet of two 512x512 images (the whole sheet: 1024 x
    1552 pixels): a band, plus one band of the error map (crop 128 rows x 512 x float64)."""
    images = run_images(rng, 512, 512)
    max_bytes = 256 * 2**10
    write_comparison(tmp_path / "c.png", images, "denoised", "noisy", max_bytes=max_bytes)
    tracemalloc.start()
    try:
        write_comparison(tmp_path / "c.png", images, "denoised", "noisy", max_bytes=max_bytes)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < max_bytes + 128 * 512 * 8 + 2**20
