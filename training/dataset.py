"""Reading a generated dataset: ``dataset.json``, ``manifest.jsonl`` and the images, into RAM.

Layout (written by ``dataset_gen``)::

    DIR/dataset.json     {"version": 1, "res": [W, H], "spp": [...], "ref_spp": N, "aovs": [...], ...}
    DIR/manifest.jsonl   one JSON object per finished scene: index, scene, split ("train"|"val"),
                         spp, aovs, ...
    DIR/images/          names from imaging.naming.image_name only

Image paths are always ``DIR/images/image_name(index, spp, kind)``; the manifest never supplies a
path. Radiance is sanitised on load (NaN -> 0, clamped to [0, HDR_MAX]); aux images are the RGB
channels of the ``.alb.exr`` (albedo, [0,1]) and ``.nrm.exr`` (normal, [-1,1]) files, the normals
world-space as rendered or (``normals="camera"``) turned into the sensor's frame of the scene's
file (:mod:`rendering.camera`): ``DIR/scenes/sceneNNNN/scene.xml``, or the manifest's
``scene_file`` for a dataset rendered from the user's files.
"""
from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dataset_gen.jobs import scene_file
from imaging.errors import DatasetError, ExrError, SceneError
from imaging.exr import read_exr
from imaging.json_read import parse_json
from imaging.naming import image_name
from model.config import AUX_NORMALS
from model.noise_input import noise_channels
from rendering.camera import rotate_normals, scene_file_rotation
from training.patches import TrainingPair
from model.transfer import HDR_MAX, TransferFunction

DATASET_VERSION = 1
CONVERGED_SPP = 0  # TrainingPair.spp of a pair whose input is the reference itself


@dataclass(frozen=True)
class SceneRecord:
    """One manifest line: scene index, split, rendered spp levels, aux buffers, the spp
    levels that have a variance image (``generate-dataset --variance``) and the PSNR ceiling its
    reference's own noise sets (dB, from its two halves; None where not recorded)."""

    index: int
    split: str
    spp: tuple[int, ...]
    aovs: tuple[str, ...]
    variance_spp: tuple[int, ...] = ()
    ref_ceiling_db: float | None = None
    scene_file: str | None = None  # the user's scene file it was rendered from (None: a generated scene)


@dataclass(frozen=True)
class ValImage:
    """A whole validation image: linear radiance HxWx3 float32 (noisy and reference), aux
    (HxWx6: albedo RGB then normal XYZ) or None, and the noisy image's HxWx3 variance estimate
    (None where the dataset has none, or the model does not use it)."""

    scene: int
    spp: int
    noisy: np.ndarray
    ref: np.ndarray
    aux: np.ndarray | None
    variance: np.ndarray | None = None


def read_dataset_config(root: Path) -> dict[str, Any]:
    """Parsed ``dataset.json``; raises :class:`DatasetError` if missing, malformed or unsupported."""
    path = root / "dataset.json"
    try:
        config = parse_json(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DatasetError(f"{path}: not found (is {root} a dataset folder?)") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read ({exc})") from None
    if not isinstance(config, dict) or config.get("version") != DATASET_VERSION:
        raise DatasetError(f"{path}: unsupported dataset version "
                           f"{config.get('version') if isinstance(config, dict) else None!r} "
                           f"(expected {DATASET_VERSION})")
    spp = config.get("spp")
    if not isinstance(spp, list) or not spp or not all(isinstance(s, int) and s >= 1 for s in spp):
        raise DatasetError(f"{path}: 'spp' must be a non-empty list of positive integers")
    return config


def _record(line: str, path: Path, number: int) -> SceneRecord:
    try:
        obj = parse_json(line)
        if not isinstance(obj, dict):
            raise TypeError(f"a JSON object, not {type(obj).__name__}")
        ref_noise = obj.get("ref_noise")
        ceiling = ref_noise.get("psnr_ceiling_db") if isinstance(ref_noise, dict) else None
        record = SceneRecord(int(obj["index"]), str(obj["split"]),
                             tuple(int(s) for s in obj["spp"]), tuple(str(a) for a in obj.get("aovs", [])),
                             tuple(int(s) for s in obj.get("variance_spp", [])),
                             None if ceiling is None else float(ceiling),
                             None if obj.get("scene_file") is None else str(obj["scene_file"]))
    except (json.JSONDecodeError, KeyError, TypeError, ValueError, OverflowError) as exc:  # int(Infinity)
        raise DatasetError(f"{path}:{number}: malformed manifest line ({exc})") from None
    if record.index < 0 or record.split not in ("train", "val"):
        raise DatasetError(f"{path}:{number}: bad index {record.index} or split {record.split!r}")
    return record


def read_manifest(root: Path) -> list[SceneRecord]:
    """All scene records of ``manifest.jsonl`` (blank lines ignored, later duplicates win)."""
    path = root / "manifest.jsonl"
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise DatasetError(f"{path}: not found (no finished scenes yet?)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path}: cannot read ({exc})") from None
    records = {r.index: r for n, line in enumerate(lines, 1) if line.strip() for r in [_record(line, path, n)]}
    return sorted(records.values(), key=lambda r: r.index)


def _read_rgb(root: Path, index: int, spp: int | None, kind: str) -> np.ndarray:
    path = root / "images" / image_name(index, spp, kind)
    try:
        rgb = read_exr(path).rgb
    except ExrError as exc:
        raise DatasetError(str(exc)) from None
    if kind == "hdr":
        rgb = np.clip(np.nan_to_num(rgb, nan=0.0, posinf=HDR_MAX, neginf=0.0), 0.0, HDR_MAX)
    elif kind == "var":  # a variance: up to HDR_MAX^2
        rgb = np.clip(np.nan_to_num(rgb, nan=0.0, posinf=HDR_MAX**2, neginf=0.0), 0.0, HDR_MAX**2)
    else:
        rgb = np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0)
    return rgb.astype(np.float32)


