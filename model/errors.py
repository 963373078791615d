"""Exception types of the model package. Library code raises these; only ``model.cli`` prints them."""
from __future__ import annotations

from pipeline.errors import DenoiserError


class ModelError(DenoiserError):
    """Base class of the model package's errors: a one-line message naming the file and the problem."""


class ConfigError(ModelError):
    """An invalid model, training or preset configuration (unknown name, out-of-range value...)."""


class CheckpointError(ModelError):
    """A checkpoint cannot be read: missing, truncated, not ours, or config and weights disagree."""


class DatasetError(ModelError):
    """A training dataset is missing, malformed or does not match what training expects."""


class TrainingError(ModelError):
    """Training cannot go on, e.g. the loss was NaN/Inf for too many steps in a row."""
