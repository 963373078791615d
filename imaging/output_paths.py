"""Where outputs may go: never onto an input or an earlier output, and in the format their name says.

An output path that is an input (the same path), a hard link to one (the same file under another
name) or a symbolic link to one would replace the file a person wanted to keep: :func:`check_not_inputs`
refuses it unless the command was told to overwrite. (Outputs are written to a temporary name and
renamed over the path, :mod:`imaging.atomic_io`: with ``--overwrite`` an output on a link replaces
the link, not the file it points to.) :func:`output_format` maps an image output's extension to
the format written, and refuses any other extension instead of writing one format under the name
of another. An output that exists is not replaced unless the command was told to overwrite:
:func:`check_new_file` for an output file, :func:`check_output_folder` for the files a command writes
into a folder (a folder holding none of them, or a new one, is used as it is; a path that is a file
where a folder is wanted is refused always).
"""
from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from imaging.errors import DenoiserError

IMAGE_OUTPUTS = {".exr": "exr", ".pfm": "pfm", ".hdr": "hdr", ".rgbe": "hdr", ".pic": "hdr", ".png": "png"}
OVERWRITE_HINT = "give --overwrite to replace it"


class OutputPathError(DenoiserError):
    """An output path that would replace an input, or names a format that is not written."""


def output_format(path: str | Path) -> str:
    """``exr``, ``pfm``, ``hdr`` or ``png`` from an image output's extension (case-insensitive);
    raises :class:`OutputPathError` for any other."""
    suffix = Path(path).suffix.lower()
    if suffix not in IMAGE_OUTPUTS:
        raise OutputPathError(f"{path}: cannot write {repr(suffix) if suffix else 'a file without an extension'}: "
                              "an output image's name must end in .exr, .pfm, .hdr (.rgbe, .pic) or .png")
    return IMAGE_OUTPUTS[suffix]


def check_new_file(path: str | Path, overwrite: bool = False, hint: str = OVERWRITE_HINT) -> None:
    """Raise :class:`OutputPathError` (one line naming ``path``) when the output file ``path``
    exists (a file, or a link, dangling or not), unless ``overwrite``; a folder there is refused always."""
    path = Path(path)
    if path.is_dir():
        raise OutputPathError(f"{path}: is a folder; an output file cannot replace it")
    if os.path.lexists(path) and not overwrite:
        raise OutputPathError(f"{path}: exists: refusing to replace it ({hint})")


def check_output_folder(out: str | Path, names: Iterable[str], overwrite: bool = False) -> None:
    """Raise :class:`OutputPathError` (one line) when ``out`` exists and is not a folder (always), or
    is a folder already holding one of the files ``names`` that the command writes (an earlier run's;
    a link counts), unless ``overwrite``. A folder that does not exist, or holds none of them, passes."""
    out = Path(out)
    if os.path.lexists(out) and not out.is_dir():
        raise OutputPathError(f"{out}: exists and is not a folder; choose another --out")
    if overwrite or not out.is_dir():
        return
    held = [name for name in names if os.path.lexists(out / name)]
    if held:
        shown = ", ".join(held[:3]) + (f" and {len(held) - 3} more" if len(held) > 3 else "")
        raise OutputPathError(f"{out}: holds an earlier run's files ({shown}): refusing to replace them "
                              "(give --overwrite to replace them, or choose another --out)")


def _same_file(output: Path, source: Path) -> str | None:
    """How ``output`` is ``source`` (``"is"``, ``"is a symbolic link to"``, ``"is a hard link to"``), or None."""
    try:
        if not os.path.samefile(output, source):
            return None
    except OSError:  # one of them does not exist (or cannot be looked at): compare the paths
        try:
            return "is" if output.resolve() == source.resolve() else None
        except (OSError, RuntimeError):  # a symbolic link loop (RuntimeError before Python 3.13)
            raise OutputPathError(f"{output}: a symbolic link loop, or a path that cannot be resolved") from None
    if output.absolute() == source.absolute():
        return "is"
    if output.is_symlink():
        return "is a symbolic link to"
    return "is" if output.resolve() == source.resolve() else "is a hard link to"


def check_not_inputs(outputs: Iterable[str | Path], inputs: Iterable[str | Path | None], overwrite: bool = False,
                     hint: str = OVERWRITE_HINT) -> None:
    """Raise :class:`OutputPathError` (one line naming both) when an output is an input, a hard
    link or a symbolic link to one (module notes); ``overwrite`` allows it. None inputs are skipped."""
    if overwrite:
        return
    sources = [Path(p) for p in inputs if p is not None]
    for output in map(Path, outputs):
        for source in sources:
            how = _same_file(output, source)
            if how is not None:
                raise OutputPathError(f"{output}: {how} the input {source}: refusing to overwrite it ({hint})")
