"""Every command's usage errors: one line on stderr naming the problem, no usage text, exit code 2."""
from __future__ import annotations

from collections.abc import Callable

import pytest

from dataset_gen.cli import main as generate_main
from model.cli import main as train_main
from pipeline.cli import denoise_main, main as render_main, tradeoff_main

COMMANDS: dict[str, Callable[[list[str]], int]] = {
    "render-and-denoise": render_main, "denoise": denoise_main, "tradeoff": tradeoff_main,
    "generate-dataset": generate_main, "train": train_main,
}
CASES = [
    ("render-and-denoise", ["scene.xml", "--no-such-flag"], "unrecognized arguments: --no-such-flag"),
    ("render-and-denoise", ["scene.xml", "--spp", "0"], "--spp"),
    ("render-and-denoise", [], "scene"),
    ("denoise", ["in.exr", "out.exr", "--bogus"], "unrecognized arguments: --bogus"),
    ("denoise", ["in.exr"], "output"),
    ("tradeoff", ["scene.xml", "--reference-spp", "4", "--bogus"], "unrecognized arguments: --bogus"),
    ("tradeoff", ["scene.xml"], "--reference"),
    ("tradeoff", ["scene.xml", "--reference-spp", "4", "--metric", "nope"], "--metric"),
    ("generate-dataset", ["--scenes", "1", "--out", "x", "--bogus"], "unrecognized arguments: --bogus"),
    ("generate-dataset", ["--out", "x"], "--scenes"),
    ("train", ["--out", "x", "--bogus"], "unrecognized arguments: --bogus"),
    ("train", ["--out", "x", "--preset", "huge"], "--preset"),
]


@pytest.mark.parametrize("command, argv, needle", CASES)
def test_usage_error_is_one_line_exit_2(command: str, argv: list[str], needle: str,
                                        capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exc:
        COMMANDS[command](argv)
    out, err = capsys.readouterr()
    assert exc.value.code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"{command}: error: ") and needle in lines[0], lines[0]
    assert "usage:" not in err and "Traceback" not in err and out == ""


def test_every_command_is_covered() -> None:
    assert {c for c, _, _ in CASES} == set(COMMANDS)
