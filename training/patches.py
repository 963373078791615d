"""Training patches: random crops of in-RAM images, the flat-patch filter, and augmentation.

Images are HxWxC float32 arrays already in transfer space: the noisy input has RGB first, then
(when the model uses them) albedo RGB and normal XYZ; the reference is HxWx3 RGB. A batch is a
pair of NxPxPxC / NxPxPx3 float32 arrays (NHWC; ``torch.from_numpy(a).permute(0, 3, 1, 2)`` gives
an NCHW tensor in channels-last memory order without a copy).

Following Kim & Lee, a crop whose noisy RGB holds fewer than ``min_unique`` distinct values is
dropped (flat background, clipped sky...). With ``detail`` d > 0, crops are chosen by how much
the reference varies in them (in the spirit of the importance-sampled patches of Bako et al. 2017,
KPCN): among ``DETAIL_CANDIDATES`` times as many accepted candidates as the batch needs, a crop is
drawn with probability ``(1 - d) / n + d * s / sum(s)``, ``s`` its reference's standard deviation
(transfer space, over pixels and channels), without replacement; d = 0 is the paper's uniform
sampling (the same random stream as before the option existed). Augmentation applies the same random flip/transpose and
the same RGB channel permutation to input and target (albedo is permuted with the RGB; world-space
normals are only moved spatially, their XYZ values are left as they are; normals in the camera's
frame turn with the image, as the normals of the mirrored scene would: a horizontal flip negates
their X, a vertical flip their Y, a transpose swaps X and Y, :mod:`rendering.camera`).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imaging.errors import ConfigError, DatasetError

DETAIL_CANDIDATES = 4  # candidates per crop of the batch when crops are chosen by detail
_RGB_PERMUTATIONS = np.array([[0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]])


@dataclass(frozen=True)
class PatchConfig:
    """``size``: crop side in pixels; ``min_unique``: distinct noisy-RGB values a crop needs;
    ``augment``: random flips/transposes/RGB permutations; ``max_rounds``: candidate rounds per
    batch before the sampler gives up (the data is then almost entirely flat); ``detail``: share
    of the crops' probability given by the reference's local variation (module docstring)."""

    size: int = 28
    min_unique: int = 100
    augment: bool = True
    max_rounds: int = 50
    detail: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.size, int) or self.size < 1:
            raise ConfigError(f"patch size must be a positive integer, got {self.size!r}")
        if not isinstance(self.min_unique, int) or self.min_unique < 0:
            raise ConfigError(f"patch min_unique must be an integer >= 0, got {self.min_unique!r}")
        if not isinstance(self.max_rounds, int) or self.max_rounds < 1:
            raise ConfigError(f"patch max_rounds must be a positive integer, got {self.max_rounds!r}")
        if not (isinstance(self.detail, (int, float)) and not isinstance(self.detail, bool)
                and 0 <= self.detail <= 1):
            raise ConfigError(f"patch detail must be in [0, 1], got {self.detail!r}")


@dataclass(frozen=True)
class TrainingPair:
    """One noisy image and its reference, both in transfer space (see the module docstring)."""

    noisy: np.ndarray
    ref: np.ndarray
    scene: int
    spp: int


def unique_counts(patches: np.ndarray) -> np.ndarray:
    """Number of distinct values in each patch of an Nx... array -> N int64."""
    flat = np.sort(patches.reshape(len(patches), -1), axis=1)
    return 1 + np.count_nonzero(flat[:, 1:] != flat[:, :-1], axis=1)


def augment(noisy: np.ndarray, ref: np.ndarray, rng: np.random.Generator,
            color_groups: Sequence[int] | None = None,
            camera_normals: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Apply one random dihedral transform + RGB permutation identically to a PxPxC / PxPx3 pair.

    ``color_groups``: first channels of the input's colour triplets that the permutation
    applies to (default: RGB, and albedo at 3..5 when there are >= 6 channels).
    ``camera_normals``: first channel of the input's normals when they are in the camera's frame
    (they turn with the image, module docstring); None: left as they are.
    """
    c = noisy.shape[-1]
    if color_groups is None:
        color_groups = (0, 3) if c >= 6 else (0,)
    both = np.concatenate([noisy, ref], axis=-1)
    sign, swap = np.ones(3, np.float32), False
    if rng.random() < 0.5:
        both = both[:, ::-1]
        sign[0] = -1.0  # image left <-> right: the camera's X
    if rng.random() < 0.5:
        both = both[::-1]
        sign[1] = -1.0  # up <-> down: its Y
    if rng.random() < 0.5:
        both = both.transpose(1, 0, 2)
        swap = True  # left <-> up: X <-> Y
    perm = _RGB_PERMUTATIONS[rng.integers(len(_RGB_PERMUTATIONS))]
    channels = np.arange(c + 3)
    for start in color_groups:
        channels[start:start + 3] = start + perm
    channels[c:] = c + perm
    both = both[:, :, channels]
    if camera_normals is not None:
        normals = both[:, :, camera_normals:camera_normals + 3] * sign
        both[:, :, camera_normals:camera_normals + 3] = normals[:, :, [1, 0, 2]] if swap else normals
    return both[:, :, :c], both[:, :, c:]


