"""What every command shares on its command line: one parser whose usage errors are one line
(exit code 2), the same one-line report of any other error (exit code 1) or of Ctrl-C (130), and the
argument types the commands have in common."""
from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from typing import Any, NoReturn, TypeVar

from imaging.errors import DenoiserError

T = TypeVar("T")
# what a command reports as one line (exit 1); MemoryError: an allocation no check foresaw
COMMAND_ERRORS = (DenoiserError, OSError, ValueError, MemoryError)
USAGE_EXIT = 2
ERROR_EXIT = 1
INTERRUPTED_EXIT = 130


def error_line(exc: BaseException) -> str:
    """One line for an exception: an OSError as ``REASON: FILE``, a MemoryError as ``out of memory:
    MESSAGE``, anything else as the first line of its message (its type's name when it has none)."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.strerror}: {exc.filename}" if exc.filename else exc.strerror
    lines = [line for line in str(exc).strip().splitlines() if line.strip()]
    if isinstance(exc, MemoryError):
        return f"out of memory: {lines[0].strip() if lines else 'an allocation failed'}"
    return lines[0].strip() if lines else type(exc).__name__


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line on stderr (exit 2), without the usage text:
    ``PROG: error: MESSAGE (see --help)``; :meth:`fail` reports any other error the same way."""

    def error(self, message: str) -> NoReturn:
        first = message.strip().splitlines()[0] if message.strip() else "invalid arguments"
        print(f"{self.prog}: error: {first} (see --help)", file=sys.stderr)
        raise SystemExit(USAGE_EXIT)

    def fail(self, exc: BaseException, context: str = "") -> int:
        """Print ``PROG: error: CONTEXTMESSAGE`` (:func:`error_line`) on stderr; return exit code 1."""
        print(f"{self.prog}: error: {context}{error_line(exc)}", file=sys.stderr)
        return ERROR_EXIT

    def interrupted(self, note: str = "") -> int:
        """Print ``PROG: interrupted`` and ``note`` (what to run next) on stderr; return 130."""
        print(f"{self.prog}: interrupted{note}", file=sys.stderr)
        return INTERRUPTED_EXIT

    def attempt(self, action: Callable[[], T], errors: tuple[type[BaseException], ...] = COMMAND_ERRORS
                ) -> tuple[T | None, int]:
        """Run a command's library call: ``(result, 0)``; on one of ``errors`` ``(None, 1)`` after
        :meth:`fail`, on Ctrl-C ``(None, 130)`` after :meth:`interrupted`."""
        try:
            return action(), 0
        except errors as exc:
            return None, self.fail(exc)
        except KeyboardInterrupt:
            return None, self.interrupted()


def _positive(text: str, convert: Callable[[str], Any], what: str) -> Any:
    try:
        value = convert(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive {what}, got {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected a positive {what}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    """Argument type: an integer >= 1."""
    return _positive(text, int, "integer")


def positive_float(text: str) -> float:
    """Argument type: a finite number > 0."""
    return _positive(text, float, "number")


def int_list(text: str) -> tuple[int, ...]:
    """Argument type: comma-separated positive integers (at least one), e.g. ``4,16,128``."""
    try:
        values = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or min(values) < 1:
        raise argparse.ArgumentTypeError(f"expected positive integers, got {text!r}")
    return values


def name_list(text: str) -> tuple[str, ...]:
    """Argument type: comma-separated names, empty ones dropped (``a,b`` -> ("a", "b"))."""
    return tuple(name for name in text.split(",") if name)


def name_value(text: str) -> tuple[str, str]:
    """Argument type: ``NAME=VALUE`` (the value may be empty or hold '=')."""
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise argparse.ArgumentTypeError(f"expected name=value, got {text!r}")
    return name, value


def size_list(text: str) -> list[tuple[int, int]]:
    """Argument type: comma-separated image sizes WxH (at least one), e.g. ``1920x1080,3840x2160``."""
    sizes = []
    for item in (v.strip() for v in text.split(",") if v.strip()):
        try:
            w, h = (int(v) for v in item.lower().split("x"))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated sizes WxH, got {text!r}") from None
        if min(w, h) < 1:
            raise argparse.ArgumentTypeError(f"expected positive sizes WxH, got {text!r}")
        sizes.append((w, h))
    if not sizes:
        raise argparse.ArgumentTypeError(f"expected comma-separated sizes WxH, got {text!r}")
    return sizes
