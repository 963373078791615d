"""Self-contained interactive HTML reports: one file, no network, no external scripts.

A :class:`Page` holds *sets* of images (a run's noisy / ours / OIDN / reference; a scoreboard's
scenes). Radiance images are embedded as linear float16 (HxWx3, byte planes, deflate, base64) and
tonemapped in the page at the chosen exposure; FLIP and weight maps as 8-bit [0, 1] values shown
in false colour; the relative squared error is computed in the page from an image and its set's
reference. The viewer (``viewer_assets/viewer.js``) shows native pixels, zooms by powers of two
with nearest-neighbour blocks, pans, and flips between a set's rows with keys 1-9 at the same zoom
and pan; ``i``/``f``/``r`` pick image / FLIP / relative squared error. Tables, plots and notes go
below the viewer as HTML sections.
"""
from __future__ import annotations

import base64
import html
import json
import math
import re
import tempfile
import weakref
import zlib
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from imaging.atomic_io import atomic_path
from imaging.blocks import DEFAULT_BLOCK_BYTES, row_blocks
from imaging.exr import HALF_MAX
from imaging.metrics import tonemap

RADIANCE_BYTES_PER_VALUE = 16  # Page.radiance / scalar: float32 and float16 temporaries per value
SPOOL_MEMORY = 8 * 2**20  # a page's deflated images stay in memory up to this, then go to a file
BASE64_PIECE = 3 * 2**16  # deflated bytes encoded at a time when the page is written (a multiple of 3)
COLUMNS = [{"id": "image", "label": "image", "key": "i"},
           {"id": "flip", "label": "FLIP", "key": "f"},
           {"id": "relse", "label": "rel. squared error", "key": "r"}]
VIEWER_BLOCK = """<section id="viewer">
<div class="toolbar">
 <div class="group"><select class="set-select" aria-label="set"></select></div>
 <div class="group rows"></div>
 <div class="group cols"></div>
 <div class="group"><span>exposure</span><input class="exposure" type="range" min="-12" max="12"
   step="0.1" value="0" aria-label="exposure"><span class="exposure-label"></span>
   <select class="tonemap" aria-label="tonemap"><option value="metric">x/(1+x), gamma 2.2</option>
   <option value="srgb">sRGB, clipped</option></select></div>
 <div class="group"><button class="zoom-out">&minus;</button><span class="zoom-label"></span>
   <button class="zoom-in">+</button><button class="zoom-fit">fit</button></div>
</div>
<div class="stage-wrap"><canvas class="stage"></canvas><span class="caption"></span></div>
<div class="statusbar"><span class="pixel"></span><span class="legend"></span><span class="set-note"></span>
<span class="message"></span></div>
<p class="help">keys: 1-9 image, i / f / r image / FLIP / relative squared error, + / - / wheel zoom,
0 fit, drag or arrows pan, [ / ] exposure, n / p next / previous set</p>
</section>"""


@dataclass
class ViewerRow:
    """One flippable entry of a set: ``image`` (id of a radiance image, or of a [0, 1] map when
    ``kind`` is ``weight``) and optionally the id of its FLIP map against the set's reference."""

    label: str
    image: str
    flip: str | None = None
    kind: str = "radiance"


@dataclass
class ViewerSet:
    """Images of one scene (and spp) that flip in place; ``reference``: id of the reference image."""

    name: str
    rows: list[ViewerRow]
    reference: str | None = None
    note: str = ""


def _asset(name: str) -> str:
    return resources.files("pipeline").joinpath("viewer_assets", name).read_text(encoding="utf-8")


def _colormap(name: str) -> list[int]:
    from matplotlib import colormaps

    table = colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3]
    return [int(v) for v in np.round(table * 255).astype(np.uint8).ravel()]


