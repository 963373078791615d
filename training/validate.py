"""Validation on whole images: PSNR and relMSE of the model vs the noisy input vs OIDN, per spp.

Metrics come from :mod:`imaging.metrics` (tonemapped PSNR in dB, relMSE on linear radiance).
The noisy-input and OIDN figures do not change during training, so they are computed once per
validation image and cached. OIDN (colour only, ``pyoidn.denoise(color, hdr=True)``) is used when
``pyoidn`` imports and works; otherwise its entries are None.
"""
from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from imaging.metrics import psnr, relmse
from training.dataset import ValImage
from denoise.chain import denoise_image

Metrics = tuple[float, float]  # (PSNR dB, relMSE)


def _metrics(img: np.ndarray, ref: np.ndarray) -> Metrics:
    return psnr(img, ref), relmse(img, ref)


def _oidn_denoiser() -> Callable[[np.ndarray], np.ndarray] | None:
    try:
        import pyoidn
    except ImportError:
        return None
    return lambda color: np.asarray(pyoidn.denoise(np.ascontiguousarray(color, dtype=np.float32), hdr=True))


def _mean(values: list[float | None]) -> float | None:
    present = [v for v in values if v is not None]
    if not present:
        return None
    mean = float(np.mean(present))
    return mean if math.isfinite(mean) else None


class Validator:
    """Holds the validation images and the cached noisy/OIDN metrics of each."""

    def __init__(self, images: Sequence[ValImage], use_oidn: bool = True) -> None:
        self.images = list(images)
        self._baseline: dict[tuple[int, int], dict[str, Metrics | None]] = {}
        self._oidn = _oidn_denoiser() if use_oidn else None

    def _baselines(self, image: ValImage) -> dict[str, Metrics | None]:
        key = (image.scene, image.spp)
        if key not in self._baseline:
            oidn: Metrics | None = None
            if self._oidn is not None:
                try:
                    oidn = _metrics(self._oidn(image.noisy), image.ref)
                except (RuntimeError, ValueError, TypeError, OSError):
                    self._oidn = None  # OIDN unusable here: stop trying, report None
            self._baseline[key] = {"noisy": _metrics(image.noisy, image.ref), "oidn": oidn}
        return self._baseline[key]

    def run(self, model: torch.nn.Module, tile: int = 256) -> dict[str, Any]:
        """Denoise every validation image; return the mean metrics overall and per spp.

        Result: ``{"psnr": ours mean dB, "relmse": ours mean, "images": n, "noisy_psnr": the noisy
        inputs' mean dB, "oidn_psnr": OIDN's (None without OIDN), "per_spp": {"16": {"psnr": {"ours",
        "noisy", "oidn"}, "relmse": {...}}}}``; non-finite means become None.
        """
        rows: dict[int, dict[str, list[Metrics | None]]] = defaultdict(lambda: defaultdict(list))
        for image in self.images:
            ours = _metrics(denoise_image(model, image.noisy, image.aux, core=tile, variance=image.variance),
                            image.ref)
            rows[image.spp]["ours"].append(ours)
            for name, value in self._baselines(image).items():
                rows[image.spp][name].append(value)
        per_spp: dict[str, Any] = {}
        for spp in sorted(rows):
            per_spp[str(spp)] = {
                metric: {name: _mean([v[i] if v is not None else None for v in values])
                         for name, values in rows[spp].items()}
                for i, metric in enumerate(("psnr", "relmse"))}
        ours_all = [m for spp in rows for m in rows[spp]["ours"]]
        baseline = {name: _mean([m[0] if m is not None else None for spp in rows for m in rows[spp][name]])
                    for name in ("noisy", "oidn")}
        oidn_complete = all(m is not None for spp in rows for m in rows[spp]["oidn"])
        return {"psnr": _mean([m[0] for m in ours_all]), "relmse": _mean([m[1] for m in ours_all]),
                "images": len(ours_all), "noisy_psnr": baseline["noisy"],
                "oidn_psnr": baseline["oidn"] if oidn_complete else None, "per_spp": per_spp}
