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
import math
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import safetensors.torch
import torch

from imaging.atomic_io import atomic_path
from imaging.errors import CheckpointError, ConfigError
from imaging.json_read import parse_json
from model.architectures import build_model
from model.config import ModelConfig
from model.shapes import ExpectedState, expected_state, min_parameters, min_state_entries

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


_SAFETENSORS_DTYPES = {"F64": torch.float64, "F32": torch.float32, "F16": torch.float16, "BF16": torch.bfloat16,
                       "I64": torch.int64, "I32": torch.int32, "I16": torch.int16, "I8": torch.int8,
                       "U8": torch.uint8, "BOOL": torch.bool}
_OPTIMIZER_KEYS = ("exp_avg", "exp_avg_sq", "max_exp_avg_sq")  # Adam's per-parameter moments


def _json(text: str, path: Path, what: str) -> Any:
    try:
        return parse_json(text)
    except ValueError as exc:
        raise CheckpointError(f"{path}: corrupt checkpoint {what} ({str(exc).splitlines()[0][:200]})") from None


def _open_tensors(path: Path) -> tuple[dict[str, str], dict[str, tuple[tuple[int, ...], str]]]:
    """(metadata, name -> (shape, safetensors dtype)) of a safetensors file, read from its header
    alone (safetensors checks that every tensor lies within the file)."""
    try:
        with safetensors.safe_open(str(path), framework="pt") as f:
            metadata = f.metadata() or {}
            shapes = {k: (tuple(f.get_slice(k).get_shape()), f.get_slice(k).get_dtype()) for k in f.keys()}
    except FileNotFoundError:
        raise CheckpointError(f"{path}: checkpoint not found") from None
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except Exception as exc:  # safetensors raises its own error type for any malformed file
        raise CheckpointError(f"{path}: truncated or not a safetensors checkpoint "
                              f"({str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__})") from None
    return metadata, shapes


def _load_tensors(path: Path, names: list[str]) -> dict[str, torch.Tensor]:
    try:
        with safetensors.safe_open(str(path), framework="pt") as f:
            return {k: f.get_tensor(k) for k in names}
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read ({exc.strerror or exc})") from None
    except Exception as exc:
        raise CheckpointError(f"{path}: truncated or not a safetensors checkpoint ({exc})") from None


def _header(path: Path, metadata: dict[str, str]) -> dict[str, Any]:
    if _META_KEY not in metadata:
        raise CheckpointError(f"{path}: not a denoiser checkpoint (no '{_META_KEY}' header)")
    header = _json(metadata[_META_KEY], path, "header")
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a denoiser checkpoint (format {header.get('format')!r})"
                              if isinstance(header, dict) else f"{path}: corrupt checkpoint header")
    if header.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {header.get('format_version')!r} is not "
                              f"supported (expected {FORMAT_VERSION})")
    _check_header_fields(path, header)
    return header


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check_header_fields(path: Path, header: dict[str, Any]) -> None:
    """The header's fields have the types :func:`save_checkpoint` writes: ``step`` a count,
    ``extra`` an object, the configs and the optimiser an object or null (its parameter groups
    objects), the spp range a training config records counts."""
    problems = []
    if not (_is_int(header.get("step")) and header["step"] >= 0):
        problems.append(f"step {header.get('step')!r}")
    for key in ("train_config", "data_config", "optimizer"):
        if header.get(key) is not None and not isinstance(header[key], dict):
            problems.append(f"{key} of type {type(header[key]).__name__}")
    if not isinstance(header.get("extra", {}), dict):
        problems.append(f"extra of type {type(header['extra']).__name__}")
    optimizer = header.get("optimizer") if isinstance(header.get("optimizer"), dict) else {}
    if optimizer and not (isinstance(optimizer.get("param_groups"), list)
                          and all(isinstance(g, dict) for g in optimizer["param_groups"])):
        problems.append("optimizer param_groups not a list of objects")
    train_config = header.get("train_config") if isinstance(header.get("train_config"), dict) else {}
    for key in ("min_spp", "max_spp"):
        value = train_config.get(key)
        if value is not None and not (_is_int(value) and value >= 0):
            problems.append(f"train_config {key} {value!r}")
    if problems:
        raise CheckpointError(f"{path}: corrupt checkpoint header ({'; '.join(problems)})")


def model_config_of(path: Path, header: dict[str, Any]) -> ModelConfig:
    """The header's model config; raises :class:`CheckpointError` when it is missing or invalid."""
    try:
        return ModelConfig.from_dict(header.get("model_config"))
    except (ConfigError, TypeError) as exc:
        raise CheckpointError(f"{path}: bad model config in checkpoint ({exc})") from None


