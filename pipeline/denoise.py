"""The inference object: a checkpoint loaded once, applied to images of any kind and size.

The chain itself (sanitise, transfer, exact tiling under a memory bound, inverse) is
:func:`model.infer.denoise_image`; this object counts the invalid input values it replaced, picks
the tile size from the memory budget and converts between array kinds. Mirrors ``mi.OptixDenoiser``'s call shape (``denoiser(noisy, albedo=...,
normals=...)`` returns the same kind of object it was given) but runs on the CPU with our model.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from imaging.errors import DenoiserError
from imaging.hashing import file_sha256
from imaging.tiling import core_for_budget, run_tiled
from pipeline.noise_guard import DEFAULT_STRENGTH, blend, blend_weight, strength_for

if TYPE_CHECKING:
    from imaging.render import RenderResult

WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "model" / "weights"
DEFAULT_WEIGHTS = WEIGHTS_DIR / "default.ckpt"
DEFAULT_MAX_MEMORY_MB = 1024


def resolve_model(name: str | Path | None) -> Path:
    """Checkpoint file of a ``--model`` value: None -> the shipped default, a preset name (``fast``,
    ``balanced``, ``high``) -> ``model/weights/<name>.ckpt``, anything else -> a path.

    Raises :class:`DenoiserError` naming the file when the default or a preset's weights are missing.
    """
    from model.config import PRESETS

    if name is None:
        if not DEFAULT_WEIGHTS.exists():
            raise DenoiserError(f"{DEFAULT_WEIGHTS}: no default weights are shipped yet; pass --model "
                                "PATH (a checkpoint written by `train`)")
        return DEFAULT_WEIGHTS
    if str(name) in PRESETS and not Path(name).exists():
        path = WEIGHTS_DIR / f"{name}.ckpt"
        if not path.exists():
            raise DenoiserError(f"{path}: no weights for model preset '{name}' yet (train them, or pass "
                                "a checkpoint file)")
        return path
    return Path(name)


@dataclass
class DenoiseResult:
    """``image``: HxWx3 float32 linear radiance >= 0; counts of sanitised input values."""

    image: np.ndarray
    nonfinite: int
    negative: int
    seconds: float
    tiles: int
    guard_weight: float | None = None  # noise guard's mean weight of the denoiser (None: no guard)
    guard_map: np.ndarray | None = None  # HxW float32 in [0, 1]: that weight per pixel
    network: np.ndarray | None = None  # the network's output before the guard (``keep_network``)


def count_invalid(rgb: np.ndarray) -> tuple[int, int]:
    """Numbers of non-finite and of negative values in an image (both are replaced by 0)."""
    nonfinite = rgb.size - int(np.count_nonzero(np.isfinite(rgb)))
    with np.errstate(invalid="ignore"):  # no copies: this runs on 8K images
        negative = int(np.count_nonzero(rgb < 0)) - int(np.count_nonzero(np.isneginf(rgb)))
    return nonfinite, negative


class Denoiser:
    """A trained model ready to denoise HxWx3 linear radiance on the CPU.

    ``checkpoint``: a file written by ``train`` or a preset name (:func:`resolve_model`; default:
    the shipped ``model/weights/default.ckpt``).
    ``max_memory_mb`` bounds the activations of one tile; ``threads`` sets torch's CPU threads.
    ``optimize``: run the folded, concatenation-free copy of the model
    (:mod:`model.inference_net`, :mod:`model.inference_unet`; equal up to float32 rounding)
    instead of the training module. ``skip_below``: with a variance, leave the parts of the image
    whose transfer-space noise is below this out of the network (:func:`model.infer.denoise_image`).
    """

    def __init__(self, checkpoint: str | Path | None = None,
                 max_memory_mb: float = DEFAULT_MAX_MEMORY_MB, threads: int | None = None,
                 optimize: bool = True, skip_below: float | None = None) -> None:
        import torch

        from model.checkpoint import load_model
        from model.architectures import prepare_for_inference, receptive_radius

        path = resolve_model(checkpoint)
        if not 0 < max_memory_mb < float("inf"):  # also refuses NaN
            raise DenoiserError(f"max memory must be positive and finite, got {max_memory_mb} MB")
        if threads:
            torch.set_num_threads(int(threads))
        self.path = path
        self.model, self.config, self.meta = load_model(path)
        self.model.eval()
        self.net = prepare_for_inference(self.model) if optimize else self.model
        self.max_memory_mb = float(max_memory_mb)
        self.margin = receptive_radius(self.config)
        self.skip_below = skip_below

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
                      normals: np.ndarray | None = None, variance: np.ndarray | None = None,
                      strength: float = DEFAULT_STRENGTH, keep_network: bool = False) -> DenoiseResult:
        """Denoise HxWx3 linear radiance (any float dtype) with :func:`model.infer.denoise_image`.

        ``variance``: HxWx3 variance of ``rgb``'s Monte Carlo estimate (a render made of two
        halves, :func:`imaging.render.render_loaded`); given, the output is blended with the
        render where the render's noise does not explain the change (:mod:`pipeline.noise_guard`).
        ``keep_network``: also return the network's output before that blend (``network``).
        """
        from model.infer import denoise_image

        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or min(rgb.shape[:2]) < 1:
            raise DenoiserError(f"expected an HxWx3 image, got shape {rgb.shape}")
        start = time.perf_counter()
        nonfinite, negative = count_invalid(rgb)
        aux = None
        if self.needs_aovs:
            if albedo is None or normals is None:
                raise DenoiserError(f"model {self.name} needs albedo and normals")
            for buffer in (albedo, normals):
                if np.shape(buffer) != rgb.shape:
                    raise DenoiserError(f"AOV shape {np.shape(buffer)} differs from image {rgb.shape}")
            aux = np.concatenate([np.asarray(albedo, np.float32), np.asarray(normals, np.float32)], axis=2)
        if variance is not None and np.shape(variance) != rgb.shape:
            raise DenoiserError(f"variance shape {np.shape(variance)} differs from image {rgb.shape}")
        count = [0]
        out = denoise_image(self.net, rgb, aux, self.core_size(),
                            progress=lambda n, total: count.__setitem__(0, total),
                            variance=variance, skip_below=self.skip_below)
        weight = weights = None
        network = out if keep_network else None
        if variance is not None:
            with np.errstate(invalid="ignore"):
                clean = np.clip(np.nan_to_num(np.asarray(rgb, np.float32), nan=0.0, posinf=0.0,
                                              neginf=0.0), 0.0, None)
            weights = blend_weight(clean, out, np.asarray(variance, np.float32), strength=strength)
            out, weight = blend(clean, out, weights), float(weights.mean())
        return DenoiseResult(out, nonfinite, negative, time.perf_counter() - start, count[0], weight,
                             None if weights is None else weights[:, :, 0], network)

    def denoise_render(self, render: RenderResult, keep_network: bool = False) -> DenoiseResult:
        """Denoise a render of :mod:`imaging.render` with what it carries: its AOVs and, for a
        render made in two halves, its variance (the model's noise input, if it has one) and the
        noise guard at the strength for its spp. ``keep_network`` as in :meth:`denoise_array`."""
        return self.denoise_array(render.rgb, render.aovs.get("albedo"), render.aovs.get("sh_normal"),
                                  render.variance, strength_for(render.spp), keep_network)

    def __call__(self, noisy: Any, albedo: Any = None, normals: Any = None) -> Any:
        """Denoise a numpy array, torch tensor, ``mi.TensorXf`` or ``mi.Bitmap`` (HxWx3, or HxWx4
        with alpha kept); returns the same kind of object."""
        kind = type(noisy).__module__.split(".")[0]
        data = np.array(noisy.detach().cpu().numpy() if kind == "torch" else noisy, dtype=np.float32)
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
