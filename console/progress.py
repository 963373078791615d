"""The one progress-bar protocol: what a long loop (training, dataset generation, tradeoff) may
call on the bar it is given — the part of ``tqdm`` they use. Library code draws progress only
through such an object; the commands make them with :func:`tqdm_bars`."""
from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any, Protocol


class ProgressBar(Protocol):
    """A progress bar: ``tqdm`` or anything with these methods. ``total`` is the count it runs to; a
    loop may revise it (then calls :meth:`refresh`): training under a time limit does."""

    total: Any

    def update(self, n: int = 1) -> Any: ...
    def refresh(self) -> Any: ...
    def set_description(self, desc: str | None = None, refresh: bool = True) -> Any: ...
    def set_postfix_str(self, s: str = "", refresh: bool = True) -> Any: ...
    def write(self, s: str) -> Any: ...
    def close(self) -> Any: ...


class ProgressFactory(Protocol):
    """Makes the bar of one loop: ``total`` steps, ``initial`` of them already done (a resume)."""

    def __call__(self, total: int, initial: int = 0) -> ProgressBar: ...


def tqdm_bars(unit: str, enabled: bool = True, scale: bool = False) -> ProgressFactory:
    """A :class:`ProgressFactory` of ``tqdm`` bars on stderr counting ``unit``; ``enabled=False``
    (``--quiet``, ``--no-progress``, ``--json``) draws nothing; ``scale``: counts with SI prefixes
    (``12.3M/256M``)."""
    def bar(total: int, initial: int = 0) -> ProgressBar:
        from tqdm import tqdm

        return tqdm(total=total, initial=initial, unit=unit, unit_scale=scale, dynamic_ncols=True,
                    disable=not enabled, file=sys.stderr)

    return bar


def counted(bars: ProgressFactory | None, description: str) -> Callable[[int, int], None] | None:
    """A ``(done, total)`` callback (a render's progress, :func:`rendering.render.render_loaded`)
    that draws one bar of ``bars`` described as ``description``: opened at the first call, moved
    to ``done``, closed when ``done`` reaches ``total``. None without ``bars``."""
    if bars is None:
        return None
    state: dict[str, Any] = {"bar": None, "done": 0}

    def advance(done: int, total: int) -> None:
        if state["bar"] is None:
            state["bar"] = bars(total)
            state["bar"].set_description(description)
        state["bar"].update(done - state["done"])
        state["done"] = done
        if done >= total:
            state["bar"].close()

    return advance


def console_lines(prefix: str) -> Callable[[str], None]:
    """A writer of one line each on stdout, starting with ``prefix``, that does not tear a bar
    being drawn on stderr (``tqdm.write`` clears the bar, writes, and draws it again)."""
    def write(line: str) -> None:
        from tqdm import tqdm

        tqdm.write(f"{prefix}{line}", file=sys.stdout)
        sys.stdout.flush()

    return write
