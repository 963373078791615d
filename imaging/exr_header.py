"""An EXR file's headers and chunk tables, read and checked before OpenEXR allocates any pixel.

OpenEXR's binding allocates every channel of a part's data window, then reads the chunks: a header
that lies (a data window of 100000x100000 in a 4 KB file, millions of channels or parts) would
make it allocate what the header says. :func:`read_exr_header` parses the headers itself (the
layout of the OpenEXR file format: magic, version and flags, attributes until an empty name, one
header per part, then one table of chunk offsets per part), bounds what they claim
(:data:`MAX_SIDE`, :data:`MAX_CHANNELS`, :data:`MAX_PARTS`), checks that every part's chunk table
lies within the file and points into it, and that the file can hold the pixels the header
promises (uncompressed, or within the largest ratio of RLE and ZIP: a small file cannot claim a
huge image of zeros). What the pixels need in memory (:attr:`ExrHeader.pixel_bytes`) is then known
before anything is allocated. Deep parts are refused (their sizes are not in the header).
"""
from __future__ import annotations

import mmap
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from imaging.errors import ExrError

EXR_MAGIC = b"\x76\x2f\x31\x01"
MAX_SIDE = 2**20  # pixels along either side of a data window
MAX_CHANNELS = 4096  # channels of a file, all parts together
MAX_PARTS = 1024
MAX_NAME = 255  # bytes of an attribute name or type (OpenEXR's long-name limit)
PIXEL_TYPE_BYTES = {0: 4, 1: 2, 2: 4}  # UINT, HALF, FLOAT
# scanlines per chunk of the compressions OpenEXR 3 defines (NONE, RLE, ZIPS, ZIP, PIZ, PXR24, B44,
# B44A, DWAA, DWAB); others are left to OpenEXR
LINES_PER_CHUNK = {0: 1, 1: 1, 2: 1, 3: 16, 4: 32, 5: 16, 6: 32, 7: 32, 8: 32, 9: 256}
# the most bytes one stored byte can decode to: none 1, RLE 64 (two bytes give a run of 128), ZIPS and
# ZIP 1032 (deflate's limit: a 258-byte match in 2 bits); the other compressions are left unbounded
MAX_RATIO = {0: 1, 1: 64, 2: 1032, 3: 1032}
COMPRESSION_NAMES = {0: "uncompressed", 1: "RLE", 2: "ZIPS", 3: "ZIP"}
_TILED, _NON_IMAGE, _MULTIPART = 0x200, 0x800, 0x1000
_DEEP = ("deepscanline", "deeptile")


@dataclass(frozen=True)
class ExrChannel:
    """One channel of a part: its name, pixel type (0 uint, 1 half, 2 float) and sampling."""

    name: str
    pixel_type: int
    x_sampling: int = 1
    y_sampling: int = 1


