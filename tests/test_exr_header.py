"""EXR headers read and checked before any pixel is allocated: what OpenEXR writes parses to what
it wrote; headers that claim more than the file holds, or more than the bounds, are refused."""
from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

from imaging import exr_header
from imaging.errors import ExrError
from imaging.exr import read_exr, write_exr
from imaging.exr_header import read_exr_header, tile_count
from imaging.exr_layers import read_exr_file


def _planes(rng: np.random.Generator, h: int, w: int, names: str = "RGB", dtype: type = np.float16) -> dict:
    return {c: rng.random((h, w)).astype(dtype) for c in names}


def _patch_attribute(data: bytes, name: str, value: bytes) -> bytes:
    """``data`` with the value of its first attribute ``name`` replaced by ``value`` (same size)."""
    at = data.index(name.encode() + b"\0")
    size_at = data.index(b"\0", at + len(name) + 1) + 1
    (size,) = struct.unpack("<i", data[size_at:size_at + 4])
    assert size == len(value)
    return data[:size_at + 4] + value + data[size_at + 4 + size:]


@pytest.mark.parametrize("compression", [OpenEXR.NO_COMPRESSION, OpenEXR.RLE_COMPRESSION, OpenEXR.ZIPS_COMPRESSION,
                                         OpenEXR.ZIP_COMPRESSION, OpenEXR.PIZ_COMPRESSION, OpenEXR.PXR24_COMPRESSION,
                                         OpenEXR.B44_COMPRESSION, OpenEXR.B44A_COMPRESSION, OpenEXR.DWAA_COMPRESSION,
                                         OpenEXR.DWAB_COMPRESSION, OpenEXR.ZSTD_COMPRESSION])
def test_scanline_files_parse_as_written(tmp_path: Path, rng: np.random.Generator, compression) -> None:
    with OpenEXR.File({"compression": compression}, _planes(rng, 37, 29)) as f:
        f.write(str(tmp_path / "a.exr"))
    header = read_exr_header(tmp_path / "a.exr")
    (part,) = header.parts
    assert (part.width, part.height, part.window) == (29, 37, (0, 0, 28, 36))
    assert sorted(c.name for c in part.channels) == ["B", "G", "R"]
    assert part.pixel_bytes == header.pixel_bytes == 37 * 29 * 3 * 2
    assert part.compression == int(compression) and not header.multipart


@pytest.mark.parametrize("mode", [OpenEXR.ONE_LEVEL, OpenEXR.MIPMAP_LEVELS, OpenEXR.RIPMAP_LEVELS])
@pytest.mark.parametrize("rounding", [OpenEXR.ROUND_DOWN, OpenEXR.ROUND_UP])
def test_tiled_files_parse_and_read(tmp_path: Path, rng: np.random.Generator, mode, rounding) -> None:
    tiles = OpenEXR.TileDescription()
    tiles.xSize, tiles.ySize, tiles.mode, tiles.roundingMode = 8, 8, mode, rounding
    channels = _planes(rng, 37, 29, dtype=np.float32)
    with OpenEXR.File({"type": OpenEXR.tiledimage, "tiles": tiles}, dict(channels)) as f:
        f.write(str(tmp_path / "t.exr"))
    part = read_exr_header(tmp_path / "t.exr").parts[0]
    assert part.tiles == (8, 8, int(mode), int(rounding))
    if mode == OpenEXR.ONE_LEVEL:  # the binding writes a mipmap's first level only, and cannot read it back
        assert np.array_equal(read_exr(tmp_path / "t.exr").rgb, np.stack([channels[c] for c in "RGB"], -1))


