"""OpenEXR reading and writing: RGB plus named 3-channel layers, with metadata.

Layout: images are HxWx3 float32 (linear radiance for RGB). Extra layers are stored as
``<layer>.R/G/B`` (or ``.X/Y/Z`` for normals), e.g. ``albedo.R``, ``normal.X``. Metadata values
(str, int or float) go into the EXR header under their own names.

Files are written a block of rows at a time through OpenEXR's scanline writer
(``OpenEXR.OutputFile``, which takes rows in pieces), so the planes made for the file stay within
a bound at any image size: ``OpenEXR.File`` writes whole contiguous planes only (and reads a
strided view's memory as if it were contiguous). The bytes are those ``OpenEXR.File`` writes.
"""
from __future__ import annotations

import contextlib
import ctypes
import io
import os
import sys
import threading
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import Imath
import numpy as np
import OpenEXR

from imaging.atomic_io import atomic_path
from imaging.blocks import DEFAULT_BLOCK_BYTES, row_blocks
from imaging.errors import ExrError

XYZ_LAYERS = ("normal", "sh_normal", "nrm")
HALF_MAX = 65504.0  # largest finite float16
EXR_MAGIC = b"\x76\x2f\x31\x01"
_LIBC = ctypes.CDLL(None)
_QUIET_LOCK = threading.Lock()
CONVERT_BYTES_PER_PIXEL = 16  # plane(): one channel's finite mask, clip and cast for float16
_PIXEL_TYPES = {np.dtype(np.uint32): Imath.PixelType.UINT, np.dtype(np.float16): Imath.PixelType.HALF,
                np.dtype(np.float32): Imath.PixelType.FLOAT}
RowSource = Callable[[int, int], np.ndarray]  # rows(y0, y1) of a channel, contiguous, its pixel type
_STANDARD_KEYS = {"channels", "compression", "dataWindow", "displayWindow", "lineOrder",
                  "pixelAspectRatio", "screenWindowCenter", "screenWindowWidth", "type"}


@dataclass
class ExrImage:
    """``rgb``: HxWx3 float32; ``layers``: name -> HxWx3 float32; ``metadata``: header extras."""

    rgb: np.ndarray
    layers: dict[str, np.ndarray] = field(default_factory=dict)
    metadata: dict[str, str | int | float] = field(default_factory=dict)


def layer_suffixes(layer: str) -> tuple[str, str, str]:
    """Channel suffixes of an extra layer: X/Y/Z for normals, R/G/B otherwise."""
    return ("X", "Y", "Z") if layer in XYZ_LAYERS else ("R", "G", "B")


def _check_image(name: str, img: np.ndarray, shape: tuple[int, ...] | None) -> np.ndarray:
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ExrError(f"{name}: expected an HxWx3 array, got shape {img.shape}")
    if shape is not None and img.shape != shape:
        raise ExrError(f"{name}: shape {img.shape} differs from RGB {shape}")
    return img


def plane(values: np.ndarray, half: bool) -> np.ndarray:
    """One channel as contiguous float32, or float16 with finite values beyond +-65504 saturated
    (a plain cast would turn them into Inf)."""
    if not half:
        return np.ascontiguousarray(values, dtype=np.float32)
    saturated = np.where(np.isfinite(values), np.clip(values, -HALF_MAX, HALF_MAX), values)
    return np.ascontiguousarray(saturated, dtype=np.float16)


def _column(img: np.ndarray, index: int, half: bool) -> tuple[np.dtype, RowSource]:
    """Channel ``index`` of an HxWxC image as the chunked writer takes it: its pixel type and its
    rows, converted by :func:`plane` one block at a time."""
    return np.dtype(np.float16 if half else np.float32), lambda y0, y1: plane(img[y0:y1, :, index], half)


def write_scanlines(path: str | Path, attributes: Mapping[str, object], width: int, height: int,
                    channels: Mapping[str, tuple[np.dtype, RowSource]],
                    max_bytes: float = DEFAULT_BLOCK_BYTES) -> None:
    """Write a single-part scanline EXR to ``path`` a block of rows at a time, each block's
    planes within ``max_bytes``. ``attributes``: header values as OpenEXR's scanline writer takes
    them (``Imath`` objects, bytes for strings, int, float); ``channels``: name -> (pixel type:
    float16, float32 or uint32; ``rows(y0, y1)`` giving those rows as a contiguous
    (y1-y0)xW array of that type). Not atomic: callers write to a temporary path. Raises what
    OpenEXR raises (OSError, TypeError)."""
    header = OpenEXR.Header(width, height)
    header.update(attributes)
    header["channels"] = {name: Imath.Channel(Imath.PixelType(_PIXEL_TYPES[dtype]))
                          for name, (dtype, _) in channels.items()}
    per_pixel = sum(dtype.itemsize for dtype, _ in channels.values()) + CONVERT_BYTES_PER_PIXEL
    out = OpenEXR.OutputFile(str(path), header)
    try:
        for rows in row_blocks(height, width, per_pixel, max_bytes):
            out.writePixels({name: rows_of(rows.start, rows.stop) for name, (_, rows_of) in channels.items()},
                            rows.stop - rows.start)
    finally:
        out.close()


