"""The inference object: one call owns the whole chain, from raw radiance to denoised radiance.

sanitize (NaN/Inf/negative -> 0, counted) -> transfer function -> network, tiled under a memory
bound with margins covering the receptive field (exact, see :mod:`pipeline.tiling`) -> inverse
transfer -> clamp >= 0. Mirrors ``mi.OptixDenoiser``'s call shape (``denoiser(noisy, albedo=...,
normals=...)`` returns the same kind of object it was given) but runs on the CPU with our model.
"""
from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import DenoiserError
from pipeline.tiling import core_for_budget, run_tiled

DEFAULT_WEIGHTS = Path(__file__).resolve().parents[1] / "model" / "weights" / "default.ckpt"
DEFAULT_MAX_MEMORY_MB = 1024


@dataclass
class DenoiseResult:
    """``image``: HxWx3 float32 linear radiance >= 0; counts of sanitised input values."""

    image: np.ndarray
    nonfinite: int
    negative: int
    seconds: float
    tiles: int


def sanitize_input(rgb: np.ndarray) -> tuple[np.ndarray, int, int]:
    """HxWxC float -> float32 copy with NaN/Inf and negatives set to 0, and their counts."""
    img = np.array(rgb, dtype=np.float32, copy=True)
    bad = ~np.isfinite(img)
    nonfinite = int(bad.sum())
    img[bad] = 0.0
    neg = img < 0
    negative = int(neg.sum())
    img[neg] = 0.0
    return img, nonfinite, negative


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file (model identity in reports)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


class Denoiser:
    """A trained model ready to denoise HxWx3 linear radiance on the CPU.

    ``checkpoint``: a file written by ``train`` (default: the shipped ``model/weights``).
    ``max_memory_mb`` bounds the activations of one tile; ``threads`` sets torch's CPU threads.
    """

    def __init__(self, checkpoint: str | Path | None = None,
                 max_memory_mb: float = DEFAULT_MAX_MEMORY_MB, threads: int | None = None) -> None:
        import torch

        from model.checkpoint import load_model
        from model.transfer import get_transfer

        path = Path(checkpoint) if checkpoint is not None else DEFAULT_WEIGHTS
        if checkpoint is None and not path.exists():
            raise DenoiserError(f"{path}: no default weights are shipped yet; pass --model PATH "
                                "(a checkpoint written by `train`)")
        if max_memory_mb <= 0:
            raise DenoiserError(f"max memory must be positive, got {max_memory_mb} MB")
        if threads:
            torch.set_num_threads(int(threads))
        self.path = path
        self.model, self.config, self.meta = load_model(path)
        self.model.eval()
        self.transfer = get_transfer(self.config.transfer)
        self.max_memory_mb = float(max_memory_mb)
        # receptive-field radius: 7x7 head (3) + L 3x3 convs + 3x3 tail (1) + forward gradient (1)
        self.margin = 3 + self.config.layers + 1 + 1

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def sha256(self) -> str:
        return file_sha256(self.path)

    @property
    def needs_aovs(self) -> bool:
        """True when the model consumes albedo and normals (the render must provide them)."""
        return bool(self.config.aux_inputs)

    def bytes_per_pixel(self) -> float:
        """Peak activation bytes per input pixel (float32) of one forward pass, with headroom."""
        c = self.config
        widest = (c.init_features + c.layers * c.growth) if c.arch == "densenet" else 2 * c.init_features
        channels = 2 * widest + 2 * c.bottleneck * c.growth + 2 * c.in_channels + 16
        return 4.0 * channels * 1.5

    def core_size(self) -> int:
        """Tile core side that keeps one tile's activations under ``max_memory_mb``."""
        return core_for_budget(self.bytes_per_pixel(), self.max_memory_mb * 2**20, self.margin)

    def denoise_array(self, rgb: np.ndarray, albedo: np.ndarray | None = None,
                      normals: np.ndarray | None = None) -> DenoiseResult:
        """Denoise HxWx3 linear radiance (any float dtype); see the module doc for the chain."""
        import torch

        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or min(rgb.shape[:2]) < 1:
            raise DenoiserError(f"expected an HxWx3 image, got shape {rgb.shape}")
        start = time.perf_counter()
        clean, nonfinite, negative = sanitize_input(rgb)
        planes = [self.transfer.forward(torch.from_numpy(clean)).numpy()]
        if self.needs_aovs:
            if albedo is None or normals is None:
                raise DenoiserError(f"model {self.name} needs albedo and normals")
            for aux in (albedo, normals):
                aux = np.asarray(aux, dtype=np.float32)
                if aux.shape != rgb.shape:
                    raise DenoiserError(f"AOV shape {aux.shape} differs from image {rgb.shape}")
                planes.append(np.nan_to_num(aux, nan=0.0, posinf=0.0, neginf=0.0))
        encoded = np.concatenate(planes, axis=2)

        def net(window: np.ndarray) -> np.ndarray:
            x = torch.from_numpy(np.ascontiguousarray(window.transpose(2, 0, 1)))[None]
            with torch.inference_mode():
                return self.model(x)[0].numpy().transpose(1, 2, 0)

        core = self.core_size()
        count = [0]
        out = run_tiled(net, encoded, core, self.margin,
                        progress=lambda n, total: count.__setitem__(0, total))
        radiance = self.transfer.inverse(torch.from_numpy(np.ascontiguousarray(out))).numpy()
        radiance = np.nan_to_num(np.clip(radiance, 0.0, None), nan=0.0, posinf=0.0).astype(np.float32)
        return DenoiseResult(radiance, nonfinite, negative, time.perf_counter() - start, count[0])

    def __call__(self, noisy: Any, albedo: Any = None, normals: Any = None) -> Any:
        """Denoise a numpy array, torch tensor, ``mi.TensorXf`` or ``mi.Bitmap`` (HxWx3, or HxWx4
        with alpha kept); returns the same kind of object."""
        kind = type(noisy).__module__.split(".")[0]
        data = np.array(noisy.detach().cpu() if kind == "torch" else noisy, dtype=np.float32)
        if data.ndim != 3 or data.shape[2] not in (3, 4):
            raise DenoiserError(f"expected HxWx3 or HxWx4 input, got shape {data.shape}")
        aux = [None if a is None else np.array(a, dtype=np.float32)[..., :3] for a in (albedo, normals)]
        out = self.denoise_array(data[..., :3], *aux).image
        if data.shape[2] == 4:
            out = np.concatenate([out, data[..., 3:]], axis=2)
        if kind == "torch":
            import torch

            return torch.from_numpy(out).to(noisy.device)
        if kind in ("mitsuba", "drjit"):
            import mitsuba as mi

            return mi.Bitmap(out) if isinstance(noisy, mi.Bitmap) else mi.TensorXf(out)
        return out