def test_tile_counts_by_hand() -> None:
    assert tile_count(29, 37, (8, 8, 0, 0)) == 4 * 5
    # mipmap levels rounded down: 29x37, 14x18, 7x9, 3x4, 1x2, 1x1 -> 20 + 2*3 + 1*2 + 1 + 1 + 1
    assert tile_count(29, 37, (8, 8, 1, 0)) == 20 + 6 + 2 + 1 + 1 + 1
    # rounded up: 29x37, 15x19, 8x10, 4x5, 2x3, 1x2, 1x1 (ceil(log2 37) + 1 = 7 levels)
    assert tile_count(29, 37, (8, 8, 1, 1)) == 20 + 6 + 2 + 1 + 1 + 1 + 1
    # ripmap: every pair of a width level (29, 14, 7, 3, 1) and a height level (37, 18, 9, 4, 2, 1)
    widths, heights = [29, 14, 7, 3, 1], [37, 18, 9, 4, 2, 1]
    assert tile_count(29, 37, (8, 8, 2, 0)) == sum(-(-w // 8) * -(-h // 8) for w in widths for h in heights)


def test_multipart_parts_and_names(tmp_path: Path, rng: np.random.Generator) -> None:
    parts = [OpenEXR.Part({"compression": OpenEXR.ZIP_COMPRESSION}, _planes(rng, 5, 6), name="color"),
             OpenEXR.Part({"compression": OpenEXR.PIZ_COMPRESSION}, _planes(rng, 5, 6, "Y", np.float32),
                          name="depth")]
    with OpenEXR.File(parts) as f:
        f.write(str(tmp_path / "m.exr"))
    header = read_exr_header(tmp_path / "m.exr")
    assert header.multipart and [p.name for p in header.parts] == ["color", "depth"]
    assert header.pixel_bytes == 5 * 6 * (3 * 2 + 4)


@pytest.fixture
def small(tmp_path: Path) -> bytes:
    write_exr(tmp_path / "small.exr", np.ones((8, 8, 3), np.float32))
    return (tmp_path / "small.exr").read_bytes()


@pytest.mark.parametrize("window, message", [
    ((0, 0, 99999, 99999), "chunk table of part 0 runs past the end of the file"),
    ((0, 0, 2**21, 7), "data window of 2097153x8 pixels (each side must be 1..1048576)"),
    ((5, 0, 0, 7), "data window of -4x8 pixels"),
    ((0, 0, 7, 16), "chunk 0 of part 0 lies at byte [0-9]+, outside the file's chunks"),  # 2 ZIP chunks claimed
])
def test_lying_data_windows_are_refused(tmp_path: Path, small: bytes, window: tuple, message: str) -> None:
    (tmp_path / "lie.exr").write_bytes(_patch_attribute(small, "dataWindow", struct.pack("<4i", *window)))
    with pytest.raises(ExrError, match="lie.exr: .*" + message.replace("(", r"\(").replace(")", r"\)")):
        read_exr_header(tmp_path / "lie.exr")


def test_offsets_outside_the_file_and_uncompressed_pixels_missing(tmp_path: Path, rng: np.random.Generator,
                                                                  small: bytes) -> None:
    header = read_exr_header(tmp_path / "small.exr")
    offset_at = header.tables_end - 8
    bad = small[:offset_at] + struct.pack("<Q", len(small) + 100) + small[offset_at + 8:]
    (tmp_path / "far.exr").write_bytes(bad)
    far = (f"lies at byte {len(small) + 100:,}, outside the file's chunks "
           f"\\(bytes {header.tables_end:,} to {len(small):,}\\)")
    with pytest.raises(ExrError, match=r"far.exr: .*chunk 0 of part 0 " + far):
        read_exr_header(tmp_path / "far.exr")
    with OpenEXR.File({"compression": OpenEXR.NO_COMPRESSION}, _planes(rng, 64, 64, dtype=np.float32)) as f:
        f.write(str(tmp_path / "raw.exr"))
    data = (tmp_path / "raw.exr").read_bytes()
    (tmp_path / "raw_cut.exr").write_bytes(data[:len(data) // 3])
    with pytest.raises(ExrError, match=r"raw_cut.exr: truncated or corrupt EXR \(.*(outside the file|need 49,152)"):
        read_exr_header(tmp_path / "raw_cut.exr")


def test_a_small_file_cannot_claim_a_huge_image_of_zeros(tmp_path: Path) -> None:
    """One ZIP chunk (16 rows) whose data window is widened to 100000 pixels: the chunk table still
    fits, but 100000 x 16 x 3 float32 values cannot come out of a few hundred bytes of deflate."""
    write_exr(tmp_path / "z.exr", np.zeros((16, 8, 3), np.float32))
    data = _patch_attribute((tmp_path / "z.exr").read_bytes(), "dataWindow", struct.pack("<4i", 0, 0, 99999, 15))
    (tmp_path / "bomb.exr").write_bytes(data)
    with pytest.raises(ExrError, match=f"bomb.exr: truncated or corrupt EXR \\(part 0's pixels need 19,200,000 bytes, "
                                       f"more than the file's {len(data):,} bytes hold with ZIP compression "
                                       "\\(at most 1032:1\\)"):
        read_exr_header(tmp_path / "bomb.exr")


def test_channel_and_part_bounds(tmp_path: Path, rng: np.random.Generator, monkeypatch: pytest.MonkeyPatch) -> None:
    with OpenEXR.File({}, _planes(rng, 2, 2, "ABCDEFG")) as f:
        f.write(str(tmp_path / "seven.exr"))
    monkeypatch.setattr(exr_header, "MAX_CHANNELS", 6)
    with pytest.raises(ExrError, match="seven.exr: more than 6 channels in a part"):
        read_exr_header(tmp_path / "seven.exr")
    parts = [OpenEXR.Part({}, _planes(rng, 2, 2), name=f"p{i}") for i in range(3)]
    with OpenEXR.File(parts) as f:
        f.write(str(tmp_path / "three.exr"))
    monkeypatch.setattr(exr_header, "MAX_PARTS", 2)
    with pytest.raises(ExrError, match="three.exr: more than 2 parts"):
        read_exr_header(tmp_path / "three.exr")


def test_not_an_exr_missing_and_folders(tmp_path: Path, small: bytes) -> None:
    (tmp_path / "text.exr").write_text("hello")
    (tmp_path / "magic_only.exr").write_bytes(small[:6])
    (tmp_path / "v3.exr").write_bytes(small[:4] + b"\x03" + small[5:])
    for name, message in (("text.exr", "not an OpenEXR file"), ("magic_only.exr", "not an OpenEXR file"),
                          ("v3.exr", "format version 3, expected 2"), ("none.exr", "file not found")):
        with pytest.raises(ExrError, match=f"{name}: .*{message}"):
            read_exr_header(tmp_path / name)
    with pytest.raises(ExrError, match="is a directory"):
        read_exr_header(tmp_path)


def test_images_beyond_the_memory_left_are_refused_naming_both(tmp_path: Path, rng: np.random.Generator,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """A well-formed file whose pixels need more than the memory left: one line, before reading."""
    import imaging.memory_limit

    write_exr(tmp_path / "a.exr", rng.random((64, 32, 3)).astype(np.float32))
    monkeypatch.setattr(imaging.memory_limit, "available_bytes", lambda: 20_000)
    with pytest.raises(ExrError, match=r"a.exr: 32x64 pixels: 1 float32 image\(s\) need 24,576 bytes, more than "
                                       r"the 20,000 bytes of memory available"):
        read_exr(tmp_path / "a.exr")
    with pytest.raises(ExrError, match=r"a.exr: 32x64 pixels: its channels and a float32 colour image need "
                                       r"49,152 bytes, more than the 20,000 bytes"):
        read_exr_file(tmp_path / "a.exr")


def test_whole_reads_beyond_the_budget_are_refused_blocks_are_not(tmp_path: Path, rng: np.random.Generator) -> None:
    """A scanline file is read in row blocks within any budget (the same pixels); a tiled file is
    decoded whole, refused when that exceeds the budget."""
    rgb = rng.random((40, 30, 3)).astype(np.float32)
    write_exr(tmp_path / "s.exr", rgb, layers={"albedo": rgb * 0.5})
    small = read_exr(tmp_path / "s.exr", max_bytes=1)
    assert np.array_equal(small.rgb, rgb) and np.array_equal(small.layers["albedo"], rgb * np.float32(0.5))
    tiles = OpenEXR.TileDescription()
    tiles.xSize, tiles.ySize = 16, 16
    planes = {c: rgb[..., i].copy() for i, c in enumerate("RGB")}
    with OpenEXR.File({"type": OpenEXR.tiledimage, "tiles": tiles}, planes) as f:
        f.write(str(tmp_path / "t.exr"))
    assert np.array_equal(read_exr(tmp_path / "t.exr", max_bytes=40 * 30 * 12).rgb, rgb)
    with pytest.raises(ExrError, match=r"t.exr: a tiled EXR is read whole: its pixels need 14,400 bytes, more "
                                       r"than the memory budget of 14,399 bytes"):
        read_exr(tmp_path / "t.exr", max_bytes=40 * 30 * 12 - 1)


def test_a_compression_this_module_does_not_know_leaves_the_tables_to_openexr(tmp_path: Path, small: bytes) -> None:
    """A single part whose compression is not one this module knows: the header parses and the
    table's end is unknown (None); OpenEXR decides the rest: the image (OpenEXR 3.5 reads the ZIP
    chunks) or a one-line error."""
    (tmp_path / "odd.exr").write_bytes(_patch_attribute(small, "compression", bytes([42])))
    header = read_exr_header(tmp_path / "odd.exr")
    assert header.parts[0].compression == 42 and header.tables_end is None
    try:
        assert read_exr(tmp_path / "odd.exr").rgb.shape == (8, 8, 3)
    except ExrError as exc:
        assert "odd.exr" in str(exc) and "\n" not in str(exc)
