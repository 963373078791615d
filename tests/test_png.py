"""Display images and PNGs written a block of rows at a time: the display values of a whole-image
tonemap, the bytes Pillow writes for the whole image, and numpy's allocations within the blocks."""
from __future__ import annotations

import io
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from imaging.png import PngWriter, save_png, to_display


def pillow_bytes(image: np.ndarray) -> bytes:
    out = io.BytesIO()
    Image.fromarray(image).save(out, format="PNG")
    return out.getvalue()


def whole_display(rgb: np.ndarray) -> np.ndarray:
    """The display values computed on the whole image at once, in float64 (the tonemap of
    imaging.metrics: x/(1+x), gamma 1/2.2, negatives clamped; NaN and +inf -> 0)."""
    x = np.clip(np.nan_to_num(rgb, nan=0.0, posinf=0.0).astype(np.float64), 0.0, None)
    return np.round((x / (1.0 + x)) ** (1.0 / 2.2) * 255.0).astype(np.uint8)


def radiance(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    rgb = (rng.random((h, w, 3)) * 10.0 ** rng.uniform(-3, 3, (h, w, 1))).astype(np.float32)
    rgb.flat[:4] = [np.nan, np.inf, -np.inf, -1.0]
    return rgb


@pytest.mark.parametrize("max_bytes", [1, 2000, 16 * 2**20])
def test_blocked_display_is_the_whole_image_tonemap(rng: np.random.Generator, max_bytes: int) -> None:
    for h, w in ((1, 1), (37, 23), (5, 300)):
        rgb = radiance(rng, h, w)
        assert np.array_equal(to_display(rgb, max_bytes), whole_display(rgb))
    assert np.array_equal(to_display(rgb.astype(np.float64), max_bytes), whole_display(rgb.astype(np.float64)))


def images(rng: np.random.Generator) -> dict[str, np.ndarray]:
    smooth = np.linspace(0, 255, 90 * 70 * 3).reshape(90, 70, 3).astype(np.uint8)
    return {
        "noise (several IDAT chunks)": rng.integers(0, 256, (300, 257, 3), dtype=np.uint8),
        "smooth": smooth,
        "flat": np.full((40, 30, 3), 77, np.uint8),
        "1x1": np.array([[[1, 2, 3]]], np.uint8),
        "grey": rng.integers(0, 256, (64, 33), dtype=np.uint8),
        "rgba": rng.integers(0, 256, (20, 17, 4), dtype=np.uint8),
        "wide rows (IDAT chunks of 4 bytes per pixel)": rng.integers(0, 4, (3, 17000, 3), dtype=np.uint8),
        "textured": (np.cumsum(rng.normal(0, 20, (60, 90, 3)), axis=1) % 256).astype(np.uint8),
    }


@pytest.mark.parametrize("max_bytes", [1, 5000, 16 * 2**20])  # one row per block, a few, the whole
def test_png_bytes_are_pillows(tmp_path: Path, rng: np.random.Generator, max_bytes: int) -> None:
    for name, image in images(rng).items():
        save_png(tmp_path / "x.png", image, max_bytes)
        assert (tmp_path / "x.png").read_bytes() == pillow_bytes(image), name
    rgb = radiance(rng, 41, 29)
    save_png(tmp_path / "r.png", rgb, max_bytes)
    assert (tmp_path / "r.png").read_bytes() == pillow_bytes(whole_display(rgb))
    assert np.array_equal(np.asarray(Image.open(tmp_path / "r.png")), whole_display(rgb))


def test_writer_refuses_missing_and_extra_rows() -> None:
    writer = PngWriter(io.BytesIO(), 4, 3)
    writer.write(np.zeros((2, 4, 3), np.uint8))
    with pytest.raises(ValueError, match="PNG of 3 rows given 5"):
        writer.write(np.zeros((3, 4, 3), np.uint8))
    with pytest.raises(ValueError, match="PNG of 3 rows given 2"):
        writer.close()
    with pytest.raises(ValueError, match="1, 3 or 4 channels"):
        PngWriter(io.BytesIO(), 4, 3, channels=2)


def test_save_png_scratch_stays_within_its_blocks(tmp_path: Path, rng: np.random.Generator) -> None:
    """numpy's (and Python's) allocations while writing a 512x512 float image: its blocks, plus
    the zlib state (~0.4 MB) and a pending IDAT chunk (64 KB), where the whole-image tonemap
    held several 6 MB float64 arrays."""
    rgb = rng.random((512, 512, 3), dtype=np.float32) * 4
    max_bytes = 256 * 2**10
    for image in (rgb, to_display(rgb)):
        save_png(tmp_path / "x.png", image, max_bytes)  # imports and caches before measuring
        tracemalloc.start()
        try:
            save_png(tmp_path / "x.png", image, max_bytes)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < max_bytes + 2**20, (image.dtype, peak)
