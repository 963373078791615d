"""Multi-layer and multi-part EXRs as other renderers write them, read and written back whole.

A file is a list of parts (one for an ordinary EXR), each a header and named channels (HxW arrays:
float16, float32 or uint32). Channels ``<prefix>.<suffix>`` group into layers by prefix: R,G,B
(+A) make a colour-like layer, X,Y,Z a vector layer (normals), a lone channel a scalar layer.
Layer names are the prefix (``ViewLayer.Combined``, ``albedo``, Mitsuba's AOV names); the bare
R,G,B of a part have the name ``""`` in a single-part file and the part's name in a multi-part
one (parts named ``color``, ``albedo``, ``normal``). :func:`pick_color_layer` chooses the image to
denoise; :func:`replace_layer` puts a result back in its place, keeping every other channel,
part and attribute and the channel's pixel type (float16 saturates at +-65504).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR

from imaging.atomic_io import atomic_path
from imaging.errors import ExrError
from imaging.exr import check_exr_file, plane, quiet_native_output

COLOR_WORDS = ("color", "colour", "rgb", "rgba", "beauty", "combined", "image", "noisy image")
ALBEDO_WORDS = ("albedo", "denoising albedo")
NORMAL_WORDS = ("normal", "normals", "sh_normal", "nn", "n", "denoising normal")
VARIANCE_WORDS = ("variance",)
AUX_WORDS = (*ALBEDO_WORDS, *NORMAL_WORDS, *VARIANCE_WORDS, "depth", "z", "position", "alpha",
             "denoising depth", "uv", "vector", "mist")
_COMPUTED_KEYS = ("channels", "chunkCount")  # the writer derives these from the channels
_DEEP = ("deepscanline", "deeptile")


@dataclass
class ExrPart:
    """One part: ``header`` as OpenEXR's binding gives it, ``channels`` name -> HxW array."""

    header: dict[str, Any]
    channels: dict[str, np.ndarray]

    @property
    def name(self) -> str:
        return str(self.header.get("name") or "")


@dataclass(frozen=True)
class Layer:
    """Channels of one part read together: ``channels`` in order (R,G,B / X,Y,Z / one),
    ``alpha`` the layer's A channel if it has one."""

    name: str
    part: int
    channels: tuple[str, ...]
    alpha: str | None = None

    @property
    def kind(self) -> str:
        """``rgb``, ``xyz`` or ``scalar``."""
        if len(self.channels) == 1:
            return "scalar"
        return "xyz" if self.channels[0].endswith("X") else "rgb"

    @property
    def word(self) -> str:
        """The last component of the name, lower case (``ViewLayer.Combined`` -> ``combined``)."""
        return self.name.rpartition(".")[2].lower()


@dataclass
class ExrFile:
    """A whole EXR file: its parts in order, and where it came from (for messages)."""

    parts: list[ExrPart]
    path: str = ""
    layers: dict[str, Layer] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.layers:
            self.layers = find_layers(self.parts)

    def image(self, layer: Layer) -> np.ndarray:
        """HxWxC float32 pixels of ``layer`` (C = 3 or 1)."""
        planes = self.parts[layer.part].channels
        return np.stack([np.asarray(planes[c], np.float32) for c in layer.channels], axis=-1)

    def is_half(self, layer: Layer) -> bool:
        return self.parts[layer.part].channels[layer.channels[0]].dtype == np.float16

    def metadata(self, part: int = 0) -> dict[str, str | int | float]:
        """A part's non-standard str/int/float attributes (``spp``, a renderer's notes...)."""
        return {k: v for k, v in self.parts[part].header.items()
                if k not in _STANDARD_ATTRIBUTES and isinstance(v, (str, int, float))}


_STANDARD_ATTRIBUTES = {"channels", "chunkCount", "compression", "dataWindow", "displayWindow",
                        "lineOrder", "name", "pixelAspectRatio", "screenWindowCenter",
                        "screenWindowWidth", "tiles", "type", "version"}


def _groups(part: ExrPart) -> dict[str, dict[str, str]]:
    """prefix -> {suffix: channel name} of one part."""
    groups: dict[str, dict[str, str]] = {}
    for name in part.channels:
        prefix, _, suffix = name.rpartition(".")
        groups.setdefault(prefix, {})[suffix] = name
    return groups


def find_layers(parts: list[ExrPart]) -> dict[str, Layer]:
    """Every colour, vector and scalar layer of the parts, by name (see the module notes)."""
    layers: dict[str, Layer] = {}
    for index, part in enumerate(parts):
        for prefix, suffixes in sorted(_groups(part).items()):
            name = prefix or (part.name if len(parts) > 1 else "")
            if name in layers:
                name = f"{part.name or index}.{prefix}" if prefix else f"{part.name or index}"
            for triple in (("R", "G", "B"), ("X", "Y", "Z")):
                if all(s in suffixes for s in triple):
                    layers[name] = Layer(name, index, tuple(suffixes[s] for s in triple), suffixes.get("A"))
                    break
            else:
                if len(suffixes) == 1:
                    layers[name] = Layer(name, index, tuple(suffixes.values()))
    return layers


