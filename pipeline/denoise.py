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

from imaging.allocator import fix_mmap_threshold, use_huge_pages
from imaging.blocks import block_rows
from imaging.errors import DenoiserError
from imaging.hashing import file_sha256
from imaging.tiling import core_for_budget, cores_for_budget
from pipeline.noise_guard import DEFAULT_STRENGTH, guard_in_place, strength_for

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


COUNT_BYTES_PER_PIXEL = 4  # count_invalid: one boolean mask of a row block's 3 channels at a time


def count_invalid(rgb: np.ndarray, rows: int | None = None) -> tuple[int, int]:
    """Numbers of non-finite and of negative values in an HxWxC image (both are replaced by 0),
    counted ``rows`` rows at a time (None: all at once); no copy of the image is made."""
    nonfinite = negative = 0
    step = rows or max(1, rgb.shape[0])
    for y in range(0, rgb.shape[0], step):
        block = rgb[y:y + step]
        nonfinite += block.size - int(np.count_nonzero(np.isfinite(block)))
        with np.errstate(invalid="ignore"):
            negative += int(np.count_nonzero(block < 0)) - int(np.count_nonzero(np.isneginf(block)))
    return nonfinite, negative


class Denoiser:
    """A trained model ready to denoise HxWx3 linear radiance on the CPU.

    ``checkpoint``: a file written by ``train`` or a preset name (:func:`resolve_model`; default:
    the shipped ``model/weights/default.ckpt``).
    ``max_memory_mb`` bounds the scratch memory of :meth:`denoise_array` as OIDN's
    ``maxMemoryMB`` does: the memory it uses beyond the input and output images (the output,
    the guard's weight map and, asked for, the network's output). Every step works within it:
    counting invalid values and the exposure in row blocks, the network on tiles planned with
    :func:`model.infer.tile_bytes_per_pixel`, the noise guard on tiles and row blocks
    (:func:`pipeline.noise_guard.guard_in_place`). Creating a Denoiser fixes glibc's mmap
    threshold for the process (:mod:`imaging.allocator`): without it freed tile temporaries stay
    resident and the process peaks at about twice that; it also asks torch for transparent huge
    pages (:func:`imaging.allocator.use_huge_pages`: a fresh mapping faults per 2 MiB, not per 4 KiB;
    it takes effect when no large torch tensor was made before). ``threads`` sets torch's CPU threads.
    ``optimize``: run the folded, concatenation-free copy of the model
    (:mod:`model.inference_net`, :mod:`model.inference_unet`; equal up to float32 rounding)
    instead of the training module. ``skip_below``: with a variance, leave the parts of the image
    whose transfer-space noise is below this out of the network (:func:`model.infer.denoise_image`).
    ``precision``: the float format of the folded network (:mod:`model.precision`: ``auto`` is
    bfloat16 for a multi-scale network on a CPU with native bfloat16, else float32; the training
    module is always float32). ``flips``: average the network over 1, 2 or 4 mirrored copies of
    each tile (:func:`model.infer.flip_average`): 2x or 4x the network's time for ~0.1 or ~0.2 dB
    (docs/speed.md).
    """

    def __init__(self, checkpoint: str | Path | None = None,
                 max_memory_mb: float = DEFAULT_MAX_MEMORY_MB, threads: int | None = None,
                 optimize: bool = True, skip_below: float | None = None, precision: str = "auto",
                 flips: int = 1) -> None:
        import torch

        from model.checkpoint import load_model
        from model.architectures import prepare_for_inference, receptive_radius
        from model.precision import check_precision, compute_dtype

        from model.flips import check_flips

        path = resolve_model(checkpoint)
        try:
            check_precision(precision)  # before the checkpoint is read
            self.flips = check_flips(flips)
        except ValueError as exc:
            raise DenoiserError(str(exc)) from None
        if not 0 < max_memory_mb < float("inf"):  # also refuses NaN
            raise DenoiserError(f"max memory must be positive and finite, got {max_memory_mb} MB")
        if threads:
            torch.set_num_threads(int(threads))
        fix_mmap_threshold()
        use_huge_pages()  # before the first large tensor: the tiles' temporaries fault per 2 MiB
        self.path = path
        self.model, self.config, self.meta = load_model(path)
        if self.flips > 1 and self.config.aux_inputs:
            raise DenoiserError(f"{path.name}: test-time flips need a model without albedo/normal inputs")
        self.model.eval()
        self.optimize = optimize
        self.dtype = compute_dtype(precision, self.config.multiscale) if optimize else torch.float32
        self.net = prepare_for_inference(self.model, self.dtype) if optimize else self.model
        self.max_memory_mb = float(max_memory_mb)
        self.margin = receptive_radius(self.config)
        self.skip_below = skip_below

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def precision(self) -> str:
        """The float format the network computes in: ``float32`` or ``bfloat16``."""
        return str(self.dtype).removeprefix("torch.")

    @property
    def sha256(self) -> str:
        return file_sha256(self.path)

    @property
    def needs_aovs(self) -> bool:
        """True when the model consumes albedo and normals (the render must provide them)."""
        return bool(self.config.aux_inputs)

    @property
    def max_bytes(self) -> float:
        """The scratch memory bound in bytes."""
        return self.max_memory_mb * 2**20

    def bytes_per_pixel(self) -> float:
        """Peak scratch bytes per window pixel of one tile (:func:`model.infer.tile_bytes_per_pixel`)."""
        from model.infer import tile_bytes_per_pixel

        return tile_bytes_per_pixel(self.config, self.optimize, self.dtype.itemsize, self.flips)

    def core_size(self) -> int:
        """Tile core side that keeps one tile within ``max_memory_mb``: its window's pixels at
        :meth:`bytes_per_pixel`, plus the fixed cost of a forward pass."""
        from model.infer import TILE_FIXED_BYTES

        return core_for_budget(self.bytes_per_pixel(), self.max_bytes - TILE_FIXED_BYTES, self.margin)

    def cores(self, height: int, width: int) -> tuple[int, int]:
        """The (rows, columns) tile core for an HxW image: every window within ``max_memory_mb``
        as :meth:`core_size`'s, and the fewest window pixels in all (:func:`imaging.tiling.cores_for_budget`:
        with a multi-scale network's ~250-px margins, a 1080p image in two full-height strips
        processes 1.3x its pixels where square tiles under the same bound process 2.3x)."""
        from model.architectures import alignment
        from model.infer import TILE_FIXED_BYTES

        return cores_for_budget(height, width, self.bytes_per_pixel(), self.max_bytes - TILE_FIXED_BYTES,
                                self.margin, alignment(self.config), minimum=16)

    def denoise_array(self, rgb: np.ndarray, albedo: np.ndarray | None = None,
                      normals: np.ndarray | None = None, variance: np.ndarray | None = None,
                      strength: float = DEFAULT_STRENGTH, keep_network: bool = False) -> DenoiseResult:
        """Denoise HxWx3 linear radiance (any float dtype) with :func:`model.infer.denoise_image`.

        ``variance``: HxWx3 variance of ``rgb``'s Monte Carlo estimate (a render made of two
        halves, :func:`imaging.render.render_loaded`); given, the output is blended with the
        render where the render's noise does not explain the change (:mod:`pipeline.noise_guard`).
        ``keep_network``: also return the network's output before that blend (``network``).
        None of the inputs is changed or copied whole.
        """
        from model.infer import denoise_image

        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or min(rgb.shape[:2]) < 1:
            raise DenoiserError(f"expected an HxWx3 image, got shape {rgb.shape}")
        start = time.perf_counter()
        height, width = rgb.shape[:2]
        nonfinite, negative = count_invalid(rgb, block_rows(width, COUNT_BYTES_PER_PIXEL, self.max_bytes, height))
        aux = None
        if self.needs_aovs:
            if albedo is None or normals is None:
                raise DenoiserError(f"model {self.name} needs albedo and normals")
            for buffer in (albedo, normals):
                if np.shape(buffer) != rgb.shape:
                    raise DenoiserError(f"AOV shape {np.shape(buffer)} differs from image {rgb.shape}")
            aux = (np.asarray(albedo), np.asarray(normals))
        if variance is not None and np.shape(variance) != rgb.shape:
            raise DenoiserError(f"variance shape {np.shape(variance)} differs from image {rgb.shape}")
        count = [0]
        out = denoise_image(self.net, rgb, aux, self.cores(height, width),
                            progress=lambda n, total: count.__setitem__(0, total),
                            variance=variance, skip_below=self.skip_below, max_bytes=self.max_bytes,
                            flips=self.flips)
        network = None
        if keep_network:  # the guard changes ``out`` in place
            network = out.copy() if variance is not None else out
        weight = weights = None
        if variance is not None:
            weights = np.empty((height, width, 1), np.float32)
            guard_in_place(rgb, out, variance, weights, self.max_bytes, strength=strength)
            weight = float(weights.mean())
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
