"""PFM and Radiance HDR files: read as Mitsuba reads them, a PFM a block of rows at a time, and
headers that claim more than the file (or the memory left) refused before anything is allocated."""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import imaging.memory_limit
from imaging.bitmap_io import ImageFormatError, read_bitmap, read_bitmap_header, write_bitmap

RGB = (np.arange(5 * 7 * 3, dtype=np.float32).reshape(5, 7, 3) + 1) / 8


def _pfm(path: Path, header: bytes, rows: np.ndarray, dtype: str = "<f4", tail: bytes = b"") -> Path:
    path.write_bytes(header + np.ascontiguousarray(rows[::-1], dtype=dtype).tobytes() + tail)
    return path


@pytest.mark.parametrize("name, header, dtype, expected_scale", [
    ("little.pfm", b"PF\n7 5\n-1.0\n", "<f4", 1.0),
    ("big.pfm", b"PF\n7 5\n1.0\n", ">f4", 1.0),
    ("scaled.pfm", b"PF\n7 5\n-2.5\n", "<f4", 2.5),  # the scale's magnitude multiplies the values
    ("one_line.pfm", b"PF 7 5 -1\n", "<f4", 1.0),
])
def test_pfm_read_as_mitsuba_reads_it(tmp_path: Path, mi: Any, name: str, header: bytes, dtype: str,
                                      expected_scale: float) -> None:
    path = _pfm(tmp_path / name, header, RGB, dtype, tail=b"\n")  # bytes after the pixels are ignored
    ours = read_bitmap(path)
    assert ours.dtype == np.float32 and ours.shape == (5, 7, 3)
    assert np.array_equal(ours, RGB * np.float32(expected_scale))
    assert np.array_equal(ours, np.asarray(mi.Bitmap(str(path))))
    assert np.array_equal(read_bitmap(path, max_bytes=1), ours)  # one row per block


def test_greyscale_pfm_is_three_equal_channels(tmp_path: Path) -> None:
    grey = RGB[..., 0]
    image = read_bitmap(_pfm(tmp_path / "g.pfm", b"Pf\n7 5\n-1.0\n", grey))
    assert np.array_equal(image, np.repeat(grey[..., None], 3, axis=2))


def test_pfm_and_hdr_round_trip_through_mitsubas_writer(tmp_path: Path) -> None:
    write_bitmap(tmp_path / "a.pfm", RGB)
    assert np.array_equal(read_bitmap(tmp_path / "a.pfm"), RGB)
    write_bitmap(tmp_path / "a.hdr", RGB)
    assert read_bitmap_header(tmp_path / "a.hdr").width == 7
    np.testing.assert_allclose(read_bitmap(tmp_path / "a.hdr"), RGB, rtol=1 / 128)  # RGBE: 8-bit mantissas


@pytest.mark.parametrize("content, message", [
    (b"PF\n100000 100000\n-1.0\n" + bytes(4000),
     "header says 100000x100000 pixels (120,000,000,000 bytes), the file holds 4,000 bytes after its header"),
    (b"PF\n7 5\n-1.0\n" + bytes(7 * 5 * 12 - 1), "header says 7x5 pixels (420 bytes), the file holds 419 bytes"),
    (b"Pf\n7 5\n-1.0\n" + bytes(7 * 5 * 4 - 4), "header says 7x5 pixels (140 bytes), the file holds 136"),
    (b"PF\n0 5\n-1.0\n", "image of 0x5 pixels"),
    (b"PF\n7 5\n0\n" + bytes(420), "PFM scale '0' is not a nonzero number"),
    (b"PF\n7 5\nnan\n" + bytes(420), "PFM scale 'nan' is not a nonzero number"),
    (b"PF\n7 x5\n-1\n" + bytes(420), "not a valid PFM header"),
])
def test_lying_or_broken_pfm_headers(tmp_path: Path, content: bytes, message: str) -> None:
    (tmp_path / "x.pfm").write_bytes(content)
    with pytest.raises(ImageFormatError, match="x.pfm: " + re.escape(message)):
        read_bitmap(tmp_path / "x.pfm")


def _rgbe(path: Path, size_line: bytes, body: bytes, fmt: bytes = b"32-bit_rle_rgbe") -> Path:
    path.write_bytes(b"#?RADIANCE\nFORMAT=" + fmt + b"\n\n" + size_line + b"\n" + body)
    return path


@pytest.mark.parametrize("width, least", [(60000, 4 * 60000), (7, 4 * 7), (8, 12), (127, 12), (128, 20),
                                          (1000, 4 + 8 * 8)])
