"""The one progress-bar protocol: what a long loop (training, dataset generation, tradeoff) may
call on the bar it is given — the part of ``tqdm`` they use. Library code draws progress only
through such an object; the commands make them with :func:`tqdm_bars`."""
from __future__ import annotations

from typing import Any, Protocol


class ProgressBar(Protocol):
    """A progress bar: ``tqdm`` or anything with these methods."""

    def update(self, n: int = 1) -> Any: ...
    def set_description(self, desc: str | None = None, refresh: bool = True) -> Any: ...
    def set_postfix_str(self, s: str = "", refresh: bool = True) -> Any: ...
    def write(self, s: str) -> Any: ...
    def close(self) -> Any: ...


class ProgressFactory(Protocol):
    """Makes the bar of one loop: ``total`` steps, ``initial`` of them already done (a resume)."""

    def __call__(self, total: int, initial: int = 0) -> ProgressBar: ...


def tqdm_bars(unit: str, enabled: bool = True) -> ProgressFactory:
    """A :class:`ProgressFactory` of ``tqdm`` bars on stderr counting ``unit``; ``enabled=False``
    (``--quiet``, ``--no-progress``) draws nothing."""
    def bar(total: int, initial: int = 0) -> ProgressBar:
        import sys

        from tqdm import tqdm

        return tqdm(total=total, initial=initial, unit=unit, dynamic_ncols=True, disable=not enabled,
                    file=sys.stderr)

    return bar
