"""A dependency-free progress bar for long runs (sweeps, benchmarks).

Draws ``label [#####.....] done/total unit  rate unit/s  ETA m:ss`` on one terminal line,
redrawn at most every ``min_interval`` seconds. It is silent when the stream is not a
terminal (CI logs, pipes) or when ``enabled=False`` (e.g. ``--json``), so scripted output
stays clean.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO

__all__ = ["Progress", "format_duration"]


def format_duration(seconds: float) -> str:
    """``h:mm:ss`` or ``m:ss``; ``?`` for an unknown (non-finite) duration."""
    if seconds != seconds or seconds in (float("inf"), float("-inf")):
        return "?"
    seconds = max(0, round(seconds))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


class Progress:
    """Progress over ``total`` items. Call :meth:`advance` as items finish (``computed``
    items count towards the rate; skipped ones, e.g. resumed chunks, only towards the
    count) and :meth:`close` at the end."""

    def __init__(self, total: int, *, label: str = "", unit: str = "items",
                 stream: TextIO | None = None, enabled: bool = True,
                 min_interval: float = 0.2, width: int = 28):
        self.total = max(int(total), 0)
        self.label = label
        self.unit = unit
        self.stream = sys.stderr if stream is None else stream
        isatty = getattr(self.stream, "isatty", None)
        self.enabled = bool(enabled and isatty is not None and isatty())
        self.min_interval = min_interval
        self.width = width
        self.done = 0
        self.computed = 0
        self.start = time.perf_counter()
        self._last_draw = -float("inf")

    @property
    def rate(self) -> float:
        """Computed items per second so far."""
        elapsed = time.perf_counter() - self.start
        return self.computed / elapsed if elapsed > 0 and self.computed else 0.0

    def advance(self, n: int, *, computed: bool = True) -> None:
        self.done += n
        if computed:
            self.computed += n
        now = time.perf_counter()
        if now - self._last_draw >= self.min_interval or self.done >= self.total:
            self._draw()
            self._last_draw = now

    def line(self) -> str:
        frac = self.done / self.total if self.total else 1.0
        filled = round(frac * self.width)
        bar = "#" * filled + "." * (self.width - filled)
        rate = self.rate
        eta = (self.total - self.done) / rate if rate > 0 else float("nan")
        return (f"{self.label} [{bar}] {self.done}/{self.total} {self.unit}  "
                f"{rate:.3g} {self.unit}/s  ETA {format_duration(eta)}")

    def _draw(self) -> None:
        if self.enabled:
            self.stream.write("\r" + self.line() + "\x1b[K")
            self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self._draw()
            self.stream.write("\n")
            self.stream.flush()
