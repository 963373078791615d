"""A command's start on the perf_counter clock: a fresh interpreter's, and unreadable stat files."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from console.clock import process_started

ROOT = Path(__file__).resolve().parents[1]


def test_a_fresh_process_started_before_its_first_line() -> None:
    # the child sleeps 1 s before it asks: its start lies that far (and less than a minute) back
    code = ("import time; time.sleep(1.0); from console.clock import process_started; "
            "print(time.perf_counter() - process_started())")
    age = float(subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                               check=True).stdout)
    assert 1.0 - 0.02 <= age < 60.0  # 0.02: the start is known to the clock tick (10 ms)


def test_this_process_started_in_the_past() -> None:
    assert process_started() < time.perf_counter()


def test_unreadable_stat_is_none(tmp_path: Path) -> None:
    assert process_started(tmp_path / "missing") is None
    garbled = tmp_path / "stat"
    garbled.write_text("1 (python) R")
    assert process_started(garbled) is None
