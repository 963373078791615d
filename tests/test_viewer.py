"""The report viewer: what the page embeds (checked in Python), and how it behaves in a real
headless Chromium: keys flip the four images in place, f / r / 5 show the error and weight maps,
exposure changes the tonemapped pixels, and zoom shows single pixels as uniform blocks."""
from __future__ import annotations

import base64
import json
import os
import re
import zlib
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main as render_main
from pipeline.viewer import Page, Table, ViewerRow, ViewerSet, flip_map
from tests.cdp import Browser, find_chromium

DEMO = Path(__file__).resolve().parents[1] / "scenes" / "examples" / "demo.xml"
W, H = 32, 24


def embedded(page_html: str, ident: str) -> tuple[dict[str, str], bytes]:
    match = re.search(rf'<script type="application/octet-stream" id="img-{ident}" ([^>]*)>([^<]*)</script>',
                      page_html)
    attrs = dict(re.findall(r'data-(\w+)="([^"]*)"', match.group(1)))
    return attrs, zlib.decompress(base64.b64decode(match.group(2)))


def test_page_embeds_float16_radiance_and_8bit_maps(rng: np.random.Generator) -> None:
    rgb = (rng.random((5, 7, 3)) * 10 ** rng.uniform(-3, 3, (5, 7, 1))).astype(np.float32)
    rgb[0, 0] = [1e6, np.nan, -np.inf]
    page = Page("t")
    ident, map_id = page.radiance(rgb), page.scalar(rng.random((5, 7)))
    page.add_set(ViewerSet("s", [ViewerRow("a", ident), ViewerRow("m", map_id, kind="weight")], ident))
    text = page.html()
    attrs, raw = embedded(text, ident)
    assert (attrs["w"], attrs["h"], attrs["c"], attrs["dtype"]) == ("7", "5", "3", "f16")
    n = rgb.size
    halves = (np.frombuffer(raw[:n], np.uint8).astype(np.uint16)
              | (np.frombuffer(raw[n:], np.uint8).astype(np.uint16) << 8)).view(np.float16)
    back = halves.astype(np.float32).reshape(rgb.shape)
    assert back[0, 0].tolist() == [65504.0, 0.0, -65504.0]
    np.testing.assert_allclose(back[1:], rgb[1:], rtol=1e-3)
    attrs, raw = embedded(text, map_id)
    assert attrs["dtype"] == "u8" and len(raw) == 35
    payload = json.loads(re.search(r'id="viewer-payload">(.*?)</script>', text, re.S).group(1))
    assert payload["sets"][0]["rows"][1]["kind"] == "weight" and len(payload["colormaps"]["magma"]) == 768
    # self-contained: nothing is fetched
    assert not re.search(r"<(script|link|img)[^>]*\s(src|href)=['\"]?(https?:|//)", text)
    assert "http://" not in text and "https://" not in text


def whole_image_tags(rgb: np.ndarray, values: np.ndarray) -> list[str]:
    """The two images' script tags as embedded from whole images (before the row blocks)."""
    half = np.clip(np.nan_to_num(rgb.astype(np.float32), nan=0.0, posinf=65504, neginf=-65504),
                   -65504, 65504).astype("<f2")
    planes = np.ascontiguousarray(half.view(np.uint8).reshape(-1, 2).T).tobytes()
    quantised = np.round(np.clip(np.nan_to_num(values.astype(np.float32)), 0, 1) * 255).astype(np.uint8)
    h, w = values.shape
    return [f'<script type="application/octet-stream" id="img-{i}" data-w="{w}" data-h="{h}" data-c="{c}" '
            f'data-dtype="{dtype}">{base64.b64encode(zlib.compress(raw, 6)).decode("ascii")}</script>'
            for i, (raw, c, dtype) in enumerate([(planes, 3, "f16"), (quantised.tobytes(), 1, "u8")])]


