"""Display images: tonemapped 8-bit sRGB-ish PNGs of linear radiance (x/(1+x), gamma 1/2.2)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from imaging.atomic_io import atomic_path
from imaging.metrics import tonemap


def to_display(rgb: np.ndarray) -> np.ndarray:
    """HxWx3 linear radiance (>=0) -> HxWx3 uint8 with the metrics' tonemap."""
    return np.round(tonemap(np.nan_to_num(rgb, nan=0.0, posinf=0.0)) * 255.0).astype(np.uint8)


def save_png(path: str | Path, image: np.ndarray) -> None:
    """Write an HxWx3 image atomically: uint8 as is, float as linear radiance (tonemapped)."""
    data = image if image.dtype == np.uint8 else to_display(image)
    with atomic_path(path) as tmp:
        Image.fromarray(data).save(tmp, format="PNG")
