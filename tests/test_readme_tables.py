"""The README's and docs' measured tables are what ``python -m benchmarks.readme_tables`` renders
from the result files: a hand-edited or stale figure fails here."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from benchmarks import readme_tables
from benchmarks.readme_tables import MARKERS, TABLES, Results, caption, pages, render_page, stale_tables

ROOT = Path(__file__).resolve().parents[1]


def test_every_table_matches_its_result_file() -> None:
    assert stale_tables() == [], "run: python -m benchmarks.readme_tables"


def test_every_table_is_shown_and_every_marker_known() -> None:
    shown = {m.group(2) for page in pages() for m in MARKERS.finditer(page.read_text())}
    assert shown == set(TABLES)


@pytest.fixture
def copy(tmp_path: Path) -> Path:
    """The pages and the result files they are rendered from, in a folder of their own."""
    shutil.copy(ROOT / "README.md", tmp_path)
    shutil.copytree(ROOT / "docs", tmp_path / "docs")
    shutil.copytree(ROOT / "benchmarks" / "results", tmp_path / "benchmarks" / "results")
    for path in (ROOT / "experiments" / "training").glob("**/*.json*"):  # stage-STAGE/ logs too
        target = tmp_path / path.parent.relative_to(ROOT)
        target.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, target)
    return tmp_path


def test_a_changed_figure_or_result_is_caught_and_rewritten(copy: Path) -> None:
    readme = copy / "README.md"
    text = readme.read_text()
    table = MARKERS.search(text[text.index("<!-- table:models -->"):])
    assert table and "| `fast` | " in table.group(3)
    readme.write_text(text.replace("| `fast` | ", "| `fast` | 99.99 | ", 1))
    assert stale_tables(copy) == ["README.md: table models"]
    result = copy / "benchmarks" / "results" / "budget.json"
    data = json.loads(result.read_text())
    data["summary"]["per_budget"]["10"]["mean_psnr"] = 12.5
    result.write_text(json.dumps(data))
    assert stale_tables(copy) == ["README.md: table models", "docs/evaluate.md: table budget"]
    rewritten = render_page(readme.read_text(), Results(copy))
    assert rewritten == text


def test_unknown_table_is_an_error() -> None:
    with pytest.raises(ValueError, match="docs/x.md: unknown table 'nope'"):
        render_page("<!-- table:nope -->\n<!-- /table -->\n", Results(), "docs/x.md")


def test_caption_names_command_file_date_and_load() -> None:
    data = {"command": "python -m benchmarks.x --a 1", "date": "2026-12-02 01:11",
            "machine": {"cores": 2, "load_before": 1.64, "load_after": 2.38}}
    assert caption("ignored", "benchmarks/results/x.json", data, "Note.") == (
        "Source: `python -m benchmarks.x --a 1` → `benchmarks/results/x.json`; 2026-12-02 01:11; "
        "load 1.6 at the start, 2.4 at the end on 2 cores. Note.")
    assert caption("python -m benchmarks.y", "y.json") == (
        "Source: `python -m benchmarks.y` (command not recorded in the file) → `y.json`; date not recorded; "
        "load not recorded.")


def test_check_exits_1_on_a_stale_table(copy: Path, capsys: pytest.CaptureFixture) -> None:
    root = ["--root", str(copy)]
    assert readme_tables.main(["--check", *root]) == 0
    page = copy / "docs" / "evaluate.md"
    page.write_text(page.read_text().replace("| 10 | 17/17 |", "| 10 | 16/17 |"))
    assert readme_tables.main(["--check", *root]) == 1
    assert capsys.readouterr().out == "stale: docs/evaluate.md: table budget\n"
    assert readme_tables.main(root) == 0 and readme_tables.main(["--check", *root]) == 0
    assert "| 10 | 17/17 |" in page.read_text()
