"""PFM and Radiance HDR (RGBE) images: headers checked against the file before any pixel is allocated.

Images are HxWx3 float32 linear radiance. A greyscale PFM (``Pf``) is read as three equal
channels. :func:`image_format` tells the formats apart by their first bytes, not by name.

Before reading pixels, :func:`read_bitmap_header` parses the header and compares what it claims
with the file: a PFM's pixels are uncompressed (width x height x channels float32 values after
the header, rows bottom to top, the sign of the scale giving the byte order, its magnitude a
factor on every value, as Mitsuba reads it); a run-length encoded RGBE scanline takes at least
4 + 8 ceil(W/127) bytes (four components of runs of at most 127 values, two bytes each) or 4 W
flat. A header claiming more than the file can hold, or pixels that do not fit in the memory
left (:mod:`imaging.memory_limit`), is an :class:`ImageFormatError` naming both sizes. Pixels are
read a block of rows at a time into the image; RGBE scanlines are decoded here, every run checked
against its scanline (Mitsuba's decoder writes past its buffer on some corrupt runs). Files are
written through ``mi.Bitmap``.
"""
from __future__ import annotations

import math
import mmap
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from imaging.atomic_io import atomic_path
from imaging.blocks import DEFAULT_BLOCK_BYTES, row_blocks
from imaging.errors import DenoiserError
from imaging.exr_header import EXR_MAGIC, read_exr_header
from imaging.memory_limit import fits_in_memory, megabytes
from imaging.output_paths import output_format

FORMATS = ("exr", "pfm", "hdr")
MAX_HEADER_BYTES = 65536  # a PFM or RGBE header longer than this is not one
RGB_BYTES_PER_PIXEL = 12  # the HxWx3 float32 image a reader returns
RGBE_BYTES_PER_PIXEL = 4 + 4 + 12 + 12  # a block's RGBE bytes, exponents, scale and float product
_PFM_HEADER = re.compile(rb"(P[Ff])\s+(\d{1,12})\s+(\d{1,12})\s+(\S{1,64})\s")
_RGBE_SIZE = re.compile(rb"([-+][XY]) (\d{1,12}) ([-+][XY]) (\d{1,12})")
_RGBE_FORMATS = (b"32-bit_rle_rgbe", b"32-bit_rle_xyze")


class ImageFormatError(DenoiserError):
    """An image file that is not one of the formats read here, or cannot be read or written."""


@dataclass(frozen=True)
class BitmapHeader:
    """A PFM or RGBE header: ``data_offset`` where the pixels start; PFM: ``channels`` (3 or 1),
    ``scale`` (its magnitude multiplies the values) and ``big_endian``."""

    path: str
    format: str
    width: int
    height: int
    data_offset: int
    channels: int = 3
    scale: float = 1.0
    big_endian: bool = False

    @property
    def image_bytes(self) -> int:
        """Bytes of the HxWx3 float32 image the file is read into."""
        return self.width * self.height * RGB_BYTES_PER_PIXEL


def image_format(path: str | Path) -> str:
    """``exr``, ``pfm`` or ``hdr`` from the file's first bytes; raises :class:`ImageFormatError`
    (naming the file) for a missing file, a folder or anything else."""
    path = Path(path)
    if not path.exists():
        raise ImageFormatError(f"{path}: file not found")
    if path.is_dir():
        raise ImageFormatError(f"{path}: is a directory, not an image file")
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
    except OSError as exc:
        raise ImageFormatError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if head.startswith(EXR_MAGIC):
        return "exr"
    if head[:2] in (b"PF", b"Pf") and head[2:3].isspace():
        return "pfm"
    if head.startswith((b"#?RADIANCE", b"#?RGBE")):
        return "hdr"
    raise ImageFormatError(f"{path}: not an OpenEXR file (nor PFM or Radiance HDR)")


def _pfm_header(path: Path, head: bytes, size: int) -> BitmapHeader:
    m = _PFM_HEADER.match(head)
    if m is None:
        raise ImageFormatError(f"{path}: not a valid PFM header (expected 'PF' or 'Pf', width, height, scale)")
    width, height = int(m[2]), int(m[3])
    try:
        scale = float(m[4])
    except ValueError:
        scale = math.nan
    if not (math.isfinite(scale) and scale != 0):
        raise ImageFormatError(f"{path}: PFM scale {m[4].decode('latin-1')!r} is not a nonzero number")
    channels = 3 if m[1] == b"PF" else 1
    header = BitmapHeader(str(path), "pfm", width, height, m.end(), channels, abs(scale), scale > 0)
    need, holds = width * height * channels * 4, size - m.end()
    _check_size(header, need, holds, "")
    return header


