"""Atomic writes: a failure leaves the old file and no partial file under the final name."""
from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import numpy as np
import pytest

from imaging.atomic_io import (TMP_PREFIX, atomic_path, current_umask, json_safe, write_json_atomic,
                               write_text_atomic)


def test_write_replaces_whole_file(tmp_path: Path) -> None:
    target = tmp_path / "a.json"
    write_text_atomic(target, "old")
    write_text_atomic(target, "new")
    assert target.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]


def test_failure_keeps_old_file_and_leaves_no_temp(tmp_path: Path) -> None:
    target = tmp_path / "a.json"
    write_text_atomic(target, "old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("disk full")
    assert target.read_text() == "old"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(TMP_PREFIX)]


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_finished_file_mode_follows_the_umask(tmp_path: Path, umask: int, mode: int) -> None:
    """Like a file created with open(): 0666 less the umask (mkstemp alone gives 0600)."""
    old = os.umask(umask)
    try:
        assert current_umask() == umask
        write_text_atomic(tmp_path / "a.json", "x")
        with atomic_path(tmp_path / "b.bin") as tmp:
            tmp.write_bytes(b"y")  # writers given the temporary path (EXR, PNG, checkpoints)
    finally:
        os.umask(old)
    for name in ("a.json", "b.bin"):
        assert stat.S_IMODE((tmp_path / name).stat().st_mode) == mode, name


def test_json_is_strict_and_safe(tmp_path: Path) -> None:
    """inf/NaN (PSNR of identical images) become null, numpy scalars plain numbers, tuples lists."""
    value = {"psnr": float("inf"), "x": [np.float32(0.5), (np.int64(3), float("nan"))], "ok": 1.5}
    assert json_safe(value) == {"psnr": None, "x": [0.5, [3, None]], "ok": 1.5}
    write_json_atomic(tmp_path / "m.json", value)
    assert json.loads((tmp_path / "m.json").read_text()) == json_safe(value)
    assert (tmp_path / "m.json").read_text().endswith("}\n")
