"""EXR I/O: exact float32 round trip, float16 within 1e-3, metadata, clear errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from imaging.errors import ExrError
from imaging.exr import read_exr, write_exr


def _image(rng: np.random.Generator, h: int = 17, w: int = 23) -> np.ndarray:
    return (rng.random((h, w, 3)) * 10.0 ** rng.uniform(-3, 4, (h, w, 1))).astype(np.float32)


def test_float32_round_trip_is_exact_with_layers_and_metadata(tmp_path: Path, rng) -> None:
    rgb, alb = _image(rng), rng.random((17, 23, 3)).astype(np.float32)
    nrm = rng.normal(size=(17, 23, 3)).astype(np.float32)
    meta = {"spp": 128, "seed": 7, "scene": "cbox", "mitsuba": "3.9.1", "render_s": 1.5}
    write_exr(tmp_path / "x.exr", rgb, {"albedo": alb, "normal": nrm}, meta)
    img = read_exr(tmp_path / "x.exr")
    assert np.array_equal(img.rgb, rgb) and img.rgb.dtype == np.float32
    assert np.array_equal(img.layers["albedo"], alb) and np.array_equal(img.layers["normal"], nrm)
    assert img.metadata == meta


def test_float16_round_trip_within_1e_3_relative(tmp_path: Path, rng) -> None:
    rgb = _image(rng).clip(1e-3, 6e4)
    write_exr(tmp_path / "h.exr", rgb, half=True)
    out = read_exr(tmp_path / "h.exr").rgb
    assert out.dtype == np.float32
    assert np.max(np.abs(out - rgb) / rgb) < 1e-3


@pytest.mark.parametrize("fraction", [0.05, 0.3, 0.6, 0.95])
def test_truncated_file_raises_clear_error(tmp_path: Path, rng, fraction: float) -> None:
    write_exr(tmp_path / "x.exr", _image(rng, 64, 64))
    data = (tmp_path / "x.exr").read_bytes()
    (tmp_path / "t.exr").write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(ExrError, match=r"t\.exr: .*(truncated|not an OpenEXR)"):
        read_exr(tmp_path / "t.exr")


def test_not_an_exr_missing_and_directory(tmp_path: Path) -> None:
    (tmp_path / "n.exr").write_text("hello, this is text")
    with pytest.raises(ExrError, match=r"n\.exr: not an OpenEXR file"):
        read_exr(tmp_path / "n.exr")
    with pytest.raises(ExrError, match="file not found"):
        read_exr(tmp_path / "absent.exr")
    with pytest.raises(ExrError, match="is a directory"):
        read_exr(tmp_path)


def test_file_without_rgb_raises(tmp_path: Path) -> None:
    import OpenEXR

    with OpenEXR.File({}, {"Z": np.zeros((4, 4), np.float32)}) as f:
        f.write(str(tmp_path / "z.exr"))
    with pytest.raises(ExrError, match=r"z\.exr: has no R/G/B channel"):
        read_exr(tmp_path / "z.exr")


def test_write_rejects_bad_shapes_and_folders(tmp_path: Path) -> None:
    with pytest.raises(ExrError, match="HxWx3"):
        write_exr(tmp_path / "a.exr", np.zeros((4, 4), np.float32))
    with pytest.raises(ExrError, match="differs from RGB"):
        write_exr(tmp_path / "a.exr", np.zeros((4, 4, 3)), {"albedo": np.zeros((2, 2, 3))})
    with pytest.raises(ExrError, match="output folder does not exist"):
        write_exr(tmp_path / "no" / "a.exr", np.zeros((4, 4, 3)))
    assert list(tmp_path.iterdir()) == []


def whole_file_bytes(path: Path, rgb: np.ndarray, layers: dict, metadata: dict, half: bool) -> bytes:
    """The file as OpenEXR.File writes it from whole planes (the writer before the row blocks)."""
    import OpenEXR

    from imaging.exr import layer_suffixes, plane

    channels = {s: plane(rgb[:, :, c], half) for c, s in enumerate("RGB")}
    for name, img in layers.items():
        channels.update({f"{name}.{s}": plane(img[:, :, c], half) for c, s in enumerate(layer_suffixes(name))})
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, **metadata}, channels) as f:
        f.write(str(path))
    return path.read_bytes()


@pytest.mark.parametrize("h, w", [(1, 1), (17, 23), (64, 3), (5, 200)])
@pytest.mark.parametrize("half", [False, True])
@pytest.mark.parametrize("max_bytes", [1, 5000, 64 * 2**20])  # one row per block, a few, the whole
def test_row_blocks_write_the_whole_file_bytes(tmp_path: Path, rng, h: int, w: int, half: bool,
                                                max_bytes: int) -> None:
    rgb = _image(rng, h, w)
    rgb[0, 0] = [np.inf, 1e6, -1e6]  # saturated in float16
    layers = {"albedo": rng.random((h, w, 3)).astype(np.float32),
              "normal": rng.normal(size=(h, w, 3)).astype(np.float32)}
    meta = {"spp": 128, "scene": "cbox é", "render_s": 1.5}
    write_exr(tmp_path / "x.exr", rgb, layers, meta, half=half, max_bytes=max_bytes)
    assert (tmp_path / "x.exr").read_bytes() == whole_file_bytes(tmp_path / "w.exr", rgb, layers, meta, half)
    img = read_exr(tmp_path / "x.exr")
    assert img.metadata == meta and set(img.layers) == {"albedo", "normal"}
    if not half:
        assert np.array_equal(img.rgb, rgb) and np.array_equal(img.layers["normal"], layers["normal"])


def test_write_exr_scratch_stays_within_its_blocks(tmp_path: Path, rng) -> None:
    """numpy's allocations while writing a 512x512 image with two layers (whole planes: 9 MB)."""
    import tracemalloc

    rgb = rng.random((512, 512, 3), dtype=np.float32)
    layers = {"albedo": rgb[::-1], "normal": rgb[:, ::-1]}
    max_bytes = 256 * 2**10
    for half in (False, True):
        tracemalloc.start()
        try:
            write_exr(tmp_path / "x.exr", rgb, layers, half=half, max_bytes=max_bytes)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < max_bytes + 64 * 2**10, (half, peak)
