"""OpenEXR reading and writing: RGB plus named 3-channel layers, with metadata.

Layout: images are HxWx3 float32 (linear radiance for RGB). Extra layers are stored as
``<layer>.R/G/B`` (or ``.X/Y/Z`` for normals), e.g. ``albedo.R``, ``normal.X``. Metadata values
(str, int or float) go into the EXR header under their own names.

Files are written a block of rows at a time through OpenEXR's scanline writer
(``OpenEXR.OutputFile``, which takes rows in pieces), so the planes made for the file stay within
a bound at any image size: ``OpenEXR.File`` writes whole contiguous planes only (and reads a
strided view's memory as if it were contiguous). The bytes are those ``OpenEXR.File`` writes.

Files are read only after their headers have been checked against the file and the memory left
(:mod:`imaging.exr_header`, :mod:`imaging.memory_limit`); :func:`read_exr` reads a single-part
scanline file a block of rows at a time through OpenEXR's scanline reader.
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
from imaging.exr_header import EXR_MAGIC, ExrHeader, read_exr_header
from imaging.memory_limit import megabytes, require_memory

XYZ_LAYERS = ("normal", "sh_normal", "nrm")
HALF_MAX = 65504.0  # largest finite float16
_LIBC = ctypes.CDLL(None)
_QUIET_LOCK = threading.Lock()
CONVERT_BYTES_PER_PIXEL = 16  # plane(): one channel's finite mask, clip and cast for float16
_PIXEL_TYPES = {np.dtype(np.uint32): Imath.PixelType.UINT, np.dtype(np.float16): Imath.PixelType.HALF,
                np.dtype(np.float32): Imath.PixelType.FLOAT}
RowSource = Callable[[int, int], np.ndarray]  # rows(y0, y1) of a channel, contiguous, its pixel type
_FLOAT = Imath.PixelType(Imath.PixelType.FLOAT)
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


def check_exr_file(path: Path) -> ExrHeader:
    """The headers of ``path`` checked against the file (:func:`imaging.exr_header.read_exr_header`);
    raises :class:`ExrError` unless it is an existing, plausible EXR."""
    return read_exr_header(path)


def check_exr_memory(header: ExrHeader, need: int, what: str) -> None:
    """Raise :class:`ExrError` naming both sizes when ``need`` bytes (``what``: for the message)
    do not fit in the memory left (:mod:`imaging.memory_limit`)."""
    part = header.parts[0]
    require_memory(need, f"{header.path}: {part.width}x{part.height} pixels: {what}", ExrError)


def error_text(exc: BaseException) -> str:
    """The first line of a native library's exception, or its type's name when it has none."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    return lines[0] if lines else type(exc).__name__


def check_full_resolution(header: ExrHeader) -> None:
    """Raise :class:`ExrError` for a file with subsampled channels (chroma planes of YCA files)."""
    for index, part in enumerate(header.parts):
        if any(c.x_sampling != 1 or c.y_sampling != 1 for c in part.channels):
            raise ExrError(f"{header.path}: subsampled channels are not supported (part {part.name or index!r})")


def _layer_names(names: list[str]) -> dict[str, tuple[str, ...]]:
    """R,G,B (name "") and every complete extra layer: name -> its three channels."""
    found = {"": ("R", "G", "B")} if all(c in names for c in "RGB") else {}
    for name in sorted({k.rsplit(".", 1)[0] for k in names if "." in k}):
        keys = tuple(f"{name}.{s}" for s in layer_suffixes(name))
        if all(k in names for k in keys):
            found[name] = keys
    return found


def _metadata(header: Mapping[str, object]) -> dict[str, str | int | float]:
    out: dict[str, str | int | float] = {}
    for key, value in header.items():
        if isinstance(value, bytes):
            value = value.decode("utf-8", "replace")
        if key not in _STANDARD_KEYS and isinstance(value, (str, int, float)) and not isinstance(value, bool):
            out[key] = value
    return out


def _read_blocks(header: ExrHeader, layers: dict[str, tuple[str, ...]], max_bytes: float
                 ) -> tuple[dict[str, np.ndarray], dict[str, str | int | float]]:
    """Each layer as HxWx3 float32, a block of scanlines at a time through OpenEXR's scanline
    reader (each block's decoded channels within ``max_bytes``)."""
    part = header.parts[0]
    width, height, top = part.width, part.height, part.window[1]
    images = {name: np.empty((height, width, 3), np.float32) for name in layers}
    keys = [(name, c, key) for name, names in layers.items() for c, key in enumerate(names)]
    exr = OpenEXR.InputFile(str(header.path))
    try:
        for rows in row_blocks(height, width, 8 * len(keys), max_bytes):
            planes = exr.channels([key for _, _, key in keys], _FLOAT, top + rows.start, top + rows.stop - 1)
            for (name, c, _), data in zip(keys, planes):
                images[name][rows, :, c] = np.frombuffer(data, np.float32).reshape(-1, width)
        return images, _metadata(exr.header())
    finally:
        exr.close()


def _read_whole(header: ExrHeader, max_bytes: float) -> tuple[dict[str, np.ndarray], dict[str, str | int | float]]:
    """Each layer of the first part as HxWx3 float32, the file decoded whole by ``OpenEXR.File``
    (tiled or multi-part files): refused when its decoded pixels exceed ``max_bytes``."""
    if header.pixel_bytes > max_bytes:
        raise ExrError(f"{header.path}: a {'multi-part' if header.multipart else 'tiled'} EXR is read whole: its "
                       f"pixels need {megabytes(header.pixel_bytes)}, more than the memory budget of "
                       f"{megabytes(max_bytes)}")
    with OpenEXR.File(str(header.path), separate_channels=True) as exr:
        file_header = dict(exr.header())
        channels = {k: v.pixels for k, v in exr.channels().items()}
    images = {}
    for name, keys in _layer_names(list(channels)).items():
        images[name] = np.empty(np.shape(channels[keys[0]]) + (3,), np.float32)
        for c, key in enumerate(keys):
            images[name][:, :, c] = channels[key]
    return images, _metadata(file_header)


def read_exr(path: str | Path, max_bytes: float = DEFAULT_BLOCK_BYTES) -> ExrImage:
    """Read an EXR with R, G, B channels (float16 or float32) into float32 arrays, with every
    complete extra layer. A single-part scanline file is read a block of rows at a time (the
    decoded blocks within ``max_bytes``); others whole, refused when their pixels exceed
    ``max_bytes``.

    Raises :class:`ExrError` for a missing, truncated or non-EXR file, one without RGB, or one
    whose images do not fit in the memory left.
    """
    path = Path(path)
    header = check_exr_file(path)
    names = [c.name for c in header.parts[0].channels]
    missing = [c for c in "RGB" if c not in names]
    if missing:
        raise ExrError(f"{path}: has no {'/'.join(missing)} channel(s) (found: "
                       f"{', '.join(sorted(names)) or 'none'})")
    layers = _layer_names(names)
    part = header.parts[0]
    check_full_resolution(header)
    check_exr_memory(header, len(layers) * part.width * part.height * 12, f"{len(layers)} float32 image(s)")
    try:
        with quiet_native_output():
            if header.multipart or part.tiles is not None:
                images, metadata = _read_whole(header, max_bytes)
            else:
                images, metadata = _read_blocks(header, layers, max_bytes)
    except (RuntimeError, ValueError, OSError, TypeError) as exc:
        raise ExrError(f"{path}: truncated or corrupt EXR ({error_text(exc)})") from None
    rgb = images.pop("")
    return ExrImage(rgb=rgb, layers=images, metadata=metadata)
