"""Command-line entry point `train`."""
from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    """Not yet available: exits with a clear message until issue #4 lands."""
    print("train: not implemented yet (issue #4)", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