def flip_map(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """HxW float32 FLIP error map in [0, 1] (LDR FLIP of the tonemapped images, as
    :func:`imaging.metrics.flip` averages it)."""
    import flip_evaluator

    test, ref = (np.ascontiguousarray(tonemap(x).astype(np.float32)) for x in (image, reference))
    error, _, _ = flip_evaluator.evaluate(ref, test, "LDR", applyMagma=False)
    return np.asarray(error, np.float32).reshape(image.shape[:2])


@dataclass(frozen=True)
class _Embedded:
    """An embedded image: its tag's attributes and where its deflated bytes lie in the spool."""

    ident: str
    attributes: str
    offset: int
    length: int


def _half_bytes(rgb: np.ndarray, byte: int) -> bytes:
    """Byte ``byte`` (0: low, 1: high) of each value of ``rgb`` as little-endian float16 (finite
    values beyond 65504 saturate, NaN -> 0)."""
    rgb = np.asarray(rgb, np.float32)
    half = np.clip(np.nan_to_num(rgb, nan=0.0, posinf=HALF_MAX, neginf=-HALF_MAX),
                   -HALF_MAX, HALF_MAX).astype("<f2")
    return half.view(np.uint8).reshape(-1, 2)[:, byte].tobytes()


class Page:
    """An HTML report being put together: image sets for the viewer, then HTML sections.

    Embedded images are deflated a block of rows at a time into a spool (memory while small, a
    temporary file beyond ``SPOOL_MEMORY``) and :meth:`write` streams the page from it, base64 a
    piece at a time: neither the images' bytes nor the page is ever whole in memory there
    (:meth:`html` builds the whole text)."""

    def __init__(self, title: str, subtitle: str = "", max_bytes: float = DEFAULT_BLOCK_BYTES) -> None:
        self.title, self.subtitle = title, subtitle
        self.sets: list[ViewerSet] = []
        self.sections: list[str] = []
        self.max_bytes = max_bytes
        self._images: list[_Embedded] = []
        self._spool = tempfile.SpooledTemporaryFile(max_size=SPOOL_MEMORY)
        weakref.finalize(self, self._spool.close)
        self._max_h = 0

    def _embed(self, pieces: Iterator[bytes], shape: tuple[int, int, int], dtype: str) -> str:
        """Deflate ``pieces`` (as ``zlib.compress(b"".join(pieces), 6)`` would) into the spool."""
        ident = str(len(self._images))
        h, w, c = shape
        deflate = zlib.compressobj(6)
        self._spool.seek(0, 2)
        offset = self._spool.tell()
        for piece in pieces:
            self._spool.write(deflate.compress(piece))
        self._spool.write(deflate.flush())
        self._images.append(_Embedded(ident, f'data-w="{w}" data-h="{h}" data-c="{c}" data-dtype="{dtype}"',
                                      offset, self._spool.tell() - offset))
        self._max_h = max(self._max_h, h)
        return ident

    def _blocks(self, image: np.ndarray, bytes_per_value: float) -> Iterator[slice]:
        width = image.shape[1] * (image.shape[2] if image.ndim == 3 else 1)
        return row_blocks(image.shape[0], width, bytes_per_value, self.max_bytes)

    def radiance(self, rgb: np.ndarray) -> str:
        """Embed HxWx3 linear radiance (float16: finite values beyond 65504 saturate, NaN -> 0);
        return its id. The low bytes of all values, then the high bytes (it deflates better)."""
        rgb = np.asarray(rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"expected an HxWx3 image, got shape {rgb.shape}")
        pieces = (_half_bytes(rgb[rows], byte) for byte in (0, 1)
                  for rows in self._blocks(rgb, RADIANCE_BYTES_PER_VALUE))
        return self._embed(pieces, rgb.shape, "f16")

    def scalar(self, values: np.ndarray) -> str:
        """Embed an HxW map of values in [0, 1] (8 bits); return its id."""
        values = np.asarray(values)
        if values.ndim == 3 and values.shape[2] == 1:
            values = values[:, :, 0]
        if values.ndim != 2:
            raise ValueError(f"expected an HxW map, got shape {values.shape}")
        pieces = (np.round(np.clip(np.nan_to_num(np.asarray(values[rows], np.float32)), 0.0, 1.0) * 255)
                  .astype(np.uint8).tobytes() for rows in self._blocks(values, RADIANCE_BYTES_PER_VALUE))
        return self._embed(pieces, (*values.shape, 1), "u8")

    def add_set(self, viewer_set: ViewerSet) -> None:
        self.sets.append(viewer_set)

    def add_section(self, title: str, body: str) -> None:
        """An HTML section below the viewer; ``body`` is HTML (escape text with :func:`html.escape`)."""
        self.sections.append(f"<section><h2>{html.escape(title)}</h2>{body}</section>")

    def _image_text(self) -> Iterator[str]:
        """The embedded images' script tags, one line each, a piece at a time."""
        for i, image in enumerate(self._images):
            if i:
                yield "\n"
            yield f'<script type="application/octet-stream" id="img-{image.ident}" {image.attributes}>'
            self._spool.seek(image.offset)
            left = image.length
            while left:
                piece = self._spool.read(min(left, BASE64_PIECE))
                left -= len(piece)
                yield base64.b64encode(piece).decode("ascii")
            yield "</script>"

    def _text(self) -> Iterator[str]:
        """The page's text in order, a piece at a time (the images streamed from the spool)."""
        payload = {"sets": [asdict(s) for s in self.sets], "columns": COLUMNS,
                   "colormaps": {name: _colormap(name) for name in ("magma", "viridis")}}
        stage_h = int(min(720, max(384, 2 * self._max_h + 2)))  # small images fit at 2x
        parts = {"CSS": _asset("viewer.css").replace("{{STAGE_H}}", str(stage_h)),
                 "TITLE": html.escape(self.title), "SUBTITLE": html.escape(self.subtitle),
                 "VIEWER": VIEWER_BLOCK if self.sets else "", "CONTENT": "\n".join(self.sections),
                 "PAYLOAD": json.dumps(payload).replace("</", "<\\/"), "JS": _asset("viewer.js")}
        template, at = _asset("page.html"), 0
        for match in re.finditer(r"\{\{([A-Z]+)\}\}", template):
            yield template[at:match.start()]
            if match.group(1) == "IMAGES":
                yield from self._image_text()
            else:
                yield parts[match.group(1)]
            at = match.end()
        yield template[at:]

    def html(self) -> str:
        return "".join(self._text())

    def write(self, path: str | Path) -> Path:
        """Write the page atomically (UTF-8), a piece at a time."""
        path = Path(path)
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            for piece in self._text():
                fh.write(piece.encode("utf-8"))
        return path


# ------------------------------------------------------------------------------- HTML helpers
def fmt(value: Any, digits: int = 4) -> str:
    """A table cell's text: floats to ``digits`` significant digits, None as '-'."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return "inf" if math.isinf(value) else ("-" if math.isnan(value) else f"{value:.{digits}g}")
    return html.escape(str(value))


@dataclass
class Table:
    """An HTML table; ``better`` maps a column to 'high' or 'low': its best cell is marked."""

    header: list[str]
    rows: list[list[Any]] = field(default_factory=list)
    better: dict[str, str] = field(default_factory=dict)
    digits: int = 4

    def html(self) -> str:
        best: dict[int, float] = {}
        for j, name in enumerate(self.header):
            sense = self.better.get(name)
            values = [r[j] for r in self.rows if isinstance(r[j], (int, float)) and math.isfinite(r[j])]
            if sense and len(values) > 1:
                best[j] = max(values) if sense == "high" else min(values)
        head = "".join(f"<th>{html.escape(h)}</th>" for h in self.header)
        body = ""
        for row in self.rows:
            cells = "".join(
                f"<td class='best'>{fmt(v, self.digits)}</td>" if j in best and v == best[j]
                else f"<td>{fmt(v, self.digits)}</td>" for j, v in enumerate(row))
            body += f"<tr>{cells}</tr>"
        return f"<table><tr>{head}</tr>{body}</table>"


def png_figure(png: bytes, caption: str) -> str:
    """A PNG embedded as a data URI, with a caption."""
    uri = "data:image/png;base64," + base64.b64encode(png).decode("ascii")
    return f"<figure><img src='{uri}' alt='{html.escape(caption)}'><figcaption>{html.escape(caption)}" \
           "</figcaption></figure>"


def details(value: Any) -> str:
    """Pretty-printed JSON of ``value`` in a <pre> block."""
    return f"<pre>{html.escape(json.dumps(value, indent=1, default=str))}</pre>"
