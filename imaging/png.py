"""Display images: tonemapped 8-bit sRGB-ish PNGs of linear radiance (x/(1+x), gamma 1/2.2),
tonemapped and written a block of rows at a time.

:class:`PngWriter` takes an 8-bit image (grey, RGB or RGBA) in blocks of rows and writes the
bytes Pillow's ``Image.save(path, "PNG")`` writes for the whole image: each row's filter chosen as
Pillow's encoder chooses it (the least sum of |filtered byte as a signed byte| among none, up,
sub and Paeth, tried in that order, a later one taken only when strictly better), zlib at Pillow's
settings (default level, 15-bit window, memory level 9, filtered strategy) and IDAT chunks of
Pillow's buffer size. Neither the 8-bit image nor Pillow's copy of it is ever whole in memory.
"""
from __future__ import annotations

import struct
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np
from PIL import Image

from imaging.atomic_io import atomic_path
from imaging.blocks import DEFAULT_BLOCK_BYTES, row_blocks
from imaging.metrics import tonemap

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
DISPLAY_BYTES_PER_VALUE = 32  # _display_block: float64 temporaries of the tonemap (24 measured)
FILTER_BYTES_PER_VALUE = 32  # PngWriter: the filter candidates of a block (20 measured)
_COLOR_TYPES = {1: 0, 3: 2, 4: 6}  # channels -> PNG colour type (grey, RGB, RGBA)
_PILLOW_BLOCK = 65536  # PIL.ImageFile.MAXBLOCK: the least IDAT chunk Pillow writes


def _display_block(values: np.ndarray) -> np.ndarray:
    """Linear radiance -> uint8 display values (NaN and +inf -> 0), the tonemap in float64 as
    :func:`imaging.metrics.tonemap` computes it."""
    return np.round(tonemap(np.nan_to_num(values, nan=0.0, posinf=0.0)) * 255.0).astype(np.uint8)


def _value_width(image: np.ndarray) -> int:
    """Values per row of an image (W x channels)."""
    return int(np.prod(image.shape[1:], dtype=np.int64)) if image.ndim > 1 else 1


def display_blocks(rgb: np.ndarray, max_bytes: float = DEFAULT_BLOCK_BYTES) -> Iterator[np.ndarray]:
    """:func:`to_display` of ``rgb`` a block of rows at a time, in order (each within ``max_bytes``)."""
    for rows in row_blocks(len(rgb), _value_width(rgb), DISPLAY_BYTES_PER_VALUE, max_bytes):
        yield _display_block(rgb[rows])


def to_display(rgb: np.ndarray, max_bytes: float = DEFAULT_BLOCK_BYTES) -> np.ndarray:
    """HxWx3 linear radiance (>=0) -> HxWx3 uint8 with the metrics' tonemap, computed a block of
    rows at a time (the temporaries within ``max_bytes``)."""
    rgb = np.asarray(rgb)
    if rgb.ndim == 0:
        return _display_block(rgb)
    out = np.empty(rgb.shape, np.uint8)
    y = 0
    for block in display_blocks(rgb, max_bytes):
        out[y:y + len(block)] = block
        y += len(block)
    return out


def _chunk(fh: BinaryIO, kind: bytes, data: bytes | bytearray | memoryview = b"") -> None:
    fh.write(struct.pack(">I", len(data)) + kind)
    fh.write(data)
    fh.write(struct.pack(">I", zlib.crc32(data, zlib.crc32(kind)) & 0xFFFFFFFF))


def _cost(filtered: np.ndarray) -> np.ndarray:
    """Per row: the sum of |byte read as a signed byte| (Pillow's and libpng's filter heuristic)."""
    v = filtered.astype(np.int16)
    return np.minimum(v, 256 - v).sum(axis=1, dtype=np.int64)


def filter_rows(raw: np.ndarray, above: np.ndarray, bpp: int) -> np.ndarray:
    """(n, 1 + B) uint8: each of the n rows of ``raw`` (n x B bytes) behind its PNG filter byte,
    the filter chosen as Pillow chooses it (module notes); ``above``: the B bytes of the row above
    the first (zeros for an image's first row); ``bpp``: bytes per pixel."""
    up = np.concatenate([above[None], raw[:-1]])
    left, up_left = np.zeros_like(raw), np.zeros_like(raw)
    left[:, bpp:], up_left[:, bpp:] = raw[:, :-bpp], up[:, :-bpp]
    a, b, c = (x.astype(np.int16) for x in (left, up, up_left))
    pa, pb, pc = np.abs(b - c), np.abs(a - c), np.abs(a + b - 2 * c)
    paeth = raw - np.where((pa <= pb) & (pa <= pc), a, np.where(pb <= pc, b, c)).astype(np.uint8)
    del a, b, c, pa, pb, pc, up_left
    best, kind, cost = raw, np.zeros(len(raw), np.uint8), _cost(raw)
    for code, candidate in ((2, raw - up), (1, raw - left), (4, paeth)):
        candidate_cost = _cost(candidate)
        better = candidate_cost < cost
        best = np.where(better[:, None], candidate, best)
        kind[better], cost[better] = code, candidate_cost[better]
    return np.concatenate([kind[:, None], best], axis=1)


