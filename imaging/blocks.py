"""Whole-image passes a block of rows at a time, so their scratch memory does not grow with the image.

The output stages (EXR and PNG writing, display tonemapping, metrics, the report) walk an image
in horizontal blocks: :func:`row_blocks` picks as many rows per block as ``max_bytes`` allows for
a pass that costs ``bytes_per_pixel`` of temporaries, and at least one.
"""
from __future__ import annotations

from collections.abc import Iterator

DEFAULT_BLOCK_BYTES = 16 * 2**20  # a block's temporaries: a small part of any memory budget


def block_rows(width: int, bytes_per_pixel: float, max_bytes: float, most: int) -> int:
    """Rows per block of a pass costing ``bytes_per_pixel`` of scratch: as many as ``max_bytes``
    allows, at least 1, at most ``most`` (at least 1)."""
    return max(1, min(max(1, most), int(max_bytes // (bytes_per_pixel * max(1, width)))))


def row_blocks(height: int, width: int, bytes_per_pixel: float,
               max_bytes: float = DEFAULT_BLOCK_BYTES) -> Iterator[slice]:
    """Slices covering rows ``0..height`` in order, each within ``max_bytes`` of a pass costing
    ``bytes_per_pixel`` (at least one row each)."""
    rows = block_rows(width, bytes_per_pixel, max_bytes, height)
    for y in range(0, height, rows):
        yield slice(y, min(height, y + rows))
