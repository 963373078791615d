"""Crash-safe file writing: write to a temporary file beside the target, then rename.

A reader never sees a half-written file under the final name: after a crash (kill -9, full disk)
there is either the complete old file, the complete new file, or a leftover ``.tmp-*`` file that
no reader treats as finished. The finished file gets the permissions of a file created with
``open()``: 0666 less the process's umask (0644 under the usual umask 022), not ``mkstemp``'s 0600.
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

TMP_PREFIX = ".tmp-"
CREATE_MODE = 0o666  # what open() asks for; the umask takes its bits away


def current_umask() -> int:
    """The process's umask, read from /proc without changing it (other threads may be creating
    files); where /proc does not say, set and restore it."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder; on success fsync and rename it to ``path``.

    On any exception the temporary file is removed and ``path`` is left untouched.
    An ``OSError`` (full disk, no permission...) is re-raised naming ``path``, not the temporary.
    """
    path = Path(path)
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=TMP_PREFIX, suffix=path.suffix, dir=path.parent)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        os.chmod(tmp, CREATE_MODE & ~current_umask())
        yield tmp
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            tmp.unlink()
        if isinstance(exc, OSError):
            raise OSError(exc.errno, exc.strerror or str(exc), str(path)) from None
        raise


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    write_bytes_atomic(path, text.encode("utf-8"))


def json_safe(value: Any) -> Any:
    """``value`` ready for strict JSON: non-finite floats -> None (JSON has no inf or NaN: identical
    images have PSNR null, meaning infinite), numpy scalars -> Python numbers, tuples -> lists,
    containers converted recursively."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


def write_json_atomic(path: str | Path, value: Any, indent: int | None = 1) -> None:
    """Write :func:`json_safe` ``value`` to ``path`` atomically as strict JSON plus a newline."""
    write_text_atomic(path, json.dumps(json_safe(value), indent=indent, allow_nan=False) + "\n")