class PngWriter:
    """An 8-bit PNG written a block of rows at a time to ``fh`` (module notes): :meth:`write`
    the rows in order, then :meth:`close`, which checks all ``height`` rows came."""

    def __init__(self, fh: BinaryIO, width: int, height: int, channels: int = 3) -> None:
        if channels not in _COLOR_TYPES:
            raise ValueError(f"a PNG has 1, 3 or 4 channels, not {channels}")
        self.fh, self.width, self.height, self.channels = fh, width, height, channels
        self.rows = 0
        self._above = np.zeros(width * channels, np.uint8)
        self._zlib = zlib.compressobj(zlib.Z_DEFAULT_COMPRESSION, zlib.DEFLATED, 15, 9, zlib.Z_FILTERED)
        self._pending = bytearray()
        self._chunk_size = max(_PILLOW_BLOCK, width * 4)  # Pillow's encoder buffer: one IDAT each
        fh.write(PNG_MAGIC)
        _chunk(fh, b"IHDR", struct.pack(">IIBBBBB", width, height, 8, _COLOR_TYPES[channels], 0, 0, 0))

    def write(self, rows: np.ndarray) -> None:
        """The next rows: (n, W, channels) or, for grey, (n, W) uint8."""
        raw = np.asarray(rows, np.uint8).reshape(len(rows), self.width * self.channels)
        if self.rows + len(raw) > self.height:
            raise ValueError(f"PNG of {self.height} rows given {self.rows + len(raw)}")
        if not len(raw):
            return
        self._pending += self._zlib.compress(filter_rows(raw, self._above, self.channels))
        self._above = raw[-1].copy()
        self.rows += len(raw)
        self._emit(final=False)

    def _emit(self, final: bool) -> None:
        start = 0
        while len(self._pending) - start >= self._chunk_size:
            _chunk(self.fh, b"IDAT", memoryview(self._pending)[start:start + self._chunk_size])
            start += self._chunk_size
        if final and start < len(self._pending):
            _chunk(self.fh, b"IDAT", memoryview(self._pending)[start:])
            start = len(self._pending)
        del self._pending[:start]

    def close(self) -> None:
        """Finish the file; raises ValueError unless every row was written."""
        if self.rows != self.height:
            raise ValueError(f"PNG of {self.height} rows given {self.rows}")
        self._pending += self._zlib.flush()
        self._emit(final=True)
        _chunk(self.fh, b"IEND")


def save_png(path: str | Path, image: np.ndarray, max_bytes: float = DEFAULT_BLOCK_BYTES) -> None:
    """Write an HxWx3 image atomically: uint8 as is, float as linear radiance (tonemapped), a
    block of rows at a time (:class:`PngWriter`; HxW grey and HxWx4 too)."""
    image = np.asarray(image)
    channels = 1 if image.ndim == 2 else image.shape[2] if image.ndim == 3 else 0
    if channels not in _COLOR_TYPES or min(image.shape) == 0:
        data = image if image.dtype == np.uint8 else to_display(image)
        with atomic_path(path) as tmp:  # what Pillow makes of other shapes (or refuses)
            Image.fromarray(data).save(tmp, format="PNG")
        return
    height, width = image.shape[:2]
    per_value = FILTER_BYTES_PER_VALUE + (0 if image.dtype == np.uint8 else DISPLAY_BYTES_PER_VALUE)
    convert = (lambda block: block) if image.dtype == np.uint8 else _display_block
    bands = (convert(image[rows]) for rows in row_blocks(height, width * channels, per_value, max_bytes))
    write_png_bands(path, width, height, bands, channels)


def write_png_bands(path: str | Path, width: int, height: int, bands: Iterable[np.ndarray], channels: int = 3) -> None:
    """Write a PNG atomically from its uint8 rows, given a band of rows at a time in order
    (:class:`PngWriter`)."""
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        writer = PngWriter(fh, width, height, channels)
        for band in bands:
            writer.write(band)
        writer.close()
