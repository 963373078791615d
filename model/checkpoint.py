"""Self-describing checkpoints: one safetensors file, no pickle.

Tensors: ``model/<state_dict key>`` (weights and BatchNorm statistics), ``optim/<i>/<key>``
(Adam moments and step of parameter i) and ``rng/torch`` (the torch CPU RNG state). The
safetensors metadata entry ``denoiser_checkpoint`` holds a JSON header::

    {"format": "mc-densenet-denoiser-checkpoint", "format_version": 1, "step": 1200,
     "model_config": {...ModelConfig...}, "train_config": {...} | null, "data_config": {...} | null,
     "optimizer": {"type": "Adam", "param_groups": [...]} | null, "extra": {...}, "meta": {...}}

``meta`` is what a model card shows (:func:`checkpoint_meta`): the recipe that made the file (name,
sha256, stage), the CPU and GPU hours of every stage up to it, the hardware, and the pixel filter
of the renders it was trained on (:func:`pixel_filter`; absent means a box filter).

:func:`load_model` rebuilds the network from the file alone. Files are written atomically, and
non-finite weights are never written.
"""
from __future__ import annotations

import functools
import hashlib
import json
import struct
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import safetensors.torch
import torch

from imaging.atomic_io import atomic_path
from imaging.errors import CheckpointError, ConfigError
from model.architectures import build_model
from model.config import ModelConfig

FORMAT = "mc-densenet-denoiser-checkpoint"
FORMAT_VERSION = 1
_META_KEY = "denoiser_checkpoint"
_IMPLEMENTATION_FLAGS = ("fused", "foreach", "capturable", "differentiable")
BOX_FILTER = {"type": "box"}  # the pixel filter of a checkpoint that records none


@dataclass
class Checkpoint:
    """A checkpoint read from disk: its JSON ``header`` and named CPU ``tensors``."""

    path: Path
    header: dict[str, Any]
    tensors: dict[str, torch.Tensor]

    def prefixed(self, prefix: str) -> dict[str, torch.Tensor]:
        """Tensors whose names start with ``prefix``, with the prefix removed."""
        return {k[len(prefix):]: v for k, v in self.tensors.items() if k.startswith(prefix)}


@functools.lru_cache(maxsize=1)
def code_version() -> dict[str, Any]:
    """What code wrote a checkpoint: the sha256 over the ``model`` package's sources (name and
    bytes of every ``model/*.py``, sorted; equal for equal code, also in a copy without git), the
    git commit when the package lies in a git checkout, and torch's version."""
    package = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for source in sorted(package.glob("*.py")):
        digest.update(source.name.encode() + b"\0" + source.read_bytes() + b"\0")
    commit = None
    try:
        done = subprocess.run(["git", "-C", str(package), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10)
        commit = done.stdout.strip() or None if done.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        pass
    return {"model_sources_sha256": digest.hexdigest(), "git_commit": commit, "torch": torch.__version__}


def save_checkpoint(path: str | Path, model: torch.nn.Module, *, step: int,
                    optimizer: torch.optim.Optimizer | None = None,
                    train_config: dict[str, Any] | None = None, data_config: dict[str, Any] | None = None,
                    extra: dict[str, Any] | None = None, meta: dict[str, Any] | None = None) -> None:
    """Write ``model`` (+ optimiser, torch RNG, configs, the card's ``meta``) to ``path`` atomically.

    Raises :class:`CheckpointError` if any weight or buffer is NaN/Inf (nothing is written).
    """
    path = Path(path)
    tensors = {f"model/{k}": v.detach().cpu().contiguous().clone() for k, v in model.state_dict().items()}
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise CheckpointError(f"{path}: refusing to save non-finite weights ({', '.join(bad[:3])})")
    tensors["rng/torch"] = torch.get_rng_state()
    header: dict[str, Any] = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "step": int(step),
        "model_config": model.config.to_dict(), "train_config": train_config, "data_config": data_config,
        "optimizer": None, "extra": extra or {}, "code": dict(code_version()),
    }
    if meta:
        header["meta"] = meta
    if optimizer is not None:
        header["optimizer"] = _optimizer_header(optimizer)
        for i, state in optimizer.state_dict()["state"].items():
            for key, value in state.items():
                tensors[f"optim/{i}/{key}"] = torch.as_tensor(value).detach().cpu().contiguous().clone()
    _write(path, tensors, header)


