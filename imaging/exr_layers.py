"""Multi-layer and multi-part EXRs as other renderers write them, read and written back whole.

A file is a list of parts (one for an ordinary EXR), each a header and named channels (HxW arrays:
float16, float32 or uint32). Channels ``<prefix>.<suffix>`` group into layers by prefix: R,G,B
(+A) make a colour-like layer, X,Y,Z a vector layer (normals), a lone channel a scalar layer.
Layer names are the prefix (``ViewLayer.Combined``, ``albedo``, Mitsuba's AOV names); the bare
R,G,B of a part have the name ``""`` in a single-part file and the part's name in a multi-part
one (parts named ``color``, ``albedo``, ``normal``). :func:`pick_color_layer` chooses the image to
denoise; :func:`replace_layer` puts a result back in its place, keeping every other channel,
part and attribute and the channel's pixel type (float16 saturates at +-65504): its channels are
:class:`ImagePlane` s, converted a block of rows at a time when the file is written. A one-part
scanline file whose attributes are strings, numbers and the standard ones is written a block of
rows at a time (:func:`imaging.exr.write_scanlines`, the bytes ``OpenEXR.File`` writes); other
files (several parts, tiles, other attribute types) whole, by ``OpenEXR.File``.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import Imath
import numpy as np
import OpenEXR

from imaging.atomic_io import atomic_path
from imaging.blocks import DEFAULT_BLOCK_BYTES
from imaging.errors import ExrError
from imaging.exr import (RowSource, check_exr_file, check_exr_memory, check_full_resolution, error_text, plane,
                         quiet_native_output, write_scanlines)

COLOR_WORDS = ("color", "colour", "rgb", "rgba", "beauty", "combined", "image", "noisy image")
ALBEDO_WORDS = ("albedo", "denoising albedo")
NORMAL_WORDS = ("normal", "normals", "sh_normal", "nn", "n", "denoising normal")
VARIANCE_WORDS = ("variance",)
AUX_WORDS = (*ALBEDO_WORDS, *NORMAL_WORDS, *VARIANCE_WORDS, "depth", "z", "position", "alpha",
             "denoising depth", "uv", "vector", "mist")
_COMPUTED_KEYS = ("channels", "chunkCount")  # the writer derives these from the channels
_DEEP = ("deepscanline", "deeptile")


@dataclass(frozen=True)
class ImagePlane:
    """Channel ``index`` of an HxWxC ``image``, stored as ``dtype`` (float16: finite values beyond
    +-65504 saturate), made a block of rows at a time when written instead of copied whole.
    Reads as an HxW array of ``dtype`` (``np.asarray``)."""

    image: np.ndarray
    index: int
    dtype: np.dtype

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape[:2]

    def rows(self, y0: int, y1: int) -> np.ndarray:
        """Rows ``y0..y1`` as a contiguous array of ``dtype``."""
        return plane(self.image[y0:y1, :, self.index], self.dtype == np.float16)

    def __array__(self, dtype: Any = None, copy: bool | None = None) -> np.ndarray:
        whole = self.rows(0, self.shape[0])
        return whole if dtype is None else whole.astype(dtype, copy=False)


@dataclass
class ExrPart:
    """One part: ``header`` as OpenEXR's binding gives it, ``channels`` name -> HxW array (or
    :class:`ImagePlane`)."""

    header: dict[str, Any]
    channels: dict[str, np.ndarray | ImagePlane]

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
        """HxWxC float32 pixels of ``layer`` (C = 3 or 1), converted into the image a channel at a
        time (no whole temporary beside it)."""
        planes = self.parts[layer.part].channels
        first = planes[layer.channels[0]]
        out = np.empty((*np.shape(first), len(layer.channels)), np.float32)
        for c, name in enumerate(layer.channels):
            out[:, :, c] = planes[name]
        return out

    def take_image(self, layer: Layer, channels: int | None = None) -> np.ndarray:
        """:meth:`image` of ``layer`` (a scalar layer repeated to ``channels``), which from then on
        also holds the layer's float16 and float32 channels in this file: they become
        :class:`ImagePlane` s of it (converted back exactly when written), so their pixels are in
        memory once, not twice. Only one layer's float32 copy is made at a time beside the file."""
        image = self.image(layer)
        if channels is not None and image.shape[2] == 1 and channels > 1:
            image = np.repeat(image, channels, axis=2)
        planes = self.parts[layer.part].channels
        for c, name in enumerate(layer.channels):
            dtype = np.dtype(getattr(planes[name], "dtype", None))
            if dtype in (np.dtype(np.float16), np.dtype(np.float32)):
                planes[name] = ImagePlane(image, c, dtype)
        return image

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
    """Read every part and channel of an EXR (scanline or tiled; deep parts are refused), its
    headers checked first (:func:`imaging.exr_header.read_exr_header`): its channels and a float32
    colour image must fit in the memory left.

    Raises :class:`ExrError` naming the file for a missing, truncated or non-EXR file.
    """
    path = Path(path)
    header = check_exr_file(path)
    check_full_resolution(header)
    largest = max(p.width * p.height for p in header.parts)
    check_exr_memory(header, header.pixel_bytes + 12 * largest, "its channels and a float32 colour image")
    try:
        with quiet_native_output() as printed, OpenEXR.File(str(path), separate_channels=True) as exr:
            parts = [ExrPart(dict(p.header), {k: np.array(v.pixels) for k, v in p.channels.items()})
                     for p in exr.parts]
    except (RuntimeError, ValueError, OSError, TypeError) as exc:
        raise ExrError(f"{path}: truncated or corrupt EXR ({error_text(exc)})") from None
    if len(parts) != len(header.parts) or "Exception raised reading" in printed.getvalue():
        # The binding skips a part whose pixels it cannot read, with a warning, instead of raising.
        raise ExrError(f"{path}: truncated or corrupt EXR (a part's pixels cannot be read)")
    for part in parts:
        if str(part.header.get("type", "")).rsplit(".", 1)[-1] in _DEEP:
            raise ExrError(f"{path}: deep EXR parts are not supported (part {part.name!r})")
        shapes = {np.shape(c) for c in part.channels.values()}
        if len(shapes) > 1:
            raise ExrError(f"{path}: subsampled channels are not supported (part {part.name!r})")
    return ExrFile(parts, str(path))


