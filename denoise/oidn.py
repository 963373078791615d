"""Intel Open Image Denoise, colour only: the quality and speed anchor we compare against.

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


def oidn_denoise(rgb: np.ndarray) -> tuple[np.ndarray, float]:
    """OIDN colour-only HDR denoise of HxWx3 linear radiance; returns (image, seconds)."""
    try:
        import pyoidn
    except ImportError:
        raise DenoiserError("OIDN comparison needs the optional package pyoidn: "
                            "pip install '.[oidn]'") from None
    color = np.ascontiguousarray(np.clip(np.nan_to_num(rgb, nan=0.0, posinf=0.0), 0, None),
                                 dtype=np.float32)
    start = time.perf_counter()
    out = pyoidn.denoise(color, hdr=True)
    return np.asarray(out, dtype=np.float32), time.perf_counter() - start