def _rgbe_scanline_bytes(width: int) -> int:
    """The fewest bytes an RGBE scanline of ``width`` pixels takes (module notes)."""
    flat = 4 * width
    return min(flat, 4 + 4 * 2 * -(-width // 127)) if 8 <= width <= 0x7FFF else flat


def _rgbe_header(path: Path, head: bytes, size: int) -> BitmapHeader:
    fmt, pos = None, head.index(b"\n") + 1 if b"\n" in head else len(head)
    while True:
        end = head.find(b"\n", pos)
        if end < 0:
            raise ImageFormatError(f"{path}: no image size in the first {MAX_HEADER_BYTES:,} bytes of the "
                                   "Radiance HDR header")
        line = head[pos:end].strip()
        pos = end + 1
        if line.startswith(b"FORMAT="):
            fmt = line[len(b"FORMAT="):]
        elif _RGBE_SIZE.fullmatch(line):
            break
    if fmt not in _RGBE_FORMATS:
        raise ImageFormatError(f"{path}: Radiance HDR format {fmt.decode('latin-1') if fmt else 'missing'!r} "
                               f"(expected {_RGBE_FORMATS[0].decode()})")
    m = _RGBE_SIZE.fullmatch(line)
    if (m[1], m[3]) != (b"-Y", b"+X"):
        raise ImageFormatError(f"{path}: Radiance HDR orientation {line.decode('latin-1')!r} is not "
                               "supported (only -Y H +X W, rows from the top)")
    height, width = int(m[2]), int(m[4])
    header = BitmapHeader(str(path), "hdr", width, height, pos)
    _check_size(header, height * _rgbe_scanline_bytes(width) if width and height else 0, size - pos,
                "at least ")
    return header


def _check_size(header: BitmapHeader, need: int, holds: int, least: str) -> None:
    """Refuse an empty image, pixels the file cannot hold, or an image the memory left cannot."""
    path, w, h = header.path, header.width, header.height
    if w < 1 or h < 1:
        raise ImageFormatError(f"{path}: image of {w}x{h} pixels")
    if need > holds:
        raise ImageFormatError(f"{path}: header says {w}x{h} pixels ({least}{need:,} bytes), the file "
                               f"holds {max(0, holds):,} bytes after its header (truncated or not an image)")
    fits, room = fits_in_memory(header.image_bytes)
    if not fits:
        raise ImageFormatError(f"{path}: {w}x{h} pixels need {megabytes(header.image_bytes)} as float32, "
                               f"more than the {megabytes(room)} of memory available")


def read_bitmap_header(path: str | Path) -> BitmapHeader:
    """The header of a PFM or Radiance HDR file, checked against the file and the memory left
    (module notes); raises :class:`ImageFormatError` naming the file."""
    path = Path(path)
    fmt = image_format(path)
    if fmt == "exr":
        raise ImageFormatError(f"{path}: an EXR file, not PFM or Radiance HDR")
    try:
        with open(path, "rb") as fh:
            head = fh.read(MAX_HEADER_BYTES)
            size = path.stat().st_size
    except OSError as exc:
        raise ImageFormatError(f"{path}: cannot read ({exc.strerror or exc})") from None
    return _pfm_header(path, head, size) if fmt == "pfm" else _rgbe_header(path, head, size)


def check_image_header(path: str | Path) -> None:
    """Check an EXR, PFM or Radiance HDR file's header against the file and the memory left
    without reading its pixels (what the readers check first); raises a one-line error naming
    the file."""
    if image_format(path) == "exr":
        read_exr_header(path)
    else:
        read_bitmap_header(path)


def _read_pfm(header: BitmapHeader, max_bytes: float) -> np.ndarray:
    """The PFM's pixels, a block of file rows (bottom to top) at a time, into an HxWx3 image."""
    w, h, c = header.width, header.height, header.channels
    out = np.empty((h, w, 3), np.float32)
    dtype = np.dtype(">f4" if header.big_endian else "<f4")
    with open(header.path, "rb") as fh:
        fh.seek(header.data_offset)
        for rows in row_blocks(h, w, 8 * c + RGB_BYTES_PER_PIXEL, max_bytes):
            n = rows.stop - rows.start
            block = np.fromfile(fh, dtype=dtype, count=n * w * c)
            if block.size != n * w * c:
                raise ImageFormatError(f"{header.path}: truncated PFM (pixels end early)")
            block = block.reshape(n, w, c)[::-1].astype(np.float32)
            if header.scale != 1.0:
                block *= np.float32(header.scale)
            out[h - rows.stop:h - rows.start] = block  # file rows run from the bottom of the image
    return out


class _Scanlines:
    """RGBE scanlines decoded from a buffer (Greg Ward's run-length encoding, as Bruce Walter's
    ``rgbe.c`` reads it): every count and length checked against the scanline and the data."""

    def __init__(self, data: mmap.mmap | bytes, pos: int, width: int, path: str) -> None:
        self.data, self.pos, self.width, self.path = data, pos, width, path
        self.flat = not 8 <= width <= 0x7FFF

    def fail(self, what: str) -> ImageFormatError:
        return ImageFormatError(f"{self.path}: corrupt Radiance HDR pixels ({what})")

    def _take(self, n: int) -> np.ndarray:
        if self.pos + n > len(self.data):
            raise self.fail("the pixels end early")
        out = np.frombuffer(self.data, np.uint8, n, self.pos)
        self.pos += n
        return out

    def read(self, rows: int) -> np.ndarray:
        """The next ``rows`` scanlines as rows x W x 4 RGBE bytes."""
        w = self.width
        if self.flat:
            return self._take(rows * w * 4).reshape(rows, w, 4)
        out = np.empty((rows, w, 4), np.uint8)
        for y in range(rows):
            marker = bytes(self._take(4))
            if marker[0] != 2 or marker[1] != 2 or marker[2] & 0x80:  # not run-length encoded: flat from here
                self.pos -= 4
                self.flat = True
                out[y:] = self.read(rows - y)
                break
            if (marker[2] << 8 | marker[3]) != w:
                raise self.fail(f"a scanline says {marker[2] << 8 | marker[3]} pixels, the image {w}")
            for c in range(4):
                out[y, :, c] = np.frombuffer(self._component(), np.uint8)
        return out

    def _component(self) -> bytearray:
        """One component of one run-length encoded scanline (W bytes)."""
        out, x, w, data, pos, n = bytearray(), 0, self.width, self.data, self.pos, len(self.data)
        while x < w:
            if pos >= n:
                raise self.fail("the pixels end early")
            count = data[pos]
            pos += 1
            if count > 128:  # a run of one value
                count -= 128
                if count > w - x or pos >= n:
                    raise self.fail("a run longer than its scanline" if count > w - x else "the pixels end early")
                out += data[pos:pos + 1] * count
                pos += 1
            else:
                if count == 0 or count > w - x:
                    raise self.fail(f"a run of {count} values where {w - x} remain")
                if pos + count > n:
                    raise self.fail("the pixels end early")
                out += data[pos:pos + count]
                pos += count
            x += count
        self.pos = pos
        return out


def _rgbe_to_float(rgbe: np.ndarray) -> np.ndarray:
    """rows x W x 4 RGBE bytes -> rows x W x 3 float32: mantissa x 2^(exponent - 136), 0 where the
    exponent byte is 0 (as Mitsuba reads them)."""
    exponent = rgbe[..., 3:4].astype(np.int32)
    scale = np.where(exponent > 0, np.ldexp(np.float32(1.0), exponent - 136), np.float32(0.0)).astype(np.float32)
    return rgbe[..., :3].astype(np.float32) * scale


def _read_rgbe(header: BitmapHeader, max_bytes: float) -> np.ndarray:
    """The RGBE file's pixels, decoded here a block of scanlines at a time into an HxWx3 image."""
    w, h = header.width, header.height
    out = np.empty((h, w, 3), np.float32)
    with open(header.path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
        lines = _Scanlines(data, header.data_offset, w, header.path)
        for rows in row_blocks(h, w, RGBE_BYTES_PER_PIXEL, max_bytes):
            out[rows] = _rgbe_to_float(lines.read(rows.stop - rows.start))
    return out


def read_bitmap(path: str | Path, max_bytes: float = DEFAULT_BLOCK_BYTES) -> np.ndarray:
    """HxWx3 float32 pixels of a PFM or Radiance HDR file, the header checked first (module
    notes); a PFM read a block of rows at a time, its temporaries within ``max_bytes``."""
    header = read_bitmap_header(path)
    try:
        return _read_pfm(header, max_bytes) if header.format == "pfm" else _read_rgbe(header, max_bytes)
    except OSError as exc:
        raise ImageFormatError(f"{path}: cannot read ({exc.strerror or exc})") from None


def write_bitmap(path: str | Path, rgb: np.ndarray) -> None:
    """Write HxWx3 radiance atomically as PFM or Radiance HDR (by ``path``'s suffix)."""
    import mitsuba as mi

    path = Path(path)
    fmt = output_format(path)
    if fmt not in ("pfm", "hdr"):
        raise ImageFormatError(f"{path}: write_bitmap writes .pfm or .hdr files")
    if not path.parent.is_dir():
        raise ImageFormatError(f"{path}: output folder does not exist")
    file_format = mi.Bitmap.FileFormat.PFM if fmt == "pfm" else mi.Bitmap.FileFormat.RGBE
    bitmap = mi.Bitmap(np.ascontiguousarray(rgb, dtype=np.float32))
    try:
        with atomic_path(path) as tmp:
            bitmap.write(str(tmp), file_format)
    except OSError as exc:
        raise ImageFormatError(f"{path}: cannot write ({exc.strerror or exc})") from None
    except RuntimeError as exc:
        raise ImageFormatError(f"{path}: cannot write ({_last_line(exc)})") from None


def _last_line(exc: BaseException) -> str:
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return lines[-1].split("] ", 1)[-1] if lines else type(exc).__name__
