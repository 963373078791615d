"""The integrator of every generated scene: unidirectional ``path`` with a random depth."""
from __future__ import annotations

from typing import Any

import numpy as np


def path(rng: np.random.Generator, min_depth: int = 3, max_depth: int = 12) -> dict[str, Any]:
    """A ``path`` integrator whose ``max_depth`` is uniform in [min_depth, max_depth]."""
    if not 1 <= min_depth <= max_depth:
        raise ValueError(f"need 1 <= min_depth <= max_depth, got {min_depth}, {max_depth}")
    return {"type": "path", "max_depth": int(rng.integers(min_depth, max_depth + 1))}
