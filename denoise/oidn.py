"""Intel Open Image Denoise: the quality and speed anchor we compare against, colour-only or
with the render's albedo and normals (OIDN's auxiliary images).

Optional (``pip install .[oidn]``, package ``pyoidn``).
"""
from __future__ import annotations

import time

import numpy as np

from imaging.errors import DenoiserError


def oidn_available() -> bool:
    try:
        import pyoidn  # noqa: F401
    except ImportError:
        return False
    return True


def _buffer(image: np.ndarray, low: float, high: float) -> np.ndarray:
    """A contiguous float32 copy of an HxWx3 image, NaN and infinities 0, clipped to [low, high]."""
    finite = np.nan_to_num(np.asarray(image, dtype=np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    return np.ascontiguousarray(np.clip(finite, low, high), dtype=np.float32)


def oidn_denoise(rgb: np.ndarray, albedo: np.ndarray | None = None,
                 normals: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """OIDN's HDR denoise of HxWx3 linear radiance; returns (image, seconds). With ``albedo`` and
    ``normals`` (HxWx3, as rendered: noisy, OIDN prefilters them) OIDN uses them as its auxiliary
    images: albedo clipped to [0, 1], normals (any space) to [-1, 1], as OIDN wants them; without
    them, colour only. Both or neither."""
    try:
        import pyoidn
    except ImportError:
        raise DenoiserError("OIDN comparison needs the optional package pyoidn: "
                            "pip install '.[oidn]'") from None
    if (albedo is None) != (normals is None):
        raise DenoiserError("OIDN's auxiliary images are albedo and normals together, not one of them")
    color = _buffer(rgb, 0.0, np.inf)
    aux = {}
    if albedo is not None and normals is not None:
        for name, image in (("albedo", albedo), ("normals", normals)):
            if np.shape(image) != color.shape:
                raise DenoiserError(f"OIDN's {name} is {np.shape(image)}, the colour {color.shape}")
        aux = {"albedo": _buffer(albedo, 0.0, 1.0), "normal": _buffer(normals, -1.0, 1.0)}
    start = time.perf_counter()
    out = pyoidn.denoise(color, **aux, hdr=True)
    return np.asarray(out, dtype=np.float32), time.perf_counter() - start
