"""Every exception the project raises on purpose: one hierarchy under :class:`DenoiserError`.

Library code raises these; only the command-line entry points print them (one line, exit code 1).
"""
from __future__ import annotations


class DenoiserError(Exception):
    """Base class: the message is one line that names the file and the problem."""


class SceneError(DenoiserError):
    """A scene cannot be read, parsed or loaded (missing file, bad XML, missing asset...)."""


class RenderError(DenoiserError):
    """Invalid render settings (spp, resolution, seed...)."""


class ExrError(DenoiserError):
    """An EXR file cannot be read or written (truncated, not an EXR, lacks RGB...)."""


class DatasetError(DenoiserError):
    """A dataset cannot be used: other settings, unreadable config or manifest, missing or broken
    files, or not what training expects."""


class ModelError(DenoiserError):
    """Base class of the model's errors."""


class ConfigError(ModelError):
    """An invalid model, training or preset configuration (unknown name, out-of-range value...)."""


class CheckpointError(ModelError):
    """A checkpoint cannot be read: missing, truncated, not ours, or config and weights disagree."""


class TrainingError(ModelError):
    """Training cannot go on, e.g. the loss was NaN/Inf for too many steps in a row."""