def scene_rotation(root: Path, record: SceneRecord) -> np.ndarray:
    """:func:`rendering.camera.scene_file_rotation` of the scene file ``record`` was rendered from;
    raises :class:`DatasetError` when it is missing or does not load."""
    path = Path(record.scene_file) if record.scene_file else scene_file(root, record.index)
    if not path.is_file():
        raise DatasetError(f"scene {record.index}: normals in camera space need the scene's file, {path}: not found")
    try:
        return scene_file_rotation(path)
    except SceneError as exc:
        raise DatasetError(f"scene {record.index}: cannot read its camera ({exc})") from None


def _aux(root: Path, record: SceneRecord, spp: int, rotation: np.ndarray | None = None) -> np.ndarray:
    """HxWx6 albedo and normals of ``record`` at ``spp``, the normals times ``rotation`` if given."""
    missing = {"alb", "nrm"} - set(record.aovs)
    if missing:
        raise DatasetError(f"scene {record.index}: the model needs aux inputs but the dataset has no "
                           f"{'/'.join(sorted(missing))} buffers")
    normals = _read_rgb(root, record.index, spp, "nrm")
    if rotation is not None:
        normals = rotate_normals(normals, rotation)
    return np.concatenate([_read_rgb(root, record.index, spp, "alb"), normals], axis=-1)


def _rotation(root: Path, record: SceneRecord, aux: bool, normals: str) -> np.ndarray | None:
    if normals not in AUX_NORMALS:
        raise ValueError(f"normals must be one of {AUX_NORMALS}, got {normals!r}")
    return scene_rotation(root, record) if aux and normals == "camera" else None


def _encode(transfer: TransferFunction, rgb: np.ndarray) -> np.ndarray:
    return transfer.forward(torch.from_numpy(rgb)).numpy()


def _variance(root: Path, record: SceneRecord, spp: int) -> np.ndarray | None:
    return _read_rgb(root, record.index, spp, "var") if spp in record.variance_spp else None


def load_training_pairs(root: Path, records: Iterable[SceneRecord], transfer: TransferFunction,
                        aux: bool, progress: Callable[[int], Any] | None = None,
                        converged: bool = False, noise: bool = False,
                        index_offset: int = 0, noise_radius: int = 0, normals: str = "world") -> list[TrainingPair]:
    """Every (scene, spp) of ``records`` as a transfer-space :class:`TrainingPair` held in RAM.

    With ``converged`` each scene also gets a pair whose input is its reference itself (``spp``
    = :data:`CONVERGED_SPP`; aux buffers of its highest spp; noise channels saying "variance 0"):
    it teaches the model to leave an already converged image as it is instead of smoothing it
    like a noisy one. With ``noise`` the input carries the 4 channels of
    :func:`model.noise_input.noise_channels` last (unknown where a level has no variance image;
    the variance averaged over ``noise_radius``).
    A pair's ``scene`` is the record's index + ``index_offset`` (distinct ids across datasets).
    ``normals``: ``world`` or ``camera`` (see the module docstring).
    """
    pairs = []
    for record in records:
        rotation = _rotation(root, record, aux, normals)
        ref_linear = _read_rgb(root, record.index, None, "hdr")
        ref = _encode(transfer, ref_linear)
        for spp in record.spp:
            linear = _read_rgb(root, record.index, spp, "hdr")
            noisy = _encode(transfer, linear)
            if noisy.shape != ref.shape:
                raise DatasetError(f"scene {record.index}: {spp}spp image {noisy.shape} differs from "
                                   f"reference {ref.shape}")
            parts = [noisy]
            if aux:
                parts.append(_aux(root, record, spp, rotation))
            if noise:
                parts.append(noise_channels(linear, _variance(root, record, spp), transfer, noise_radius))
            pairs.append(TrainingPair(np.ascontiguousarray(np.concatenate(parts, axis=-1)), ref,
                                      record.index + index_offset, spp))
        if converged and record.spp:
            parts = [ref]
            if aux:
                parts.append(_aux(root, record, max(record.spp), rotation))
            if noise:
                parts.append(noise_channels(ref_linear, np.zeros_like(ref_linear), transfer, noise_radius))
            pairs.append(TrainingPair(np.ascontiguousarray(np.concatenate(parts, axis=-1)), ref,
                                      record.index + index_offset, CONVERGED_SPP))
        if progress is not None:
            progress(1)
    return pairs


def load_val_images(root: Path, records: Iterable[SceneRecord], aux: bool,
                    noise: bool = False, index_offset: int = 0, normals: str = "world") -> list[ValImage]:
    """Every (scene, spp) of ``records`` as linear-radiance :class:`ValImage` held in RAM (with
    its variance image where the dataset has one and ``noise`` asks for it); ``scene`` is the
    record's index + ``index_offset``; ``normals`` as :func:`load_training_pairs`'s."""
    images = []
    for record in records:
        rotation = _rotation(root, record, aux, normals)
        ref = _read_rgb(root, record.index, None, "hdr")
        for spp in record.spp:
            images.append(ValImage(record.index + index_offset, spp, _read_rgb(root, record.index, spp, "hdr"), ref,
                                   _aux(root, record, spp, rotation) if aux else None,
                                   _variance(root, record, spp) if noise else None))
    return images