@pytest.mark.parametrize("max_bytes", [1, 3000, 16 * 2**20])  # one row per block, a few, the whole
def test_page_embeds_in_row_blocks_and_streams_the_file(tmp_path: Path, rng: np.random.Generator,
                                                        monkeypatch: pytest.MonkeyPatch, max_bytes: int) -> None:
    import pipeline.viewer as viewer

    monkeypatch.setattr(viewer, "SPOOL_MEMORY", 2000)  # the deflated images go to a file
    monkeypatch.setattr(viewer, "BASE64_PIECE", 3 * 100)
    rgb = (rng.random((37, 29, 3)) * 10 ** rng.uniform(-3, 5, (37, 29, 1))).astype(np.float64)
    rgb[0, 0] = [1e6, np.nan, -np.inf]
    values = rng.random((37, 29)) * 1.2 - 0.1
    page = Page("t", max_bytes=max_bytes)
    ids = page.radiance(rgb), page.scalar(values[:, :, None])
    page.add_set(ViewerSet("s", [ViewerRow("a", ids[0]), ViewerRow("m", ids[1], kind="weight")], ids[0]))
    text = page.html()
    assert "\n".join(whole_image_tags(rgb, values)) in text
    page.write(tmp_path / "r.html")
    assert (tmp_path / "r.html").read_bytes() == text.encode("utf-8")


