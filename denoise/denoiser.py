"""The inference object: a checkpoint loaded once, applied to images of any kind and size.

The chain itself (sanitise, transfer, exact tiling under a memory bound, inverse) is
:func:`denoise.chain.denoise_image`; this object counts the invalid input values it replaced, picks
the tile size from the memory budget and converts between array kinds. Mirrors ``mi.OptixDenoiser``'s call shape (``denoiser(noisy, albedo=...,
normals=...)`` returns the same kind of object it was given) but runs our networks (on the CPU unless
``device`` says otherwise).
"""
from __future__ import annotations

import functools
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from denoise.allocator import fix_mmap_threshold, release_free_memory, use_huge_pages
from imaging.blocks import block_rows, parallel_map, pass_workers
from imaging.errors import DenoiserError
from imaging.hashing import file_sha256
from denoise.tiling import band_cores, core_for_budget, cores_for_budget
from denoise.energy import EnergySettings, correct_in_place
from denoise.ensemble import DEFAULT_RADIUS, denoise_combined
from denoise.image_noise import NoiseStats, noise_stats
from denoise.noise_guard import DEFAULT_STRENGTH, guard_in_place, strength_for
from model.registry import SEPARATOR, Choice, Selection, range_suffix, registry
from model.checkpoint import pixel_filter

if TYPE_CHECKING:
    from rendering.render import RenderResult

DEFAULT_MAX_MEMORY_MB = 1024
OUTPUT_BYTES_PER_PIXEL = 12  # a network's HxWx3 float32 output
ModelArg = str | Path | Sequence[str | Path] | None  # what ``Denoiser(...)`` and ``--model`` take


def select(model: ModelArg) -> Selection:
    """The :class:`model.registry.Selection` of a ``--model`` value (None: the registry's default;
    a list or tuple: its items are the members)."""
    if isinstance(model, (list, tuple)):
        return registry().select_list([str(m) for m in model])
    return registry().select(None if model is None else str(model))


@dataclass
class Network:
    """One loaded checkpoint: its file, training module, config, metadata, the network that runs
    (folded unless ``optimize`` is off), its float format and its receptive radius in pixels.
    ``min_spp`` / ``max_spp``: the fewest / most spp of the renders it runs on: those it was trained
    on (``train --min-spp`` / ``--max-spp``), within the range its ensemble spec gives it (``limit``,
    ``MODEL:LO-HI``); 0: no limit."""

    path: Path
    model: Any
    config: Any
    meta: dict[str, Any]
    net: Any
    dtype: Any
    margin: int
    limit: tuple[int, int] = (0, 0)
    given: str = ""  # the name it was given by: a registry checkpoint, an earlier name or a path

    @classmethod
    def load(cls, path: Path, optimize: bool, precision: str, limit: tuple[int, int] = (0, 0),
             given: str = "") -> Network:
        import torch

        from model.architectures import receptive_radius

        from denoise.folded import prepare_for_inference
        from model.checkpoint import load_model
        from denoise.precision import compute_dtype

        model, config, meta = load_model(path)
        model.eval()
        member = cls(path, model, config, meta, model, torch.float32, receptive_radius(config), limit,
                     given or str(path))
        if optimize:
            member.dtype = compute_dtype(precision, config.multiscale, max_spp=member.max_spp)
            member.net = prepare_for_inference(model, member.dtype)
        return member

    @property
    def precision(self) -> str:
        """The float format its network computes in: ``float32`` or ``bfloat16``."""
        return str(self.dtype).removeprefix("torch.")

    @functools.cached_property
    def sha256(self) -> str:
        """Its checkpoint file's SHA-256 (hashed once)."""
        return file_sha256(self.path)

    @property
    def max_spp(self) -> int:
        ends = [n for n in (int((self.meta.get("train_config") or {}).get("max_spp") or 0), self.limit[1]) if n]
        return min(ends, default=0)

    @property
    def min_spp(self) -> int:
        return max(int((self.meta.get("train_config") or {}).get("min_spp") or 0), self.limit[0])

    @property
    def label(self) -> str:
        """Its file's stem, with the range its spec limits it to (``unet-l-allspp:17-``)."""
        return self.path.stem + range_suffix(*self.limit)

    @property
    def spec(self) -> str:
        """The name it was given by, with the range its spec limits it to: what loads it again."""
        return f"{self.given}{range_suffix(*self.limit)}"

    @property
    def meta_filter(self) -> str:
        """The pixel filter of its training renders, as its checkpoint records it (box when absent)."""
        return pixel_filter(self.meta)["type"]

    def covers(self, spp: int | None) -> bool:
        """True if it runs on renders of ``spp`` samples per pixel: always for a model trained on every
        spp and not limited; else only where ``spp`` is known to be within ``min_spp`` .. ``max_spp``."""
        if not self.min_spp and not self.max_spp:
            return True
        return spp is not None and self.min_spp <= spp and (not self.max_spp or spp <= self.max_spp)