def test_hdr_scanlines_need_their_fewest_bytes(tmp_path: Path, width: int, least: int) -> None:
    """Fewest bytes of a scanline: flat (4 per pixel) outside 8..32767 pixels, else run-length
    encoded: a 4-byte marker and, per component, two bytes per run of at most 127 (by hand)."""
    path = _rgbe(tmp_path / "x.hdr", b"-Y 3 +X %d" % width, bytes(3 * least - 1))
    with pytest.raises(ImageFormatError, match=f"header says {width}x3 pixels \\(at least {3 * least:,} bytes\\), "
                                               f"the file holds {3 * least - 1:,} bytes"):
        read_bitmap(path)
    _rgbe(path, b"-Y 3 +X %d" % width, bytes(3 * least))
    assert read_bitmap_header(path).height == 3


@pytest.mark.parametrize("size_line, fmt, message", [
    (b"-Y 60000 +X 60000", b"32-bit_rle_rgbe", "header says 60000x60000 pixels (at least 14,400,000,000 bytes)"),
    (b"+Y 2 +X 3", b"32-bit_rle_rgbe", "Radiance HDR orientation '+Y 2 +X 3' is not supported"),
    (b"-Y 2 +X 3", b"24-bit_rgb", "Radiance HDR format '24-bit_rgb'"),
    (b"-Y 0 +X 3", b"32-bit_rle_rgbe", "image of 3x0 pixels"),
])
def test_lying_or_unsupported_hdr_headers(tmp_path: Path, size_line: bytes, fmt: bytes, message: str) -> None:
    path = _rgbe(tmp_path / "x.hdr", size_line, bytes(4000), fmt)
    with pytest.raises(ImageFormatError, match="x.hdr: " + re.escape(message)):
        read_bitmap(path)


def test_hdr_header_without_an_image_size(tmp_path: Path) -> None:
    (tmp_path / "x.hdr").write_bytes(b"#?RADIANCE\n" + b"# a comment\n" * 7000)
    with pytest.raises(ImageFormatError, match="x.hdr: no image size in the first 65,536 bytes"):
        read_bitmap(tmp_path / "x.hdr")


def test_images_beyond_the_memory_left_are_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = _pfm(tmp_path / "a.pfm", b"PF\n7 5\n-1.0\n", RGB)
    monkeypatch.setattr(imaging.memory_limit, "available_bytes", lambda: 419)
    with pytest.raises(ImageFormatError, match=r"a.pfm: 7x5 pixels need 420 bytes as float32, more than the "
                                               r"419 bytes of memory available"):
        read_bitmap(path)
    monkeypatch.setattr(imaging.memory_limit, "available_bytes", lambda: 420)
    assert read_bitmap(path).shape == (5, 7, 3)


def test_run_length_encoded_hdr_decodes_as_mitsuba_decodes_it(tmp_path: Path, mi: Any, rng) -> None:
    """Scanlines with runs and literals (flat areas and noise), read in blocks of any size."""
    image = np.repeat(rng.random((6, 20, 3)).astype(np.float32) * 4, 5, axis=0).repeat(3, axis=1)
    image[::4] = rng.random(image[::4].shape).astype(np.float32)
    write_bitmap(tmp_path / "a.hdr", image)
    ours = read_bitmap(tmp_path / "a.hdr")
    assert np.array_equal(ours, np.asarray(mi.Bitmap(str(tmp_path / "a.hdr"))))
    assert np.array_equal(read_bitmap(tmp_path / "a.hdr", max_bytes=1), ours)


def _scanline(width: int, *components: bytes) -> bytes:
    return bytes([2, 2, width >> 8, width & 0xFF]) + b"".join(components)


@pytest.mark.parametrize("body, message", [
    (_scanline(8, bytes([136, 1]) * 3 + bytes([137, 1])), "a run longer than its scanline"),
    (_scanline(8, bytes([0])), "a run of 0 values where 8 remain"),
    (_scanline(8, bytes([9]) + bytes(9)), "a run of 9 values where 8 remain"),
    (_scanline(9, bytes([136, 1]) * 4), "a scanline says 9 pixels, the image 8"),
    (_scanline(8, bytes([136, 1]) * 3 + bytes([8, 1, 2])), "the pixels end early"),
])
def test_corrupt_runs_are_refused(tmp_path: Path, body: bytes, message: str) -> None:
    """Runs that do not fit their scanline (where Mitsuba's decoder writes past its buffer)."""
    path = _rgbe(tmp_path / "x.hdr", b"-Y 1 +X 8", body + bytes(max(0, 12 - len(body))))
    with pytest.raises(ImageFormatError, match="x.hdr: corrupt Radiance HDR pixels \\(" + re.escape(message)):
        read_bitmap(path)


def test_a_flat_scanline_makes_the_rest_flat(tmp_path: Path) -> None:
    """As rgbe.c: a scanline without the run-length marker starts flat pixels to the end."""
    rle = _scanline(8, *(bytes([136, v]) for v in (128, 64, 32, 129)))
    flat = bytes([128, 64, 32, 129]) * 8
    image = read_bitmap(_rgbe(tmp_path / "x.hdr", b"-Y 2 +X 8", rle + flat))
    assert np.array_equal(image, np.broadcast_to(np.float32([1.0, 0.5, 0.25]), (2, 8, 3)))
