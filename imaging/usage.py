"""Argument parsing shared by every command: usage errors are one line on stderr, exit code 2."""
from __future__ import annotations

import argparse
import sys
from typing import NoReturn

USAGE_EXIT = 2


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one line on stderr (exit 2), without the usage text:
    ``PROG: error: MESSAGE (see --help)``."""

    def error(self, message: str) -> NoReturn:
        first = message.strip().splitlines()[0] if message.strip() else "invalid arguments"
        print(f"{self.prog}: error: {first} (see --help)", file=sys.stderr)
        raise SystemExit(USAGE_EXIT)