@dataclass(frozen=True)
class EnsemblePlan:
    """How an ensemble's members denoise an image (:meth:`Denoiser.ensemble_plan`): in bands of
    ``rows`` rows, each member on its own tiles (``cores``, (rows, columns) per member), their
    outputs combined within ``combine_bytes`` of scratch."""

    rows: int
    cores: tuple[tuple[int, int], ...]
    combine_bytes: float


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
    energy_factor: float | None = None  # mean factor of the energy correction (None: not applied)
    network: np.ndarray | None = None  # the network's output before the guard (``keep_network``)
    models: tuple[str, ...] = ()  # the checkpoints' stems that ran (an ensemble: :meth:`Denoiser.active`)
    choice: str = ""  # the registry entry or spec that ran (``auto``: the entry it chose)
    notes: tuple[str, ...] = ()  # what the caller should know: an unknown spp, filtered noise
    noise: NoiseStats | None = None  # what the image tells of its own noise (:mod:`denoise.image_noise`)
    precisions: tuple[str, ...] = ()  # the float format of each of ``models``

    @property
    def precision(self) -> str:
        """The float format of the networks that ran (``+``-joined where they differ)."""
        return joined_formats(self.precisions)

    def energy_record(self) -> dict[str, float] | None:
        """The energy correction's entry of metrics.json and of ``denoise``'s report (None: off)."""
        return None if self.energy_factor is None else {"mean_factor": self.energy_factor}


def member_precision(own: str | None, asked: str) -> str:
    """The float format a member loads in: the caller's ``asked`` one (``--precision``), else under
    ``auto`` the member's ``own`` (``NAME@FORMAT``), where ``bfloat16`` holds only on a CPU that computes
    it natively (emulated it is slower than float32: :mod:`denoise.precision`)."""
    from denoise.precision import native_bfloat16

    if asked != "auto" or not own or (own == "bfloat16" and not native_bfloat16()):
        return asked
    return own


def joined_formats(formats: Sequence[str]) -> str:
    """One float format where all networks share it, else each joined by ``+`` ("" for none)."""
    return "".join(formats[:1]) if len(set(formats)) <= 1 else SEPARATOR.join(formats)


def _float_array(image: Any) -> np.ndarray:
    """A float32 copy of an array, a torch tensor (any device, with or without a gradient), a
    ``mi.TensorXf`` or a ``mi.Bitmap``."""
    if type(image).__module__.split(".")[0] == "torch":
        image = image.detach().cpu().numpy()
    return np.array(image, dtype=np.float32)


COUNT_BYTES_PER_PIXEL = 4  # count_invalid: one boolean mask of a row block's 3 channels at a time