def test_page_scratch_stays_within_its_blocks(tmp_path: Path, rng: np.random.Generator,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """numpy's (and Python's) allocations while embedding a 512x512 image and a map and writing
    the page, its deflated images spooled to a file: the blocks, the deflate state and a piece of
    base64 (the whole float16 planes alone: 1.5 MB; the page: 2 MB)."""
    import tracemalloc

    import pipeline.viewer as viewer

    monkeypatch.setattr(viewer, "SPOOL_MEMORY", 1)
    rgb = rng.random((512, 512, 3), dtype=np.float32)
    max_bytes = 128 * 2**10
    Page("warm-up").write(tmp_path / "w.html")  # the colour maps' imports
    tracemalloc.start()
    try:
        page = Page("t", max_bytes=max_bytes)
        page.add_set(ViewerSet("s", [ViewerRow("a", page.radiance(rgb), page.scalar(rgb[:, :, 0]))]))
        page.write(tmp_path / "r.html")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < max_bytes + 2**20


def test_table_marks_the_best_cell_per_column() -> None:
    table = Table(["image", "PSNR dB", "relMSE"], [["a", 30.0, 0.1], ["b", 32.0, 0.2]],
                  better={"PSNR dB": "high", "relMSE": "low"}).html()
    assert "<td class='best'>32</td>" in table and "<td class='best'>0.1</td>" in table


def test_flip_map_mean_is_the_flip_metric(rng: np.random.Generator) -> None:
    from imaging.metrics import flip

    a, b = rng.random((16, 16, 3)).astype(np.float32), rng.random((16, 16, 3)).astype(np.float32)
    error = flip_map(a, b)
    assert error.shape == (16, 16) and 0 <= error.min() and error.max() <= 1
    assert error.mean() == pytest.approx(flip(a, b), rel=1e-5)


# ----------------------------------------------------------------------------- in a browser
@pytest.fixture(scope="module")
def chromium() -> str:
    path = find_chromium()
    if path is None:
        message = "no chromium: `make` installs Debian's chromium when run as root"
        if os.environ.get("CI"):
            pytest.fail(message)
        pytest.skip(message)
    return path


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real render-and-denoise run as `make demo` makes it, small: the shipped model, the noise
    guard, OIDN compared by default, a 64-spp reference."""
    pytest.importorskip("pyoidn", reason="make installs pyoidn (the oidn extra)")
    folder = tmp_path_factory.mktemp("report")
    assert render_main([str(DEMO), "--spp", "4", "--res", str(W), str(H), "--reference-spp", "64",
                        "--out", str(folder / "run"), "--quiet"]) == 0
    return folder / "run" / "report.html"


class Viewer:
    """The report open in a browser, with the canvas's content read back from screenshots."""

    def __init__(self, browser: Browser, path: Path) -> None:
        self.b = browser
        browser.open(path)
        browser.wait_for("Number(document.body.dataset.draws) >= 1 && !document.body.dataset.busy")

    def press(self, key: str, shown: str | None = None) -> None:
        before = int(self.b.eval("document.body.dataset.draws"))
        self.b.press(key)
        self.b.wait_for(f"Number(document.body.dataset.draws) > {before} && !document.body.dataset.busy")
        if shown is not None:
            assert self.b.eval("document.body.dataset.shown") == shown

    def state(self) -> dict:
        return self.b.eval("JSON.parse(JSON.stringify(viewer.state))")

    def image(self) -> np.ndarray:
        """The displayed image as it appears on screen: zoom*H x zoom*W x 3 uint8."""
        rect = self.b.eval("(() => { const c = document.querySelector('canvas.stage');"
                           " const r = c.getBoundingClientRect();"
                           " return [r.left + c.clientLeft, r.top + c.clientTop]; })()")
        s = self.state()
        return self.b.screenshot({"x": rect[0] + s["panX"], "y": rect[1] + s["panY"],
                                  "width": W * s["zoom"], "height": H * s["zoom"]})


def test_keys_flip_images_in_place_and_zoom_shows_pixel_blocks(chromium: str, report: Path) -> None:
    with Browser(chromium, 1000, 800) as browser:
        view = Viewer(browser, report)
        shots = {}
        for key, label in zip("12345", ("noisy", "ours", "OIDN colour-only", "OIDN + albedo + normal", "reference")):
            view.press(key, f"0/{label}/image")
            shots[label] = view.image().astype(int)
        zoom = view.state()["zoom"]
        assert zoom >= 1 and shots["noisy"].shape == (H * zoom, W * zoom, 3)
        labels = list(shots)
        for i, a in enumerate(labels):  # every key shows another image, at the same place and zoom
            for b in labels[i + 1:]:
                assert np.abs(shots[a] - shots[b]).mean() > 0.5, (a, b)
        assert view.state()["zoom"] == zoom

        view.press("2", "0/ours/image")
        view.press("f", "0/ours/flip")
        flip_shot = view.image().astype(int)
        assert np.abs(flip_shot - shots["ours"]).mean() > 5
        view.press("3", "0/OIDN colour-only/flip")  # the column stays while the row flips
        assert np.abs(view.image().astype(int) - flip_shot).mean() > 0.5
        view.press("r", "0/OIDN colour-only/relse")
        view.press("6", "0/noise guard weight/image")
        view.press("i")
        view.press("2", "0/ours/image")

        for _ in range(4):  # +2 EV: the tonemapped pixels get brighter
            view.press("]")
        assert view.state()["exposure"] == 2.0
        assert view.image().mean() > shots["ours"].mean() + 10

        view.press("[")
        while view.state()["zoom"] < 32:
            view.press("+")
        state = view.state()
        assert state["zoom"] == 32
        rect = browser.eval("(() => { const c = document.querySelector('canvas.stage');"
                            " const r = c.getBoundingClientRect();"
                            " return [r.left + c.clientLeft, r.top + c.clientTop, c.clientWidth, c.clientHeight]; })()")
        shot = browser.screenshot({"x": rect[0], "y": rect[1], "width": rect[2], "height": rect[3]}).astype(int)
        z = 32
        x0 = state["panX"] % z
        y0 = state["panY"] % z
        whole_w, whole_h = (rect[2] - x0) // z, (rect[3] - y0) // z
        blocks = shot[y0:y0 + whole_h * z, x0:x0 + whole_w * z].reshape(whole_h, z, whole_w, z, 3)
        assert whole_w >= 8 and whole_h >= 8
        caption = browser.eval("(() => { const r = document.querySelector('.caption').getBoundingClientRect();"
                               " return [r.right, r.bottom]; })()")  # the label over the top-left corner
        free = np.ones((whole_h, whole_w), bool)
        free[:int((caption[1] - rect[1] - y0) // z) + 1, :int((caption[0] - rect[0] - x0) // z) + 1] = False
        # every screen block of 32x32 pixels is one colour: one image pixel, no smoothing
        uniform = (blocks == blocks[:, :1, :, :1, :]).all(axis=(1, 3, 4))
        assert uniform[free].all() and free.sum() > 0.9 * free.size
        colours = {tuple(c) for c in blocks[:, 0, :, 0, :][free].reshape(-1, 3)}
        assert len(colours) > 10  # and the blocks are image pixels, not an empty stage

        view.press("1", "0/noisy/image")  # flipping keeps the zoom and the pan
        assert {k: view.state()[k] for k in ("zoom", "panX", "panY")} == \
            {k: state[k] for k in ("zoom", "panX", "panY")}