@dataclass(frozen=True)
class ExrPartHeader:
    """What one part's header says: ``window`` (x0, y0, x1, y1) inclusive, ``tiles`` (x size,
    y size, level mode, rounding mode) for tiled parts."""

    name: str
    kind: str
    compression: int
    window: tuple[int, int, int, int]
    channels: tuple[ExrChannel, ...]
    tiles: tuple[int, int, int, int] | None = None
    chunk_count: int | None = None

    @property
    def width(self) -> int:
        return self.window[2] - self.window[0] + 1

    @property
    def height(self) -> int:
        return self.window[3] - self.window[1] + 1

    @property
    def pixel_bytes(self) -> int:
        """Bytes of the part's full-resolution pixels, every channel in its own type."""
        return sum(-(-self.width // c.x_sampling) * -(-self.height // c.y_sampling) * PIXEL_TYPE_BYTES[c.pixel_type]
                   for c in self.channels)

    def expected_chunks(self) -> int | None:
        """Chunks of the part as its header describes it (None: a compression OpenEXR knows and
        this module does not)."""
        if self.tiles is None:
            lines = LINES_PER_CHUNK.get(self.compression)
            return None if lines is None else -(-self.height // lines)
        return tile_count(self.width, self.height, self.tiles)


@dataclass(frozen=True)
class ExrHeader:
    """The headers of a whole file and where its chunk tables end (where its chunks begin; None
    where a part's compression is one this module does not know, so its table's length is unknown)."""

    path: str
    parts: tuple[ExrPartHeader, ...]
    file_size: int
    tables_end: int | None

    @property
    def pixel_bytes(self) -> int:
        """Bytes of every part's pixels (what reading the whole file allocates)."""
        return sum(p.pixel_bytes for p in self.parts)

    @property
    def multipart(self) -> bool:
        return len(self.parts) > 1


def _levels(size: int, rounding: int) -> int:
    """OpenEXR's number of mipmap levels along a side: log2 rounded down (0) or up (1), plus one."""
    log = size.bit_length() - 1
    return log + 1 + (rounding == 1 and size > 2**log)


def _level_size(size: int, level: int, rounding: int) -> int:
    return max(1, (size + (2**level - 1 if rounding == 1 else 0)) >> level)


def tile_count(width: int, height: int, tiles: tuple[int, int, int, int]) -> int | None:
    """Tiles of a tiled part over all its levels (level mode 0 one level, 1 mipmap, 2 ripmap);
    None for another mode."""
    xs, ys, mode, rounding = tiles

    def count(w: int, h: int) -> int:
        return -(-w // xs) * -(-h // ys)

    if mode == 0:
        return count(width, height)
    if mode == 1:
        return sum(count(_level_size(width, n, rounding), _level_size(height, n, rounding))
                   for n in range(_levels(max(width, height), rounding)))
    if mode == 2:
        return sum(count(_level_size(width, i, rounding), _level_size(height, j, rounding))
                   for i in range(_levels(width, rounding)) for j in range(_levels(height, rounding)))
    return None


class _Reader:
    """Bounds-checked reads from the file's bytes; every overrun is an :class:`ExrError`."""

    def __init__(self, data: mmap.mmap | bytes, path: str) -> None:
        self.data, self.path, self.pos = data, path, 0

    def fail(self, what: str) -> ExrError:
        return ExrError(f"{self.path}: truncated or corrupt EXR ({what})")

    def take(self, n: int, what: str) -> bytes:
        if n < 0 or self.pos + n > len(self.data):
            raise self.fail(f"{what} runs past the end of the file")
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def cstring(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos, self.pos + MAX_NAME + 1)
        if end < 0:
            raise self.fail(f"{what} longer than {MAX_NAME} bytes or unterminated")
        text = self.take(end - self.pos, what)
        self.pos += 1
        return utf8(text, what, self)


def utf8(raw: bytes, what: str, r: _Reader) -> str:
    """``raw`` decoded as UTF-8 (OpenEXR's binding cannot hand other bytes to Python)."""
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise r.fail(f"{what} is not UTF-8 text") from None


def _check_strings(name: str, kind: str, value: bytes, r: _Reader) -> None:
    """A string or string-vector attribute's text must be UTF-8."""
    if kind == "string":
        utf8(value, f"attribute {name!r}", r)
    elif kind == "stringvector":
        sub = _Reader(value, r.path)
        while sub.pos < len(value):
            (size,) = struct.unpack("<i", sub.take(4, f"attribute {name!r}"))
            utf8(sub.take(size, f"attribute {name!r}"), f"attribute {name!r}", r)


def _channels(value: bytes, r: _Reader) -> tuple[ExrChannel, ...]:
    sub = _Reader(value, r.path)
    out = []
    while sub.pos < len(value) and value[sub.pos] != 0:
        name = sub.cstring("a channel name")
        pixel_type, _, xs, ys = struct.unpack("<iB3xii", sub.take(16, f"channel {name!r}"))
        if pixel_type not in PIXEL_TYPE_BYTES or xs < 1 or ys < 1:
            raise r.fail(f"channel {name!r} has pixel type {pixel_type}, sampling {xs}x{ys}")
        out.append(ExrChannel(name, pixel_type, xs, ys))
        if len(out) > MAX_CHANNELS:
            raise ExrError(f"{r.path}: more than {MAX_CHANNELS} channels in a part")
    return tuple(out)


def _attributes(r: _Reader) -> dict[str, tuple[str, bytes]]:
    """name -> (type, value bytes) of one header, up to its terminating empty name."""
    attributes: dict[str, tuple[str, bytes]] = {}
    while True:
        name = r.cstring("an attribute name")
        if not name:
            return attributes
        kind = r.cstring(f"the type of attribute {name!r}")
        (size,) = struct.unpack("<i", r.take(4, f"the size of attribute {name!r}"))
        attributes[name] = (kind, r.take(size, f"attribute {name!r}"))
        _check_strings(name, kind, attributes[name][1], r)


def _part(attributes: dict[str, tuple[str, bytes]], r: _Reader, tiled_flag: bool, index: int) -> ExrPartHeader:
    def value(name: str, kind: str, size: int | None = None) -> bytes:
        found = attributes.get(name)
        if found is None or found[0] != kind or (size is not None and len(found[1]) != size):
            raise r.fail(f"part {index} has no valid {name!r} attribute")
        return found[1]

    x0, y0, x1, y1 = struct.unpack("<4i", value("dataWindow", "box2i", 16))
    width, height = x1 - x0 + 1, y1 - y0 + 1
    if not (1 <= width <= MAX_SIDE and 1 <= height <= MAX_SIDE):
        raise ExrError(f"{r.path}: data window of {width}x{height} pixels (each side must be 1..{MAX_SIDE})")
    compression = value("compression", "compression", 1)[0]
    kind = value("type", "string").decode("utf-8") if "type" in attributes else (
        "tiledimage" if tiled_flag else "scanlineimage")
    if kind in _DEEP:
        raise ExrError(f"{r.path}: deep EXR parts are not supported (part {index})")
    tiles = None
    if kind == "tiledimage" or (tiled_flag and "type" not in attributes):
        xs, ys, mode = struct.unpack("<IIB", value("tiles", "tiledesc", 9))
        if not (1 <= xs <= MAX_SIDE and 1 <= ys <= MAX_SIDE):
            raise ExrError(f"{r.path}: tiles of {xs}x{ys} pixels (each side must be 1..{MAX_SIDE})")
        tiles = (xs, ys, mode & 0x0F, mode >> 4)
    chunk_count = None
    if "chunkCount" in attributes:
        (chunk_count,) = struct.unpack("<i", value("chunkCount", "int", 4))
    name = value("name", "string").decode("utf-8") if "name" in attributes else ""
    return ExrPartHeader(name, kind, compression, (x0, y0, x1, y1),
                         _channels(value("channels", "chlist"), r), tiles, chunk_count)


def _check_tables(parts: list[ExrPartHeader], r: _Reader, size: int) -> int | None:
    """Check each part's chunk table (count, place, offsets between the tables' end and the file's
    end); return where the tables end (None: a part's table has a length this module cannot tell,
    from a compression it does not know; OpenEXR checks it)."""
    tables = []
    for index, part in enumerate(parts):
        expected = part.expected_chunks()
        count = part.chunk_count if part.chunk_count is not None else expected
        if count is None:  # no chunkCount (a single part) and a compression this module does not know
            return None
        if count < 1 or (expected is not None and count != expected):
            raise r.fail(f"part {index} has {count} chunks, its header implies {expected}")
        tables.append(np.frombuffer(r.take(8 * count, f"the chunk table of part {index}"), dtype="<u8"))
        ratio = MAX_RATIO.get(part.compression)
        if ratio is not None and part.pixel_bytes > ratio * size:
            how = "uncompressed" if ratio == 1 else \
                f"with {COMPRESSION_NAMES[part.compression]} compression (at most {ratio}:1)"
            raise r.fail(f"part {index}'s pixels need {part.pixel_bytes:,} bytes, more than the file's "
                         f"{size:,} bytes hold {how}")
    for index, (part, table) in enumerate(zip(parts, tables)):
        # a tiled part's full-resolution tiles come first; writers may leave its lower levels out (0)
        full = table if part.tiles is None else table[:tile_count(part.width, part.height, (*part.tiles[:2], 0, 0))]
        bad = np.flatnonzero((full < r.pos) | (full >= size))
        bad = bad if bad.size else np.flatnonzero((table != 0) & ((table < r.pos) | (table >= size)))
        if bad.size:
            raise r.fail(f"chunk {int(bad[0])} of part {index} lies at byte {int(table[bad[0]]):,}, "
                         f"outside the file's chunks (bytes {r.pos:,} to {size:,})")
    return r.pos


def read_exr_header(path: str | Path) -> ExrHeader:
    """The headers of the EXR at ``path``, checked against the file (see the module notes).

    Raises :class:`ExrError` naming the file for a missing file, a folder, something that is not
    an EXR, a header that is truncated or corrupt or claims more than the bounds or the file."""
    path = Path(path)
    if not path.exists():
        raise ExrError(f"{path}: file not found")
    if path.is_dir():
        raise ExrError(f"{path}: is a directory, not an EXR file")
    try:
        with open(path, "rb") as fh:
            size = path.stat().st_size
            if size < 8 or fh.read(4) != EXR_MAGIC:
                raise ExrError(f"{path}: not an OpenEXR file")
            with mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as data:
                return _parse(data, str(path), size)
    except OSError as exc:
        raise ExrError(f"{path}: cannot read ({exc.strerror or exc})") from None


def _parse(data: mmap.mmap, path: str, size: int) -> ExrHeader:
    r = _Reader(data, path)
    r.pos = 4
    (version,) = struct.unpack("<i", r.take(4, "the version"))
    if version & 0xFF != 2:
        raise r.fail(f"format version {version & 0xFF}, expected 2")
    if version & _NON_IMAGE and not version & _MULTIPART:
        raise ExrError(f"{path}: deep EXR parts are not supported")
    parts = []
    while True:
        parts.append(_part(_attributes(r), r, bool(version & _TILED), len(parts)))
        if len(parts) > MAX_PARTS:
            raise ExrError(f"{path}: more than {MAX_PARTS} parts")
        if not version & _MULTIPART:
            break
        if r.take(1, "the header list")[0] == 0:
            break
        r.pos -= 1
    channels = sum(len(p.channels) for p in parts)
    if channels > MAX_CHANNELS:
        raise ExrError(f"{path}: {channels} channels (at most {MAX_CHANNELS})")
    if version & _MULTIPART and any(p.chunk_count is None for p in parts):
        raise r.fail("a part of a multi-part file has no chunkCount")
    return ExrHeader(path, tuple(parts), size, _check_tables(parts, r, size))