def check_tensors(path: Path, header: dict[str, Any], shapes: dict[str, tuple[tuple[int, ...], str]],
                  file_bytes: int) -> None:
    """Raise :class:`CheckpointError` unless the stored tensors (name -> (shape, safetensors
    dtype)) are those the header's model config implies (:mod:`model.shapes`, nothing built or
    allocated): the weights by name, shape and dtype; Adam's moments with their parameter's shape;
    the RNG state; nothing else."""
    config = model_config_of(path, header)
    stored = {k[len("model/"):]: v for k, v in shapes.items() if k.startswith("model/")}
    if min_state_entries(config) > len(stored):
        raise CheckpointError(f"{path}: weights do not match the model config (it implies at least "
                              f"{min_state_entries(config):,} weight tensors, the file holds {len(stored):,})")
    if 4 * min_parameters(config) > file_bytes:
        raise CheckpointError(f"{path}: weights do not match the model config (it implies at least "
                              f"{min_parameters(config):,} parameters, {4 * min_parameters(config):,} bytes; "
                              f"the file has {file_bytes:,} bytes)")
    expected = expected_state(config)
    missing, unexpected = sorted(set(expected.shapes) - set(stored)), sorted(set(stored) - set(expected.shapes))
    if missing or unexpected:
        raise CheckpointError(f"{path}: weights do not match the model config "
                              f"(missing: {', '.join(missing[:3]) or '-'}; "
                              f"unexpected: {', '.join(unexpected[:3]) or '-'})")
    for key, (shape, dtype) in expected.shapes.items():
        found_shape, found_dtype = stored[key]
        if found_shape != shape or _SAFETENSORS_DTYPES.get(found_dtype) != dtype:
            needed = next((k for k, v in _SAFETENSORS_DTYPES.items() if v == dtype), str(dtype))
            raise CheckpointError(f"{path}: weight {key} has shape {found_shape} {found_dtype}, the model "
                                  f"config needs {shape} {needed}")
    _check_other_tensors(path, shapes, expected)


def _check_other_tensors(path: Path, shapes: dict[str, tuple[tuple[int, ...], str]], expected: ExpectedState
                         ) -> None:
    """The RNG state (a 1-D uint8 tensor) and Adam's per-parameter state, nothing else."""
    for name, (shape, dtype) in shapes.items():
        if name.startswith("model/"):
            continue
        if name == "rng/torch":
            if len(shape) != 1 or dtype != "U8":
                raise CheckpointError(f"{path}: tensor rng/torch has shape {shape} {dtype}, expected 1-D U8")
            continue
        index, _, key = name[len("optim/"):].partition("/")
        if not name.startswith("optim/") or not index.isdigit() or int(index) >= len(expected.parameters):
            raise CheckpointError(f"{path}: unexpected tensor {name!r}")
        parameter = expected.shapes[expected.parameters[int(index)]][0]
        if key == "step" and len(shape) <= 1 and math.prod(shape) == 1:
            continue
        if key not in _OPTIMIZER_KEYS or shape != parameter or dtype not in ("F32", "BF16", "F16", "F64"):
            raise CheckpointError(f"{path}: optimiser tensor {name} has shape {shape} {dtype}, its parameter "
                                  f"{parameter}")


def read_checkpoint(path: str | Path) -> Checkpoint:
    """Read and check a checkpoint file; raises :class:`CheckpointError` with the reason.

    The header and the tensors' names, shapes and dtypes are read and checked against each other
    (:func:`check_tensors`) before any tensor is loaded or any network built."""
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(f"{path}: cannot read (Is a directory)")
    metadata, shapes = _open_tensors(path)
    header = _header(path, metadata)
    check_tensors(path, header, shapes, path.stat().st_size)
    return Checkpoint(path, header, _load_tensors(path, list(shapes)))


def strip_optimizer(src: str | Path, dst: str | Path) -> None:
    """Write ``src`` to ``dst`` without the optimiser state (what a shipped checkpoint keeps: the
    weights, the RNG state and the header as trained, its ``optimizer`` entry null), atomically.
    Continuing from the result is a warm start (``train --init-from``) with a fresh optimiser."""
    ckpt = read_checkpoint(src)
    tensors = {k: v for k, v in ckpt.tensors.items() if not k.startswith("optim/")}
    _write(Path(dst), tensors, {**ckpt.header, "optimizer": None})


def replace_meta(path: str | Path, meta: dict[str, Any]) -> None:
    """Rewrite ``path`` with ``meta`` as its header's card record (:func:`checkpoint_meta`),
    atomically: every tensor and every other header field as they were (a file written before
    checkpoints carried the record gets it without its weights changing)."""
    ckpt = read_checkpoint(path)
    _write(Path(path), ckpt.tensors, {**ckpt.header, "meta": dict(meta)})


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
    """Rebuild the network from the header's model config and load its weights (strict): the
    tensors were checked against the config when the file was read (:func:`check_tensors`)."""
    model = build_model(model_config_of(ckpt.path, ckpt.header))
    model.load_state_dict(ckpt.prefixed("model/"), strict=True)
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
    bad = [g for g in info["param_groups"] if not _plain_group(g)]
    if bad:
        raise CheckpointError(f"{ckpt.path}: corrupt optimiser parameter group in checkpoint ({str(bad[0])[:200]})")
    # Hyper-parameters and moments come from the file; the implementation flags stay as configured.
    groups = [{**{k: (tuple(v) if k == "betas" else v) for k, v in saved.items()},
               **{k: current[k] for k in _IMPLEMENTATION_FLAGS if k in current}}
              for saved, current in zip(info["param_groups"], optimizer.state_dict()["param_groups"])]
    try:
        optimizer.load_state_dict({"state": dict(sorted(state.items())), "param_groups": groups})
    except (ValueError, KeyError, RuntimeError, TypeError, AttributeError) as exc:
        raise CheckpointError(f"{ckpt.path}: optimiser state does not match the model ({exc})") from None
    _match_param_layout(optimizer)


def _plain_group(group: dict[str, Any]) -> bool:
    """A parameter group as :func:`save_checkpoint` writes it: ``params`` a list of indices,
    ``betas`` two numbers, every other value a number, a flag or null."""
    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    return (isinstance(group.get("params"), list) and all(_is_int(i) for i in group["params"])
            and (isinstance(group.get("betas"), list) and len(group["betas"]) == 2
                 and all(number(b) for b in group["betas"]) if "betas" in group else True)
            and all(number(v) or isinstance(v, bool) or v is None for k, v in group.items()
                    if k not in ("params", "betas")))


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
