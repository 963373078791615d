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
import zlib
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from imaging.atomic_io import write_text_atomic
from imaging.exr import HALF_MAX
from imaging.metrics import tonemap

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


class Page:
    """An HTML report being put together: image sets for the viewer, then HTML sections."""

    def __init__(self, title: str, subtitle: str = "") -> None:
        self.title, self.subtitle = title, subtitle
        self.sets: list[ViewerSet] = []
        self.sections: list[str] = []
        self._images: list[str] = []
        self._max_h = 0

    def _embed(self, raw: bytes, shape: tuple[int, int, int], dtype: str) -> str:
        ident = str(len(self._images))
        h, w, c = shape
        data = base64.b64encode(zlib.compress(raw, 6)).decode("ascii")
        self._images.append(f'<script type="application/octet-stream" id="img-{ident}" data-w="{w}" '
                            f'data-h="{h}" data-c="{c}" data-dtype="{dtype}">{data}</script>')
        self._max_h = max(self._max_h, h)
        return ident

    def radiance(self, rgb: np.ndarray) -> str:
        """Embed HxWx3 linear radiance (float16: finite values beyond 65504 saturate, NaN -> 0);
        return its id."""
        rgb = np.asarray(rgb, np.float32)
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"expected an HxWx3 image, got shape {rgb.shape}")
        half = np.clip(np.nan_to_num(rgb, nan=0.0, posinf=HALF_MAX, neginf=-HALF_MAX),
                       -HALF_MAX, HALF_MAX).astype("<f2")
        planes = half.view(np.uint8).reshape(-1, 2).T  # low bytes, then high bytes: deflates better
        return self._embed(np.ascontiguousarray(planes).tobytes(), rgb.shape, "f16")

    def scalar(self, values: np.ndarray) -> str:
        """Embed an HxW map of values in [0, 1] (8 bits); return its id."""
        values = np.asarray(values, np.float32)
        if values.ndim == 3 and values.shape[2] == 1:
            values = values[:, :, 0]
        if values.ndim != 2:
            raise ValueError(f"expected an HxW map, got shape {values.shape}")
        quantised = np.round(np.clip(np.nan_to_num(values), 0.0, 1.0) * 255).astype(np.uint8)
        return self._embed(quantised.tobytes(), (*values.shape, 1), "u8")

    def add_set(self, viewer_set: ViewerSet) -> None:
        self.sets.append(viewer_set)

    def add_section(self, title: str, body: str) -> None:
        """An HTML section below the viewer; ``body`` is HTML (escape text with :func:`html.escape`)."""
        self.sections.append(f"<section><h2>{html.escape(title)}</h2>{body}</section>")

    def html(self) -> str:
        payload = {"sets": [asdict(s) for s in self.sets], "columns": COLUMNS,
                   "colormaps": {name: _colormap(name) for name in ("magma", "viridis")}}
        stage_h = int(min(720, max(384, 2 * self._max_h + 2)))  # small images fit at 2x
        parts = {"CSS": _asset("viewer.css").replace("{{STAGE_H}}", str(stage_h)),
                 "TITLE": html.escape(self.title), "SUBTITLE": html.escape(self.subtitle),
                 "VIEWER": VIEWER_BLOCK if self.sets else "", "CONTENT": "\n".join(self.sections),
                 "PAYLOAD": json.dumps(payload).replace("</", "<\\/"),
                 "IMAGES": "\n".join(self._images), "JS": _asset("viewer.js")}
        return re.sub(r"\{\{([A-Z]+)\}\}", lambda m: parts[m.group(1)], _asset("page.html"))

    def write(self, path: str | Path) -> Path:
        path = Path(path)
        write_text_atomic(path, self.html())
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
