"""Command-line entry point `render-and-denoise`."""
from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    """Not yet available: exits with a clear message until issue #5 lands."""
    print("render-and-denoise: not implemented yet (issue #5)", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
