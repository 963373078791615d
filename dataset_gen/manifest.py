"""The dataset manifest: DIR/manifest.jsonl, one JSON object per *finished* scene.

A line is appended (and fsynced) only after every file of its scene is complete, so a scene listed
here is whole. A crash can leave at most a partial last line, which readers ignore and
:func:`repair` removes before new lines are appended.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from imaging.atomic_io import write_text_atomic
from imaging.json_read import parse_json

MANIFEST_NAME = "manifest.jsonl"


def read_records(folder: Path) -> list[dict[str, Any]]:
    """All complete records, in order; a torn last line (crash mid-append) is skipped."""
    path = folder / MANIFEST_NAME
    if not path.exists():
        return []
    records = []
    for line in path.read_text(encoding="utf-8", errors="replace").splitlines(keepends=True):
        if not line.endswith("\n"):
            break
        try:
            record = parse_json(line)
        except json.JSONDecodeError:
            continue
        if isinstance(record, dict) and isinstance(record.get("index"), int):
            records.append(record)
    return records


def repair(folder: Path) -> None:
    """Drop a torn last line so that the next append starts on a line of its own."""
    path = folder / MANIFEST_NAME
    if not path.exists():
        return
    text = path.read_text(encoding="utf-8", errors="replace")
    if text and not text.endswith("\n"):
        write_text_atomic(path, text[: text.rfind("\n") + 1])


def append_record(folder: Path, record: dict[str, Any]) -> None:
    """Append one record as a line and fsync it."""
    line = json.dumps(record, sort_keys=True) + "\n"
    path = folder / MANIFEST_NAME
    try:
        with open(path, "a", encoding="utf-8") as fh:
            fh.write(line)
            fh.flush()
            os.fsync(fh.fileno())
    except OSError as exc:  # full disk: a torn line at most, dropped by repair() on the next run
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