def _candidates(pairs: Sequence[TrainingPair], count: int, size: int,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    ids = rng.integers(len(pairs), size=count)
    noisy, ref = [], []
    for i in ids:
        pair = pairs[i]
        h, w = pair.ref.shape[:2]
        y, x = rng.integers(h - size + 1), rng.integers(w - size + 1)
        noisy.append(pair.noisy[y:y + size, x:x + size])
        ref.append(pair.ref[y:y + size, x:x + size])
    return np.stack(noisy), np.stack(ref)


def detail_probabilities(refs: np.ndarray, detail: float) -> np.ndarray:
    """Probability of each of N reference crops (NxPxPxC): ``(1 - detail) / N + detail * s / sum(s)``
    with ``s`` a crop's standard deviation over its pixels and channels (uniform where all are flat)."""
    spread = refs.reshape(len(refs), -1).astype(np.float64).std(axis=1)
    total = spread.sum()
    share = spread / total if total > 0 else np.full(len(refs), 1.0 / len(refs))
    return (1.0 - detail) / len(refs) + detail * share


def detail_choice(refs: np.ndarray, count: int, detail: float, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``count`` of the reference crops ``refs``, drawn without replacement by
    :func:`detail_probabilities` (flat crops keep a tiny probability, so that ``count`` can always
    be drawn)."""
    p = detail_probabilities(refs, detail) + 1e-12
    return rng.choice(len(refs), size=count, replace=False, p=p / p.sum())


def sample_batch(pairs: Sequence[TrainingPair], batch: int, config: PatchConfig,
                 rng: np.random.Generator,
                 color_groups: Sequence[int] | None = None,
                 camera_normals: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``batch`` accepted, augmented crops -> (NxPxPxC noisy, NxPxPx3 ref) float32 arrays.
    ``color_groups``, ``camera_normals``: see :func:`augment`.

    Pairs are drawn uniformly (so every spp level of every scene is equally likely), crop
    positions uniformly. Raises :class:`DatasetError` if too few crops pass the flat-patch filter.
    """
    if not pairs:
        raise DatasetError("no training images to sample patches from")
    for pair in pairs:
        if min(pair.ref.shape[:2]) < config.size:
            raise DatasetError(f"scene {pair.scene}: image {pair.ref.shape[1]}x{pair.ref.shape[0]} is "
                               f"smaller than the {config.size}px patch size")
    kept_noisy: list[np.ndarray] = []
    kept_ref: list[np.ndarray] = []
    want = batch * DETAIL_CANDIDATES if config.detail > 0 else batch
    for _ in range(config.max_rounds):
        need = want - len(kept_noisy)
        if need <= 0:
            break
        noisy, ref = _candidates(pairs, max(2 * need, 8), config.size, rng)
        ok = unique_counts(noisy[..., :3]) >= config.min_unique
        kept_noisy.extend(noisy[ok][:need])
        kept_ref.extend(ref[ok][:need])
    if len(kept_noisy) < batch:
        raise DatasetError(f"only {len(kept_noisy)} of {batch} patches have >= {config.min_unique} distinct "
                           f"values after {config.max_rounds} rounds: the training images are almost flat")
    if config.detail > 0:
        chosen = detail_choice(np.stack(kept_ref), batch, config.detail, rng)
        kept_noisy, kept_ref = [kept_noisy[i] for i in chosen], [kept_ref[i] for i in chosen]
    if config.augment:
        pairs_out = [augment(n, r, rng, color_groups, camera_normals) for n, r in zip(kept_noisy, kept_ref)]
        kept_noisy, kept_ref = [p[0] for p in pairs_out], [p[1] for p in pairs_out]
    return (np.ascontiguousarray(np.stack(kept_noisy), dtype=np.float32),
            np.ascontiguousarray(np.stack(kept_ref), dtype=np.float32))
