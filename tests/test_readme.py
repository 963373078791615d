"""The README is a product page whose claims are checked: short, every figure from a result file,
its model names real, its links alive, its Python snippet run as written."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks.readme_tables import MARKERS
from model.registry import registry

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MAX_LINES, MAX_WIDTH, MAX_TABLE_ROWS = 150, 200, 6
# a figure: a decimal number, or a number with a unit of quality, time or size
FIGURE = re.compile(r"\d+\.\d+|\d+\s*(?:dB|%|x\b|s/MP|MB|GB|MiB|GiB|ms\b)")
FENCE = re.compile(r"```.*?```", re.S)
INLINE = re.compile(r"`[^`\n]*`")


def _prose(text: str) -> str:
    """The README without its generated blocks, code blocks and inline code."""
    text = MARKERS.sub("", text)
    return INLINE.sub("", FENCE.sub("", text))


def _tables(text: str) -> list[list[str]]:
    tables, current = [], []
    for line in FENCE.sub("", text).splitlines():
        if line.startswith("|"):
            current.append(line)
        elif current:
            tables.append(current)
            current = []
    return tables + ([current] if current else [])


def test_short_and_narrow() -> None:
    lines = README.read_text().splitlines()
    assert len(lines) <= MAX_LINES
    assert [i + 1 for i, line in enumerate(lines) if len(line) > MAX_WIDTH] == []


def test_tables_are_small_and_every_figure_comes_from_a_result_file() -> None:
    text = README.read_text()
    assert all(len(t) - 2 <= MAX_TABLE_ROWS for t in _tables(text))  # header and rule not counted
    assert FIGURE.findall(_prose(text)) == []
    assert not re.search(r"20\d\d-\d\d-\d\d|measured, not shipped", _prose(text))
    assert {m.group(2) for m in MARKERS.finditer(text)} == {"models", "strip_caption"}


def test_the_checker_sees_a_typed_figure() -> None:
    assert FIGURE.findall(_prose("OIDN is 1.4 dB better, 2x faster.\n<!-- table:models -->\n3.5 dB\n<!-- /table -->"))


def test_model_names_in_its_table_work_and_the_pictures_and_links_exist() -> None:
    text = README.read_text()
    table = MARKERS.search(text[text.index("<!-- table:models -->"):]).group(3)
    names = re.findall(r"^\| `([^`]+)` \|", table, re.M)
    assert names == list(registry().entries)
    for name in names:
        registry().select(name)
    for target in re.findall(r"\]\(([^)#]+)", text):
        if not target.startswith("http"):
            assert (ROOT / target).exists(), target
    assert (ROOT / "docs" / "figures" / "strip.png").is_file() and (ROOT / "docs" / "figures" / "quality_time.png").is_file()


@pytest.mark.slow
@pytest.mark.parametrize("page", ["README.md", "docs/denoise.md"])
def test_the_python_snippet_runs_from_any_folder_as_render_and_denoise_does(page: str, tmp_path: Path) -> None:
    """The page's Python block, run as a user would from a folder of their own, then checked: the
    default model ran its networks for 16 spp with the noise guard, improved the render, and gave
    the image ``render-and-denoise`` writes (denoised.exr) for the same scene, spp, seed and size."""
    from imaging.exr import read_exr
    from pipeline.cli import main
    from scenes.demo import DEMO_SCENE

    snippet = re.search(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S).group(1)
    check = ("\nimport numpy as np\nfrom rendering.render import render as _render\nfrom imaging.metrics import psnr\n"
             "ref = _render(DEMO_SCENE, spp=1024, resolution=(64, 64), seed=9).rgb\n"
             "assert result.choice == 'high' and result.guard_weight is not None, result\n"
             "assert result.models == ('flat-s-allspp', 'unet-m-k5-lowspp', 'unet-m-k5-lowspp-b'), result.models\n"
             "assert psnr(result.image, ref) > psnr(noisy.rgb, ref) + 1.0\n"
             "assert image.shape == noisy.rgb.shape and np.isfinite(image).all()\n"
             "np.save('snippet.npy', result.image)\nprint('ok')\n")
    user = tmp_path / "elsewhere"
    user.mkdir()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    done = subprocess.run([sys.executable, "-c", snippet + check], cwd=user, env=env, capture_output=True,
                          text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip().endswith("ok")
    assert main([str(DEMO_SCENE), "--spp", "16", "--res", "64", "64", "--seed", "0", "--no-compare", "--quiet",
                 "--out", str(tmp_path / "run")]) == 0
    np.testing.assert_array_equal(np.load(user / "snippet.npy"), read_exr(tmp_path / "run" / "denoised.exr").rgb)