def read_exr_file(path: str | Path) -> ExrFile:
    """Read every part and channel of an EXR (scanline or tiled; deep parts are refused).

    Raises :class:`ExrError` naming the file for a missing, truncated or non-EXR file.
    """
    path = Path(path)
    check_exr_file(path)
    try:
        with quiet_native_output() as printed, OpenEXR.File(str(path), separate_channels=True) as exr:
            parts = [ExrPart(dict(p.header), {k: np.array(v.pixels) for k, v in p.channels.items()})
                     for p in exr.parts]
    except (RuntimeError, ValueError, OSError) as exc:
        raise ExrError(f"{path}: truncated or corrupt EXR ({str(exc).splitlines()[0]})") from None
    if not parts or "Exception raised reading" in printed.getvalue():
        # The binding skips a part whose pixels it cannot read, with a warning, instead of raising.
        raise ExrError(f"{path}: truncated or corrupt EXR (a part's pixels cannot be read)")
    for part in parts:
        if str(part.header.get("type", "")).rsplit(".", 1)[-1] in _DEEP:
            raise ExrError(f"{path}: deep EXR parts are not supported (part {part.name!r})")
        shapes = {np.shape(c) for c in part.channels.values()}
        if len(shapes) > 1:
            raise ExrError(f"{path}: subsampled channels are not supported (part {part.name!r})")
    return ExrFile(parts, str(path))


def write_exr_file(path: str | Path, exr: ExrFile) -> None:
    """Write ``exr`` atomically with each part's header as read (compression, windows, tiling,
    attributes); a one-part file stays single-part."""
    path = Path(path)
    if not path.parent.is_dir():
        raise ExrError(f"{path}: output folder does not exist")
    headers = [{k: v for k, v in p.header.items() if k not in _COMPUTED_KEYS} for p in exr.parts]
    channels = [dict(p.channels) for p in exr.parts]  # copies: the binding replaces their values
    try:
        if len(exr.parts) == 1:
            headers[0].pop("name", None)
            out = OpenEXR.File(headers[0], channels[0])
        else:
            out = OpenEXR.File([OpenEXR.Part(h, c, name=p.name or f"part{i}")
                                for i, (h, c, p) in enumerate(zip(headers, channels, exr.parts))])
        with atomic_path(path) as tmp, out:
            out.write(str(tmp))
    except OSError as exc:
        raise ExrError(f"{path}: cannot write ({exc.strerror or exc})") from None
    except (RuntimeError, TypeError, ValueError) as exc:
        raise ExrError(f"{path}: cannot write ({str(exc).splitlines()[0]})") from None


def describe_layers(exr: ExrFile, kind: str | None = None) -> str:
    """``'' (R,G,B), 'albedo', ...``: the layer names for messages, optionally of one kind."""
    names = [n for n, layer in exr.layers.items() if kind is None or layer.kind == kind]
    return ", ".join(repr(n) for n in names) or "none"


def _channel_list(exr: ExrFile) -> str:
    names = sorted({c for p in exr.parts for c in p.channels})
    return ", ".join(names) or "none"


def pick_color_layer(exr: ExrFile, name: str | None = None) -> Layer:
    """The colour layer to denoise: ``name`` if given; else the bare R,G,B; else the one layer
    called like a colour (``color``, ``ViewLayer.Combined``, ``beauty``...); else the one R,G,B
    layer that is no known auxiliary (albedo, normal, variance...). Raises :class:`ExrError`
    listing the layers when there is none or the choice is ambiguous."""
    if name is not None:
        layer = exr.layers.get(name)
        if layer is None or layer.kind != "rgb":
            raise ExrError(f"{exr.path}: no R,G,B layer named {name!r} (colour layers: "
                           f"{describe_layers(exr, 'rgb')})")
        return layer
    rgb = [layer for layer in exr.layers.values() if layer.kind == "rgb"]
    if not rgb:
        raise ExrError(f"{exr.path}: has no R/G/B channels (found: {_channel_list(exr)})")
    bare = [layer for layer in rgb if layer.name == ""]
    named = [layer for layer in rgb if layer.word in COLOR_WORDS]
    others = [layer for layer in rgb if layer.word not in AUX_WORDS]
    for candidates in (bare, named, others):
        if len(candidates) == 1:
            return candidates[0]
        if len(candidates) > 1:
            raise ExrError(f"{exr.path}: several colour layers ({', '.join(repr(c.name) for c in candidates)})"
                           ": pick one with --layer NAME")
    raise ExrError(f"{exr.path}: no colour layer among {describe_layers(exr)}: pick one with --layer NAME")


def find_aux_layer(exr: ExrFile, words: tuple[str, ...], color: Layer, kinds: tuple[str, ...]
                   ) -> Layer | None:
    """The layer whose last name component is one of ``words`` (of one of ``kinds``), preferring
    one beside ``color`` (same view layer / part); None when there is none or no single best."""
    found = [layer for layer in exr.layers.values() if layer.word in words and layer.kind in kinds
             and layer is not color]
    parent = color.name.rpartition(".")[0]
    for beside in (lambda layer: layer.name.rpartition(".")[0] == parent,
                   lambda layer: layer.part == color.part):
        if len(found) > 1:
            found = [layer for layer in found if beside(layer)]
    return found[0] if len(found) == 1 else None


def replace_layer(exr: ExrFile, layer: Layer, image: np.ndarray,
                  attributes: Mapping[str, str | int | float] | None = None) -> ExrFile:
    """A copy of ``exr`` with ``layer``'s channels replaced by HxWxC ``image`` (stored in the
    channels' own pixel type) and ``attributes`` added to its part's header."""
    part = exr.parts[layer.part]
    if image.shape[:2] != np.shape(part.channels[layer.channels[0]]) or image.shape[2] != len(layer.channels):
        raise ExrError(f"{exr.path}: image of shape {image.shape} does not fit layer {layer.name!r}")
    half = exr.is_half(layer)
    channels = dict(part.channels)
    for i, name in enumerate(layer.channels):
        channels[name] = plane(image[:, :, i], half)
    header = {**part.header, **(attributes or {})}
    parts = list(exr.parts)
    parts[layer.part] = ExrPart(header, channels)
    return replace(exr, parts=parts)