def _scanline_attributes(header: Mapping[str, Any]) -> dict[str, object] | None:
    """A one-part scanline header as :func:`imaging.exr.write_scanlines` takes it, with the values
    ``OpenEXR.File`` would write; None when it holds anything else (tiles, decreasing lines, an
    attribute of another type)."""
    out: dict[str, object] = {"type": b"scanlineimage"}  # OpenEXR.File writes it always
    for key, value in header.items():
        if key in (*_COMPUTED_KEYS, "name"):
            continue
        if key == "type":
            if value != OpenEXR.scanlineimage:
                return None
            out[key] = b"scanlineimage"
        elif key == "compression":
            out[key] = Imath.Compression(int(value))
        elif key == "lineOrder":
            if value != OpenEXR.INCREASING_Y:
                return None
            out[key] = Imath.LineOrder(Imath.LineOrder.INCREASING_Y)
        elif key in ("dataWindow", "displayWindow"):
            (x0, y0), (x1, y1) = value
            out[key] = Imath.Box2i(Imath.V2i(int(x0), int(y0)), Imath.V2i(int(x1), int(y1)))
        elif key == "screenWindowCenter":
            out[key] = Imath.V2f(float(value[0]), float(value[1]))
        elif isinstance(value, str):
            out[key] = value.encode("utf-8")
        elif isinstance(value, float) or (isinstance(value, int) and not isinstance(value, bool)
                                          and -2**31 <= value < 2**31):
            out[key] = value  # float: a 32-bit float attribute, as OpenEXR.File writes a float
        else:
            return None
    return out


def _row_source(values: np.ndarray | ImagePlane) -> tuple[np.dtype, RowSource] | None:
    if isinstance(values, ImagePlane):
        return values.dtype, values.rows
    if values.dtype not in (np.float16, np.float32, np.uint32):
        return None
    return values.dtype, lambda y0, y1: np.ascontiguousarray(values[y0:y1])


def _write_in_blocks(tmp: Path, part: ExrPart, max_bytes: float) -> bool:
    """Write a one-part scanline file a block of rows at a time (see the module notes); False,
    writing nothing, when the part is not one :func:`imaging.exr.write_scanlines` reproduces."""
    attributes = _scanline_attributes(part.header)
    sources = {name: _row_source(values) for name, values in part.channels.items()}
    shapes = {np.shape(values) for values in part.channels.values()}
    if attributes is None or None in sources.values() or len(shapes) != 1 or any(
            getattr(c, "xSampling", 1) != 1 or getattr(c, "ySampling", 1) != 1
            for c in part.header.get("channels") or []):
        return False
    height, width = shapes.pop()
    window = part.header.get("dataWindow")
    if window is not None and (int(window[1][0]) - int(window[0][0]) + 1,
                               int(window[1][1]) - int(window[0][1]) + 1) != (width, height):
        return False
    write_scanlines(tmp, attributes, width, height, sources, max_bytes)
    return True


def _write_whole(tmp: Path, exr: ExrFile) -> None:
    headers = [{k: v for k, v in p.header.items() if k not in _COMPUTED_KEYS} for p in exr.parts]
    # new dicts of contiguous arrays (the binding replaces the values of the dicts it is given)
    channels = [{k: np.ascontiguousarray(v) for k, v in p.channels.items()} for p in exr.parts]
    if len(exr.parts) == 1:
        headers[0].pop("name", None)
        out = OpenEXR.File(headers[0], channels[0])
    else:
        out = OpenEXR.File([OpenEXR.Part(h, c, name=p.name or f"part{i}")
                            for i, (h, c, p) in enumerate(zip(headers, channels, exr.parts))])
    with out:
        out.write(str(tmp))


def write_exr_file(path: str | Path, exr: ExrFile, max_bytes: float = DEFAULT_BLOCK_BYTES) -> None:
    """Write ``exr`` atomically with each part's header as read (compression, windows, tiling,
    attributes); a one-part file stays single-part. A one-part scanline file is written a block
    of rows at a time, its planes within ``max_bytes`` (see the module notes)."""
    path = Path(path)
    if not path.parent.is_dir():
        raise ExrError(f"{path}: output folder does not exist")
    try:
        with atomic_path(path) as tmp:
            if len(exr.parts) != 1 or not _write_in_blocks(tmp, exr.parts[0], max_bytes):
                _write_whole(tmp, exr)
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
    channels' own pixel type, as :class:`ImagePlane` s of it: ``image`` is not copied) and
    ``attributes`` added to its part's header."""
    part = exr.parts[layer.part]
    if image.shape[:2] != np.shape(part.channels[layer.channels[0]]) or image.shape[2] != len(layer.channels):
        raise ExrError(f"{exr.path}: image of shape {image.shape} does not fit layer {layer.name!r}")
    dtype = np.dtype(np.float16 if exr.is_half(layer) else np.float32)
    channels = dict(part.channels)
    for i, name in enumerate(layer.channels):
        channels[name] = ImagePlane(image, i, dtype)
    header = {**part.header, **(attributes or {})}
    parts = list(exr.parts)
    parts[layer.part] = ExrPart(header, channels)
    return replace(exr, parts=parts)
