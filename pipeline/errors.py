"""Exception types of the pipeline. Library code raises these; only the CLIs print them."""
from __future__ import annotations


class DenoiserError(Exception):
    """Base class: the message is one line that names the file and the problem."""


class SceneError(DenoiserError):
    """A scene cannot be read, parsed or loaded (missing file, bad XML, missing asset...)."""


class RenderError(DenoiserError):
    """Invalid render settings (spp, resolution, seed...)."""


class ExrError(DenoiserError):
    """An EXR file cannot be read or written (truncated, not an EXR, lacks RGB...)."""
