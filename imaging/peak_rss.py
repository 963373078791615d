"""Peak resident memory of a block of code (render-and-denoise's metrics.json, benchmarks).

:class:`PeakRSS` reads this process's resident set size from ``/proc/self`` (Linux). The peak of
the block is exact whenever the block raised the kernel's high-water mark (``VmHWM``): that mark
is then the block's own peak. Otherwise the process had been larger before, and the peak is the
largest of the samples a background thread takes every ``interval_s`` (a spike shorter than that
can be missed). The high-water mark is never reset: ``time -v`` or a parent's ``ru_maxrss`` still
see the whole process's peak. Elsewhere than Linux the figures are None.
"""
from __future__ import annotations

import threading
from pathlib import Path
from types import TracebackType

from imaging.memory_limit import kb_field

_STATUS = Path("/proc/self/status")
MB = 2**20


def _status_bytes(key: str) -> int | None:
    """A ``/proc/self/status`` field given in kB (``VmRSS``, ``VmHWM``), in bytes; None if unreadable."""
    return kb_field(_STATUS, key)


def current_rss() -> int | None:
    """This process's resident set size in bytes (None where ``/proc`` is missing)."""
    return _status_bytes("VmRSS")


class PeakRSS:
    """``with PeakRSS() as m: ...`` -> ``m.start``, ``m.peak`` (bytes) and ``m.exact``.

    ``start`` is the RSS on entry, ``peak`` the largest RSS while the block ran (None off Linux);
    ``exact`` says the peak is the kernel's high-water mark rather than the largest sample.
    """

    def __init__(self, interval_s: float = 0.002) -> None:
        self.interval_s = interval_s
        self.start: int | None = None
        self.peak: int | None = None
        self.exact = False
        self._hwm: int | None = None
        self._sampled = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def _sample(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._sampled = max(self._sampled, current_rss() or 0)

    def __enter__(self) -> PeakRSS:
        self.start = current_rss()
        self._hwm = _status_bytes("VmHWM")
        if self.start is not None:
            self._sampled = self.start
            self._thread = threading.Thread(target=self._sample, name="peak-rss", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        sampled = max(self._sampled, current_rss() or 0)
        hwm = _status_bytes("VmHWM")
        self.exact = hwm is not None and self._hwm is not None and hwm > self._hwm
        self.peak = hwm if self.exact else sampled

    def to_dict(self) -> dict[str, float | bool | None]:
        """``{"start_mb", "peak_mb", "over_start_mb", "exact"}`` in MiB (None where unmeasured)."""
        if self.start is None or self.peak is None:
            return {"start_mb": None, "peak_mb": None, "over_start_mb": None, "exact": False}
        return {"start_mb": self.start / MB, "peak_mb": self.peak / MB,
                "over_start_mb": (self.peak - self.start) / MB, "exact": self.exact}
