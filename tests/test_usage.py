"""Every command's usage errors: one line on stderr naming the problem, no usage text, exit code 2;
other errors one line too (exit code 1); the argument types the commands share."""
from __future__ import annotations

import argparse
from collections.abc import Callable

import pytest

from dataset_gen.cli import main as generate_main
from imaging.errors import DenoiserError
from console.usage import OneLineParser, int_list, name_list, name_value, positive_float, positive_int, size_list
from training.cli import main as train_main
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


def test_runtime_errors_are_one_line_like_usage_errors(capsys: pytest.CaptureFixture) -> None:
    parser = OneLineParser(prog="cmd")
    assert parser.fail(DenoiserError("scene.xml: bad\nsecond line")) == 1
    assert parser.fail(OSError(28, "No space left on device", "/out/x.exr"), "rank 1: ") == 1
    assert parser.fail(ValueError()) == 1
    assert parser.interrupted("; re-run it") == 130
    assert capsys.readouterr().err.splitlines() == [
        "cmd: error: scene.xml: bad", "cmd: error: rank 1: No space left on device: /out/x.exr",
        "cmd: error: ValueError", "cmd: interrupted; re-run it"]


def test_an_allocation_no_check_foresaw_is_one_line(capsys: pytest.CaptureFixture) -> None:
    """A MemoryError (numpy's, with its size) ends a command as any other error: one line, exit 1."""
    import numpy as np

    parser = OneLineParser(prog="cmd")
    assert parser.attempt(lambda: np.empty((2**20, 2**20, 3), np.float32)) == (None, 1)
    assert parser.attempt(lambda: (_ for _ in ()).throw(MemoryError())) == (None, 1)
    first, second = capsys.readouterr().err.splitlines()
    assert first.startswith("cmd: error: out of memory: Unable to allocate ") and "(1048576, 1048576, 3)" in first
    assert second == "cmd: error: out of memory: an allocation failed"


@pytest.mark.parametrize("kind, text, value", [
    (int_list, "4,16,,128", (4, 16, 128)), (name_list, "a,,b", ("a", "b")), (name_value, "x=1=2", ("x", "1=2")),
    (positive_int, "3", 3), (positive_float, "0.5", 0.5), (size_list, "1920x1080, 64X1", [(1920, 1080), (64, 1)])])
def test_argument_types(kind: Callable[[str], object], text: str, value: object) -> None:
    assert kind(text) == value


@pytest.mark.parametrize("kind, text", [
    (int_list, "4,x"), (int_list, "4,0"), (int_list, ","), (name_value, "=1"), (name_value, "x"),
    (positive_int, "0"), (positive_int, "1.5"), (positive_float, "inf"), (positive_float, "nan"),
    (positive_float, "-1"), (size_list, "12"), (size_list, "0x5"), (size_list, ","), (size_list, "2x3x4")])
def test_bad_arguments_are_refused(kind: Callable[[str], object], text: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=repr(text)):
        kind(text)
