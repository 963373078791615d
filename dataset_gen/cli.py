"""Command-line entry point `generate-dataset`."""
from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    """Not yet available: exits with a clear message until issue #3 lands."""
    print("generate-dataset: not implemented yet (issue #3)", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