def count_invalid(rgb: np.ndarray, rows: int | None = None, workers: int = 1) -> tuple[int, int]:
    """Numbers of non-finite and of negative values in an HxWxC image (both are replaced by 0),
    counted ``rows`` rows at a time (None: all at once), ``workers`` blocks at a time on threads
    (:func:`imaging.blocks.parallel_map`); no copy of the image is made."""
    def block(y: int) -> tuple[int, int]:
        part = rgb[y:y + step]
        with np.errstate(invalid="ignore"):
            negative = int(np.count_nonzero(part < 0)) - int(np.count_nonzero(np.isneginf(part)))
        return part.size - int(np.count_nonzero(np.isfinite(part))), negative

    step = rows or max(1, rgb.shape[0])
    counts = parallel_map(block, range(0, rgb.shape[0], step), workers)
    return sum(c[0] for c in counts), sum(c[1] for c in counts)


class Denoiser:
    """The shipped models, or any checkpoint, ready to denoise HxWx3 linear radiance (on ``device``,
    the CPU by default).

    ``model``: a registry name (``fast``, ``balanced``, ``high``, ``auto``: :mod:`model.registry`;
    None: the registry's default), a checkpoint file written by ``train``, or an expert spec
    ``A+B[+...]`` (or a list of its members): every network that runs on a render denoises it and
    :mod:`denoise.ensemble` combines their outputs (weighted by their estimated error where a
    variance is given, else their mean) before the guard. Which networks run depends on the
    render's spp (:meth:`active`). ``path``, ``model``, ``config``, ``meta``, ``net`` and ``dtype``
    are the first network's; ``members`` holds every network loaded, each once.
    ``max_memory_mb`` bounds the scratch memory of :meth:`denoise_array` as OIDN's
    ``maxMemoryMB`` does: the memory it uses beyond the input images and the output (asked for,
    the network's output is one more image). Every step works within it: counting invalid values
    and the exposure in row blocks, the network on tiles planned with
    :func:`denoise.chain.tile_bytes_per_pixel` beside the networks' fixed cost
    (:meth:`fixed_bytes`), an ensemble in bands whose members' outputs and weights count against
    the budget (:meth:`ensemble_plan`), the noise guard on tiles and row blocks
    (:func:`denoise.noise_guard.guard_in_place`) beside its weight map, the energy correction in
    row blocks; freed heap memory is handed back between the steps
    (:func:`denoise.allocator.release_free_memory`). Creating a Denoiser fixes glibc's mmap
    threshold for the process (:mod:`denoise.allocator`): without it freed tile temporaries stay
    resident and the process peaks at about twice that; with ``huge_pages`` it also asks torch for
    transparent huge pages (:func:`denoise.allocator.use_huge_pages`: a fresh mapping faults per 2 MiB,
    not per 4 KiB, faster from the second call on, slower for the first; it takes effect when no
    large torch tensor was made before). ``threads`` sets torch's CPU threads.
    ``optimize``: run the folded, concatenation-free copy of the model
    (:mod:`denoise.inference_net`, :mod:`denoise.inference_unet`; equal up to float32 rounding)
    instead of the training module. ``skip_below``: with a variance, leave the parts of the image
    whose transfer-space noise is below this out of the network (:func:`denoise.chain.denoise_image`).
    ``precision``: the float format of the folded network (:mod:`denoise.precision`: ``auto`` is
    bfloat16 for a multi-scale network on a CPU with native bfloat16, else float32; the training
    module is always float32). ``flips``: average the network over 1, 2 or 4 mirrored copies of
    each tile (:func:`denoise.chain.flip_average`): 2x or 4x the network's time for ~0.1 or ~0.2 dB.
    ``energy``: match the output's local means to the render's where they differ by more than its
    noise, after the guard (:mod:`denoise.energy`; None: off). ``device``: where the networks run
    (:func:`model.device.choose_device`: ``cpu``, ``cuda``, ``auto``); on a GPU each member runs its
    training module in float32 (``optimize`` and ``precision`` apply to the CPU).
    """

    def __init__(self, model: ModelArg = None,
                 max_memory_mb: float = DEFAULT_MAX_MEMORY_MB, threads: int | None = None,
                 optimize: bool = True, skip_below: float | None = None, precision: str = "auto",
                 flips: int = 1, energy: EnergySettings | None = EnergySettings(), device: str = "cpu",
                 huge_pages: bool = True) -> None:
        import torch

        from denoise.flips import check_flips
        from denoise.precision import check_precision
        from model.device import choose_device

        try:
            check_precision(precision)  # before the checkpoint is read
            self.flips = check_flips(flips)
        except ValueError as exc:
            raise DenoiserError(str(exc)) from None
        if not 0 < max_memory_mb < float("inf"):  # also refuses NaN
            raise DenoiserError(f"max memory must be positive and finite, got {max_memory_mb} MB")
        self.selection = select(model)  # every member's file known before any load
        for member in self.selection.members:  # NAME@FORMAT: a format this module knows, before any load
            try:
                check_precision(member.precision or "auto")
            except ValueError as exc:
                raise DenoiserError(f"{member.spec}: {exc}") from None
        if threads:
            torch.set_num_threads(int(threads))
        fix_mmap_threshold()
        use_huge_pages(huge_pages)  # before the first large tensor: the tiles' temporaries fault per 2 MiB
        self.optimize = optimize
        self._networks = {m: Network.load(m.path, optimize, member_precision(m.precision, precision), (m.lo, m.hi),
                                          m.given)
                          for m in self.selection.members}
        self.members = list(self._networks.values())
        self.device = choose_device(device)
        if self.device.type != "cpu":  # the folded copies are CPU kernels: a GPU runs the module itself
            for member in self.members:
                member.net, member.dtype = member.model.to(self.device), torch.float32
        for member in self.members:
            if member.max_spp and member.min_spp > member.max_spp:
                raise DenoiserError(f"{member.label}: the range leaves out every spp {member.path.name} "
                                    "was trained on (it would never run)")
            if self.flips > 1 and member.config.aux_inputs:
                raise DenoiserError(f"{member.path.name}: test-time flips need a model without albedo/normal inputs")
        first = self.members[0]  # what a single model's callers read: its file, config and network
        self.path, self.model, self.config, self.meta = first.path, first.model, first.config, first.meta
        self.dtype, self.net = first.dtype, first.net
        self.max_memory_mb = float(max_memory_mb)
        self.margin = max(m.margin for m in self.members)
        self.skip_below = skip_below
        self.energy = energy

    @property
    def name(self) -> str:
        """What ``--model`` accepts back: the registry name (``high``), else each member as it was
        given (a registry checkpoint, an earlier name or a path) with its spp range, joined by ``+``."""
        if self.registered:
            return self.selection.name
        return SEPARATOR.join(m.spec for m in self.selection.choices[0].by_spp)

    @property
    def registered(self) -> bool:
        """True for a registry name (an entry or ``auto``), False for a file or an expert spec."""
        return self.selection.entry

    @property
    def label(self) -> str:
        """The short name: the registry name, else each member's file stem with its spp range
        (``unet-m-k5-lowspp:-16+unet-l-allspp:17-``)."""
        if self.registered:
            return self.selection.name
        return SEPARATOR.join(self._networks[m].label for m in self.selection.choices[0].by_spp)

    @property
    def precision(self) -> str:
        """The float format the network computes in: ``float32`` or ``bfloat16`` (an ensemble's
        members' joined by ``+`` where they differ)."""
        return joined_formats([m.precision for m in self.members])

    @property
    def sha256(self) -> str:
        """The checkpoint file's SHA-256 (an ensemble's members' joined by ``+``)."""
        return SEPARATOR.join(m.sha256 for m in self.members)

    @property
    def needs_aovs(self) -> bool:
        """True when a model consumes albedo and normals (the render must provide them)."""
        return any(m.config.aux_inputs for m in self.members)

    def choice(self, spp: int | None) -> Choice:
        """The entry or spec that denoises a render of ``spp`` samples per pixel (None: unknown):
        the one named, or for ``auto`` the entry :meth:`model.registry.Registry.auto_entry` picks."""
        choices = self.selection.choices
        if self.selection.auto:
            name = registry().auto_entry(spp)
            return next(c for c in choices if c.name == name)
        return choices[0]

    def active(self, spp: int | None, level: float = float("nan")) -> list[Network]:
        """The networks that denoise a render of ``spp`` samples per pixel (None: unknown), from
        :meth:`choice`: with the spp known, its members meant for renders of that many spp
        (:meth:`Network.covers`), else its first member alone; with the spp unknown, the entry's
        own choice for an image of that noise ``level`` (:mod:`denoise.image_noise`; NaN: a flat
        image), or for a spec those trained on every spp and not limited, else its first member."""
        choice = self.choice(spp)
        unknown = choice.for_unknown_spp(level) if spp is None else None
        if unknown:
            return [self._networks[m] for m in unknown]
        networks = [self._networks[m] for m in choice.by_spp]
        return [n for n in networks if n.covers(spp)] or [networks[0]]

    def ensemble_record(self) -> dict[str, Any]:
        """For several networks, what a run's record adds beside the first network's config:
        ``{"members": [{"path", "sha256", "step", "precision", "min_spp", "max_spp", "config"}...]}``;
        ``{}`` for one network."""
        if len(self.members) == 1:
            return {}
        return {"members": [{"path": str(m.path), "sha256": m.sha256, "step": m.meta.get("step"),
                             "precision": m.precision, "min_spp": m.min_spp, "max_spp": m.max_spp,
                             "config": m.config.to_dict()} for m in self.members]}

    @property
    def max_bytes(self) -> float:
        """The scratch memory bound in bytes."""
        return self.max_memory_mb * 2**20

    def bytes_per_pixel(self, member: Network | None = None) -> float:
        """Peak scratch bytes per window pixel of one tile of ``member`` (default: the first model;
        :func:`denoise.chain.tile_bytes_per_pixel`)."""
        from denoise.chain import tile_bytes_per_pixel

        m = member or self.members[0]
        return tile_bytes_per_pixel(m.config, self.optimize, m.dtype.itemsize, self.flips)

    def fixed_bytes(self, members: Sequence[Network]) -> float:
        """The fixed cost of running ``members`` on tiles, beside their pixels: :data:`denoise.chain.TILE_FIXED_BYTES`,
        and :data:`denoise.chain.NETWORK_FIXED_BYTES` for each further different network among them
        (its config and float format: oneDNN keeps each one's kernels, shared by networks of the
        same shape)."""
        from denoise.chain import NETWORK_FIXED_BYTES, TILE_FIXED_BYTES

        return TILE_FIXED_BYTES + NETWORK_FIXED_BYTES * (len({(repr(m.config), str(m.dtype)) for m in members}) - 1)

    def core_size(self, member: Network | None = None) -> int:
        """Tile core side that keeps one tile within ``max_memory_mb``: its window's pixels at
        :meth:`bytes_per_pixel`, plus the fixed cost of a forward pass."""
        from denoise.chain import TILE_FIXED_BYTES

        m = member or self.members[0]
        return core_for_budget(self.bytes_per_pixel(m), self.max_bytes - TILE_FIXED_BYTES, m.margin)

    def cores(self, height: int, width: int, member: Network | None = None) -> tuple[int, int]:
        """The (rows, columns) tile core for an HxW image: every window within ``max_memory_mb``
        as :meth:`core_size`'s, and the fewest window pixels in all (:func:`denoise.tiling.cores_for_budget`:
        with a multi-scale network's ~250-px margins, a 1080p image in two full-height strips
        processes 1.3x its pixels where square tiles under the same bound process 2.3x)."""
        from model.architectures import alignment
        from denoise.chain import TILE_FIXED_BYTES

        m = member or self.members[0]
        return cores_for_budget(height, width, self.bytes_per_pixel(m), self.max_bytes - TILE_FIXED_BYTES,
                                m.margin, alignment(m.config), minimum=16)

    def ensemble_plan(self, height: int, width: int, members: Sequence[Network], weighted: bool) -> EnsemblePlan:
        """How ``members`` (several) denoise an HxW image within ``max_memory_mb``
        (:func:`denoise.ensemble.denoise_combined`): in full-width bands, each member on its own
        tiles over a band (and the combination's context rows, ``weighted``: the outputs are
        weighted by their estimated error), then combined there. Every member's output over the band
        is held (beside the result; one band of the whole image: all but the first, which becomes
        the result), and while they are combined their weights; the tiles get what that and the
        networks' fixed cost (:meth:`fixed_bytes`) leave of the budget. Of the band heights tried
        (the whole image, multiples of the members' alignment) the one that processes the fewest
        window pixels, each member's weighted by its :meth:`bytes_per_pixel`; where none fits, the
        thinnest band and the members' smallest tiles."""
        from model.architectures import alignment
        from denoise.ensemble import context_rows, weight_bytes_per_pixel

        k, align = len(members), max(alignment(m.config) for m in members)
        context = context_rows(weighted, align)
        fixed = self.fixed_bytes(members)
        steps = (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128)
        candidates = [height] + [align * j for j in steps if align * j < height]
        best: tuple[float, EnsemblePlan] | None = None
        for rows in candidates:
            rect = min(height, rows + 2 * context)
            held = OUTPUT_BYTES_PER_PIXEL * (k - 1 if rows >= height else k) * rect * width
            combine_bytes = self.max_bytes - fixed - held - (4 * k * rect * width if weighted else 0)
            if combine_bytes < weight_bytes_per_pixel(k) * (16 + 2 * DEFAULT_RADIUS) ** 2:
                continue
            work, cores = 0.0, []
            for m in members:
                bpp = self.bytes_per_pixel(m)
                plan = band_cores(rect, height, width, bpp, self.max_bytes - fixed - held, m.margin,
                                  alignment(m.config))
                if plan is None:
                    break
                cores.append(plan[0])
                work += bpp * plan[1] * -(-height // rows)
            else:
                if best is None or work < best[0]:
                    best = (work, EnsemblePlan(rows, tuple(cores), combine_bytes))
        if best is not None:
            return best[1]
        return EnsemblePlan(min(height, align), tuple((align, align) for _ in members), self.max_bytes / 4)

    def denoise_array(self, rgb: np.ndarray, albedo: np.ndarray | None = None,
                      normals: np.ndarray | None = None, variance: np.ndarray | None = None,
                      strength: float | None = None, keep_network: bool = False,
                      spp: int | None = None, pixel_filter: str | None = None,
                      to_camera: np.ndarray | None = None) -> DenoiseResult:
        """Denoise HxWx3 linear radiance (any float dtype) with :func:`denoise.chain.denoise_image`.

        ``normals`` are world-space (Mitsuba's ``sh_normal``); a model that takes them in the
        camera's frame (``aux_normals="camera"``) needs ``to_camera``, the 3x3 rotation of
        :func:`rendering.camera.sensor_rotation` (a :class:`DenoiserError` without it).
        ``variance``: HxWx3 variance of ``rgb``'s Monte Carlo estimate (a render made of two
        halves, :func:`rendering.render.render_loaded`); given, the output is blended with the
        render where the render's noise does not explain the change (:mod:`denoise.noise_guard`).
        ``strength``: the guard's strength; None: the one for the render's spp
        (:func:`denoise.noise_guard.strength_for`, as :meth:`denoise_render` and ``render-and-denoise``
        use), 1 where the spp is unknown. ``keep_network``: also return the network's output before that blend (``network``).
        ``spp``: the render's samples per pixel, where known: only the networks meant for such
        renders run (:meth:`active`; unknown: the entry's choice for that case, named in the
        result's ``notes``). The output's local means are then matched to the render's (``energy``,
        :mod:`denoise.energy`). The result's ``noise`` says what the image tells of its own noise
        (:mod:`denoise.image_noise`); noise spread over neighbouring pixels by a pixel filter other
        than the box the shipped models were trained on is named in ``notes`` (``pixel_filter``: the
        render's filter where it is known, e.g. ``"box"``). None of the inputs is changed or copied whole.
        """
        import torch

        from denoise.chain import ChainRun, denoise_image, image_exposure

        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or min(rgb.shape[:2]) < 1:
            raise DenoiserError(f"expected an HxWx3 image, got shape {rgb.shape}")
        if spp is not None and (isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1):
            raise DenoiserError(f"spp must be a positive integer or None (unknown), got {spp!r}")
        start = time.perf_counter()
        height, width = rgb.shape[:2]
        workers = pass_workers(height * width, torch.get_num_threads())  # threads of the numpy passes
        nonfinite, negative = count_invalid(rgb, block_rows(width, COUNT_BYTES_PER_PIXEL, self.max_bytes / workers,
                                                            -(-height // workers)), workers)
        aux = None
        if self.needs_aovs:
            if albedo is None or normals is None:
                raise DenoiserError(f"model {self.name} needs albedo and normals")
            for buffer in (albedo, normals):
                if np.shape(buffer) != rgb.shape:
                    raise DenoiserError(f"AOV shape {np.shape(buffer)} differs from image {rgb.shape}")
            aux = (np.asarray(albedo), np.asarray(normals))
            if to_camera is None and any(m.config.aux_normals == "camera" for m in self.members):
                raise DenoiserError(f"model {self.name} takes normals in the camera's frame: give the camera's "
                                    "rotation (to_camera; a file holds none)")
        if variance is not None and np.shape(variance) != rgb.shape:
            raise DenoiserError(f"variance shape {np.shape(variance)} differs from image {rgb.shape}")
        count = [0]
        exposure = image_exposure(rgb, self.max_bytes)  # once for every member and the energy correction

        def rotation(member: Network) -> np.ndarray | None:
            camera = member.config.aux_inputs and member.config.aux_normals == "camera"
            return to_camera if camera else None

        noise = noise_stats(rgb)
        release_free_memory()  # each step's freed blocks leave the resident set before the next one
        members = self.active(spp, noise.level)
        choice = self.choice(spp).name
        notes = self.notes(spp, choice, members, noise, pixel_filter)
        if len(members) == 1:
            out = denoise_image(members[0].net, rgb, aux, self.cores(height, width, members[0]),
                                progress=lambda n, total: count.__setitem__(0, count[0] + (n == total) * total),
                                variance=variance, skip_below=self.skip_below, max_bytes=self.max_bytes,
                                flips=self.flips, exposure=exposure, normals_rotation=rotation(members[0]))
        else:  # band by band: no further member's output is held whole unless the budget allows
            plan = self.ensemble_plan(height, width, members, variance is not None)
            runs = [ChainRun(m.net, rgb, aux, variance, self.skip_below, self.max_bytes, self.flips, exposure,
                             rotation(m)) for m in members]
            out = denoise_combined(runs, rgb, variance, plan.rows, plan.cores, plan.combine_bytes)
            count[0] = sum(r.windows for r in runs)
        release_free_memory()
        network = None
        if keep_network:  # the guard and the energy correction change ``out`` in place
            network = out.copy() if variance is not None or self.energy is not None else out
        # what the passes after the networks may use: the budget less what the networks left resident
        # (their kernels) and the guard's weight map (scratch too: ``denoise`` never shows it)
        after = max(self.max_bytes / 8,  # (a budget smaller than that is not kept anyway)
                    self.max_bytes - self.fixed_bytes(members) - (4 * height * width if variance is not None else 0))
        weight = weights = None
        if variance is not None:
            if strength is None:
                strength = strength_for(spp) if spp is not None else DEFAULT_STRENGTH
            weights = np.empty((height, width, 1), np.float32)
            guard_in_place(rgb, out, variance, weights, after, strength=strength, workers=workers)
            weight = float(weights.mean())
            release_free_memory()
        factor = None
        if self.energy is not None:
            factor = correct_in_place(rgb, out, after, exposure, self.energy, workers)
        return DenoiseResult(out, nonfinite, negative, time.perf_counter() - start, count[0], weight,
                             None if weights is None else weights[:, :, 0], factor, network,
                             tuple(m.path.stem for m in members), choice, notes, noise,
                             tuple(m.precision for m in members))

    def notes(self, spp: int | None, choice: str, members: Sequence[Network], noise: NoiseStats,
              pixel_filter: str | None = None) -> tuple[str, ...]:
        """What a caller should be told of one call: the spp unknown (and what ran instead of the
        full path); a render whose pixel filter (``pixel_filter``; None: unknown, then judged from
        the image's ``noise``) is not the one the networks were trained on."""
        notes = []
        if spp is None and (self.registered or len(self.choice(None).by_spp) > 1):
            ran = SEPARATOR.join(m.label for m in members)
            notes.append(f"spp unknown: ran {ran} ({choice}'s choice for an image of unknown spp and noise "
                         f"level {noise.level:.3f}); give the render's spp (--spp N, or spp= in Python) for "
                         "the networks meant for it")
        trained = sorted({m.meta_filter for m in members})
        if pixel_filter is not None:
            if trained != [pixel_filter]:
                notes.append(f"the render's pixel filter is {pixel_filter}; the networks were trained on "
                             f"{'/'.join(trained)}-filtered renders: expect less denoising")
        elif noise.filtered and trained == ["box"]:
            notes.append(f"the noise looks spread over neighbouring pixels (Nyquist ratio {noise.ratio:.2f}; "
                         "independent pixels give about 1): a pixel filter other than a box? The networks "
                         "were trained on box-filtered renders: expect less denoising (render with "
                         "<rfilter type=\"box\"/>, or train for your filter)")
        return tuple(notes)

    def denoise_render(self, render: RenderResult, keep_network: bool = False) -> DenoiseResult:
        """Denoise a render of :mod:`rendering.render` with what it carries: its AOVs and, for a
        render made in two halves, its variance (the model's noise input, if it has one) and the
        noise guard at the strength for its spp (:meth:`denoise_array` with ``variance=render.variance,
        spp=render.spp`` gives the same image). ``keep_network`` as in :meth:`denoise_array`."""
        return self.denoise_array(render.rgb, render.aovs.get("albedo"), render.aovs.get("sh_normal"),
                                  render.variance, None, keep_network, render.spp, render.pixel_filter,
                                  render.to_camera)

    def __call__(self, noisy: Any, albedo: Any = None, normals: Any = None, spp: int | None = None) -> Any:
        """Denoise a numpy array, torch tensor, ``mi.TensorXf`` or ``mi.Bitmap`` (HxWx3, or HxWx4
        with alpha kept) of ``spp`` samples per pixel (None: unknown); returns the same kind of
        object. What the caller should know (an unknown spp: what ran instead; filtered noise) is
        given as a :class:`UserWarning`."""
        kind = type(noisy).__module__.split(".")[0]
        data = _float_array(noisy)
        if data.ndim != 3 or data.shape[2] not in (3, 4):
            raise DenoiserError(f"expected HxWx3 or HxWx4 input, got shape {data.shape}")
        aux = [None if a is None else _float_array(a)[..., :3] for a in (albedo, normals)]
        result = self.denoise_array(data[..., :3], *aux, spp=spp)
        for note in result.notes:
            warnings.warn(note, stacklevel=2)
        out = result.image
        if data.shape[2] == 4:
            out = np.concatenate([out, data[..., 3:]], axis=2)
        if kind == "torch":
            import torch

            return torch.from_numpy(out).to(noisy.device)
        if kind in ("mitsuba", "drjit"):
            import mitsuba as mi

            return mi.Bitmap(out) if isinstance(noisy, mi.Bitmap) else mi.TensorXf(out)
        return out