def write_exr(
    path: str | Path,
    rgb: np.ndarray,
    layers: Mapping[str, np.ndarray] | None = None,
    metadata: Mapping[str, str | int | float] | None = None,
    half: bool = False,
    max_bytes: float = DEFAULT_BLOCK_BYTES,
) -> None:
    """Write an EXR atomically (ZIP compression), float32 or, with ``half``, float16 pixels
    (finite values beyond the float16 range saturate at +-65504), a block of rows at a time:
    the planes made for the file stay within ``max_bytes`` (at least one row)."""
    path = Path(path)
    rgb = _check_image("RGB", rgb, None)
    channels = {suffix: _column(rgb, c, half) for c, suffix in enumerate("RGB")}
    for layer, img in (layers or {}).items():
        img = _check_image(layer, img, rgb.shape)
        for c, suffix in enumerate(layer_suffixes(layer)):
            channels[f"{layer}.{suffix}"] = _column(img, c, half)
    attributes: dict[str, object] = {"compression": Imath.Compression(Imath.Compression.ZIP_COMPRESSION),
                                     "type": b"scanlineimage"}  # as OpenEXR.File writes it
    for key, value in (metadata or {}).items():
        if key in _STANDARD_KEYS or not isinstance(value, (str, int, float)) or isinstance(value, bool):
            raise ExrError(f"{path}: metadata {key!r} must be a non-reserved str/int/float")
        attributes[key] = value.encode("utf-8") if isinstance(value, str) else value
    if not path.parent.is_dir():
        raise ExrError(f"{path}: output folder does not exist")
    try:
        with atomic_path(path) as tmp:
            write_scanlines(tmp, attributes, rgb.shape[1], rgb.shape[0], channels, max_bytes)
    except OSError as exc:
        raise ExrError(f"{path}: cannot write ({exc.strerror or exc})") from None
    except (RuntimeError, TypeError) as exc:
        raise ExrError(f"{path}: cannot write ({str(exc).splitlines()[0]})") from None


@contextlib.contextmanager
def quiet_native_output() -> Iterator[io.StringIO]:
    """Send what OpenEXR's C/C++ code prints on a corrupt file (to stdout and stderr) to /dev/null:
    the one-line :class:`ExrError` replaces it. Yields the buffer that receives what the binding
    prints through Python (its warnings about parts it could not read). One reader at a time:
    threads that interleaved their saves and restores of the descriptors could leave stdout
    pointing at /dev/null."""
    with _QUIET_LOCK:
        for stream in (sys.stdout, sys.stderr):
            if stream is not None:
                stream.flush()
        saved = [os.dup(1), os.dup(2)]
        try:
            with open(os.devnull, "wb") as null:
                os.dup2(null.fileno(), 1)
                os.dup2(null.fileno(), 2)
            captured = io.StringIO()
            with contextlib.redirect_stdout(captured), contextlib.redirect_stderr(captured):
                yield captured  # the binding's warnings go through Python's sys.stdout, the C core's to fd 2
        finally:
            _LIBC.fflush(None)  # C stdio buffers (where C++ std::cout writes) still hold their text
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)


def check_exr_file(path: Path) -> None:
    """Raise :class:`ExrError` unless ``path`` is an existing file that starts like an EXR."""
    if not path.exists():
        raise ExrError(f"{path}: file not found")
    if path.is_dir():
        raise ExrError(f"{path}: is a directory, not an EXR file")
    with open(path, "rb") as fh:
        if fh.read(4) != EXR_MAGIC:
            raise ExrError(f"{path}: not an OpenEXR file")


def read_exr(path: str | Path) -> ExrImage:
    """Read an EXR with R, G, B channels (float16 or float32) into float32 arrays.

    Raises :class:`ExrError` for a missing, truncated or non-EXR file, or one without RGB.
    """
    path = Path(path)
    check_exr_file(path)
    try:
        with quiet_native_output(), OpenEXR.File(str(path), separate_channels=True) as exr:
            header = dict(exr.header())
            channels = {k: np.array(v.pixels) for k, v in exr.channels().items()}
    except (RuntimeError, ValueError, OSError) as exc:
        raise ExrError(f"{path}: truncated or corrupt EXR ({str(exc).splitlines()[0]})") from None
    missing = [c for c in "RGB" if c not in channels]
    if missing:
        raise ExrError(f"{path}: has no {'/'.join(missing)} channel(s) (found: "
                       f"{', '.join(sorted(channels)) or 'none'})")
    rgb = np.stack([channels[c] for c in "RGB"], axis=-1).astype(np.float32)
    layers: dict[str, np.ndarray] = {}
    for name in sorted({k.rsplit(".", 1)[0] for k in channels if "." in k}):
        keys = [f"{name}.{s}" for s in layer_suffixes(name)]
        if all(k in channels for k in keys):
            layers[name] = np.stack([channels[k] for k in keys], axis=-1).astype(np.float32)
    metadata = {k: v for k, v in header.items()
                if k not in _STANDARD_KEYS and isinstance(v, (str, int, float))}
    return ExrImage(rgb=rgb, layers=layers, metadata=metadata)