def _write(path: Path, tensors: dict[str, torch.Tensor], header: dict[str, Any]) -> None:
    """``tensors`` and the JSON ``header`` as one safetensors file, atomically; raises
    :class:`CheckpointError` when it cannot be written."""
    try:
        with atomic_path(path) as tmp:
            safetensors.torch.save_file(tensors, str(tmp), metadata={_META_KEY: json.dumps(header)})
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot write ({exc.strerror or exc})") from None
    except safetensors.SafetensorError as exc:  # e.g. "No space left on device" from the Rust writer
        raise CheckpointError(f"{path}: cannot write ({str(exc).splitlines()[0]})") from None


def _optimizer_header(optimizer: torch.optim.Optimizer) -> dict[str, Any]:
    groups = optimizer.state_dict()["param_groups"]
    return {"type": type(optimizer).__name__,
            "param_groups": [{k: (list(v) if isinstance(v, tuple) else v) for k, v in g.items()} for g in groups]}


def _read_metadata(data: bytes) -> dict[str, str]:
    (length,) = struct.unpack("<Q", data[:8])
    return json.loads(data[8:8 + length]).get("__metadata__") or {}


def read_checkpoint(path: str | Path) -> Checkpoint:
    """Read and check a checkpoint file; raises :class:`CheckpointError` with the reason."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise CheckpointError(f"{path}: checkpoint not found") from None
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read ({exc.strerror or exc})") from None
    try:
        tensors = safetensors.torch.load(data)
        metadata = _read_metadata(data)
    except Exception as exc:  # safetensors raises its own error type for any malformed file
        raise CheckpointError(f"{path}: truncated or not a safetensors checkpoint ({exc})") from None
    if _META_KEY not in metadata:
        raise CheckpointError(f"{path}: not a denoiser checkpoint (no '{_META_KEY}' header)")
    try:
        header = json.loads(metadata[_META_KEY])
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"{path}: corrupt checkpoint header ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a denoiser checkpoint (format {header.get('format')!r})"
                              if isinstance(header, dict) else f"{path}: corrupt checkpoint header")
    if header.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {header.get('format_version')!r} is not "
                              f"supported (expected {FORMAT_VERSION})")
    return Checkpoint(path, header, tensors)


def strip_optimizer(src: str | Path, dst: str | Path) -> None:
    """Write ``src`` to ``dst`` without the optimiser state (what a shipped checkpoint keeps: the
    weights, the RNG state and the header as trained, its ``optimizer`` entry null), atomically.
    Continuing from the result is a warm start (``train --init-from``) with a fresh optimiser."""
    ckpt = read_checkpoint(src)
    tensors = {k: v for k, v in ckpt.tensors.items() if not k.startswith("optim/")}
    _write(Path(dst), tensors, {**ckpt.header, "optimizer": None})


def compact_optimizer(src: str | Path, dst: str | Path) -> None:
    """Write ``src`` to ``dst`` with the optimiser's floating-point state (Adam's moments) in
    bfloat16, everything else as it was, atomically: a resumable copy small enough to commit (a
    u-balanced run with the filter: 8.5 -> 5.7 MB). ``train --resume`` from it continues the run
    with moments rounded to 8 significant bits (:func:`restore_optimizer` casts them back to each
    parameter's dtype), so the continuation follows the exact one closely, not bit for bit; the
    header's ``optimizer.moments`` says so. Raises :class:`CheckpointError` when ``src`` has no
    optimiser state."""
    ckpt = read_checkpoint(src)
    if not ckpt.header.get("optimizer"):
        raise CheckpointError(f"{ckpt.path}: has no optimiser state to compact")
    tensors = {k: (v.to(torch.bfloat16) if k.startswith("optim/") and v.is_floating_point()
                   and not k.endswith("/step") else v)
               for k, v in ckpt.tensors.items()}
    _write(Path(dst), tensors, {**ckpt.header, "optimizer": {**ckpt.header["optimizer"], "moments": "bfloat16"}})


def checkpoint_meta(header: dict[str, Any]) -> dict[str, Any]:
    """The ``meta`` entry of a checkpoint header (``Checkpoint.header`` or :func:`load_model`'s
    third value): ``recipe`` ({"name", "sha256", "stage"}), ``hours`` ({"cpu", "gpu"}: all stages
    up to this file), ``hardware`` (list of strings), ``pixel_filter``; {} for a file without one."""
    meta = header.get("meta")
    return dict(meta) if isinstance(meta, dict) else {}


def pixel_filter(header: dict[str, Any]) -> dict[str, Any]:
    """The pixel filter of the renders the checkpoint was trained on, as {"type": NAME, PARAM: value,
    ...} (e.g. {"type": "gaussian", "stddev": 0.5}): ``meta.pixel_filter``, else its dataset's
    ``filter`` (a name or such a dict), else a box filter (every checkpoint that records none was
    trained on box-filtered renders)."""
    recorded = checkpoint_meta(header).get("pixel_filter")
    if recorded is None:
        recorded = (header.get("data_config") or {}).get("filter")
    if isinstance(recorded, str):
        return {"type": recorded}
    return dict(recorded) if isinstance(recorded, dict) and recorded.get("type") else dict(BOX_FILTER)


def model_from_checkpoint(ckpt: Checkpoint) -> torch.nn.Module:
    """Rebuild the network from the header's model config and load its weights (strict)."""
    try:
        config = ModelConfig.from_dict(ckpt.header.get("model_config"))
    except (ConfigError, TypeError) as exc:
        raise CheckpointError(f"{ckpt.path}: bad model config in checkpoint ({exc})") from None
    model = build_model(config)
    state = ckpt.prefixed("model/")
    expected = model.state_dict()
    missing, unexpected = sorted(set(expected) - set(state)), sorted(set(state) - set(expected))
    if missing or unexpected:
        raise CheckpointError(f"{ckpt.path}: weights do not match the model config "
                              f"(missing: {', '.join(missing[:3]) or '-'}; "
                              f"unexpected: {', '.join(unexpected[:3]) or '-'})")
    for key, value in expected.items():
        if state[key].shape != value.shape or state[key].dtype != value.dtype:
            raise CheckpointError(f"{ckpt.path}: weight {key} has shape {tuple(state[key].shape)} "
                                  f"{state[key].dtype}, the model config needs {tuple(value.shape)} {value.dtype}")
    model.load_state_dict(state, strict=True)
    return model


def load_model(path: str | Path) -> tuple[torch.nn.Module, ModelConfig, dict[str, Any]]:
    """(model in eval mode, its config, header without tensors) rebuilt from the file alone."""
    ckpt = read_checkpoint(path)
    model = model_from_checkpoint(ckpt)
    model.eval()
    meta = {k: v for k, v in ckpt.header.items() if k != "optimizer"}
    return model, model.config, meta


def restore_optimizer(ckpt: Checkpoint, optimizer: torch.optim.Optimizer) -> None:
    """Load the checkpoint's optimiser state into ``optimizer`` (same param order and type)."""
    info = ckpt.header.get("optimizer")
    if not info or info.get("type") != type(optimizer).__name__:
        raise CheckpointError(f"{ckpt.path}: has no {type(optimizer).__name__} optimiser state to resume from")
    state: dict[int, dict[str, torch.Tensor]] = {}
    for name, tensor in ckpt.prefixed("optim/").items():
        index, key = name.split("/", 1)
        state.setdefault(int(index), {})[key] = tensor
    if len(info["param_groups"]) != len(optimizer.param_groups):
        raise CheckpointError(f"{ckpt.path}: optimiser has {len(info['param_groups'])} parameter groups, "
                              f"expected {len(optimizer.param_groups)}")
    # Hyper-parameters and moments come from the file; the implementation flags stay as configured.
    groups = [{**{k: (tuple(v) if k == "betas" else v) for k, v in saved.items()},
               **{k: current[k] for k in _IMPLEMENTATION_FLAGS if k in current}}
              for saved, current in zip(info["param_groups"], optimizer.state_dict()["param_groups"])]
    try:
        optimizer.load_state_dict({"state": dict(sorted(state.items())), "param_groups": groups})
    except (ValueError, KeyError, RuntimeError) as exc:
        raise CheckpointError(f"{ckpt.path}: optimiser state does not match the model ({exc})") from None
    _match_param_layout(optimizer)


def _match_param_layout(optimizer: torch.optim.Optimizer) -> None:
    """Give each moment tensor its parameter's memory layout (e.g. channels-last): fused Adam
    walks parameter and moments as flat memory, so their strides must agree."""
    for group in optimizer.param_groups:
        for param in group["params"]:
            state = optimizer.state.get(param, {})
            for key, value in state.items():
                if torch.is_tensor(value) and value.shape == param.shape and value.stride() != param.stride():
                    state[key] = torch.empty_like(param).copy_(value)


def restore_rng(ckpt: Checkpoint) -> None:
    """Restore the torch CPU RNG state saved in the checkpoint."""
    if "rng/torch" in ckpt.tensors:
        torch.set_rng_state(ckpt.tensors["rng/torch"])
