"""PFM and Radiance HDR (RGBE) images, read and written through Mitsuba's ``mi.Bitmap``.

Images are HxWx3 float32 linear radiance. A greyscale PFM (``Pf``) is read as three equal
channels. :func:`image_format` tells the formats apart by their first bytes, not by name.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from imaging.atomic_io import atomic_path
from imaging.errors import DenoiserError
from imaging.exr import EXR_MAGIC

FORMATS = ("exr", "pfm", "hdr")
_WRITE_SUFFIX = {".pfm": "pfm", ".hdr": "hdr", ".rgbe": "hdr", ".pic": "hdr"}


class ImageFormatError(DenoiserError):
    """An image file that is not one of the formats read here, or cannot be read or written."""


def image_format(path: str | Path) -> str:
    """``exr``, ``pfm`` or ``hdr`` from the file's first bytes; raises :class:`ImageFormatError`
    (naming the file) for a missing file, a folder or anything else."""
    path = Path(path)
    if not path.exists():
        raise ImageFormatError(f"{path}: file not found")
    if path.is_dir():
        raise ImageFormatError(f"{path}: is a directory, not an image file")
    with open(path, "rb") as fh:
        head = fh.read(16)
    if head.startswith(EXR_MAGIC):
        return "exr"
    if head[:2] in (b"PF", b"Pf") and head[2:3].isspace():
        return "pfm"
    if head.startswith((b"#?RADIANCE", b"#?RGBE")):
        return "hdr"
    raise ImageFormatError(f"{path}: not an OpenEXR file (nor PFM or Radiance HDR)")


def output_format(path: str | Path) -> str:
    """The format written for an output path: ``.pfm`` -> pfm, ``.hdr`` -> hdr, else exr."""
    return _WRITE_SUFFIX.get(Path(path).suffix.lower(), "exr")


def read_bitmap(path: str | Path) -> np.ndarray:
    """HxWx3 float32 pixels of a PFM or Radiance HDR file."""
    import mitsuba as mi

    try:
        data = np.array(mi.Bitmap(str(path)), dtype=np.float32)
    except RuntimeError as exc:
        raise ImageFormatError(f"{path}: cannot read ({_last_line(exc)})") from None
    if data.ndim == 2:
        data = data[:, :, None]
    if data.shape[2] == 1:
        data = np.repeat(data, 3, axis=2)
    if data.ndim != 3 or data.shape[2] < 3:
        raise ImageFormatError(f"{path}: expected an RGB or greyscale image, got shape {data.shape}")
    return np.ascontiguousarray(data[:, :, :3])


def write_bitmap(path: str | Path, rgb: np.ndarray) -> None:
    """Write HxWx3 radiance atomically as PFM or Radiance HDR (by ``path``'s suffix)."""
    import mitsuba as mi

    path = Path(path)
    fmt = output_format(path)
    if fmt == "exr":
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
