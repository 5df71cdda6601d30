"""Progress bars for long runs (sweeps, fits), drawn by `tqdm <https://tqdm.github.io>`_.

Draws ``label [#####.....] done/total unit  rate unit/s  ETA m:ss`` on one terminal line
(stderr by default), redrawn at most every ``min_interval`` seconds. It is silent when the
stream is not a terminal (CI logs, pipes) or when ``enabled=False`` (e.g. ``--json``), so
scripted output stays clean.
"""

from __future__ import annotations

import math
import sys
import time
from typing import TextIO

from tqdm import tqdm

__all__ = ["Progress", "format_duration"]

_BAR_FORMAT = "{desc} [{bar:%d}] {n_fmt}/{total_fmt} {unit}  {rate_fmt}  ETA {remaining}"


def format_duration(seconds: float) -> str:
    """``h:mm:ss`` or ``mm:ss`` (tqdm's format); ``?`` for an unknown (non-finite)
    duration."""
    if not math.isfinite(seconds):
        return "?"
    return tqdm.format_interval(max(0, round(seconds)))


class _Bar(tqdm):
    # No monitor thread: the bar is redrawn from the caller's thread only (a sweep's
    # workers and the distributed heartbeat are left alone).
    monitor_interval = 0


class Progress:
    """Progress over ``total`` items. Call :meth:`advance` as items finish (``computed``
    items count towards the rate; skipped ones, e.g. resumed chunks, only towards the
    count) and :meth:`close` at the end. ``label`` and ``total`` may be changed between
    calls (the next redraw shows them)."""

    def __init__(self, total: int, *, label: str = "", unit: str = "items",
                 stream: TextIO | None = None, enabled: bool = True,
                 min_interval: float = 0.2, width: int = 28):
        self.stream = sys.stderr if stream is None else stream
        isatty = getattr(self.stream, "isatty", None)
        self.enabled = bool(enabled and isatty is not None and isatty())
        self.unit = unit
        self.width = width
        self.done = 0
        self.computed = 0
        self.start = time.perf_counter()
        # smoothing=0: the rate is (n - initial) / elapsed, i.e. computed items per second
        # (skipped items raise ``initial`` with ``n``, see advance).
        self._bar = _Bar(total=max(int(total), 0), desc=label, unit=unit, file=self.stream,
                         disable=not self.enabled, mininterval=min_interval, miniters=1,
                         smoothing=0, ascii=".#", bar_format=_BAR_FORMAT % width, leave=True)
        if self.enabled:
            # A terminal that reports no size (e.g. a bare pty): tqdm would truncate the
            # line to nothing and hide the bar; draw it whole instead.
            if self._bar.ncols is not None and self._bar.ncols <= 0:
                self._bar.ncols = None
            if self._bar.nrows is not None and self._bar.nrows <= 0:
                self._bar.nrows = None
        self._label = label

    @property
    def label(self) -> str:
        return self._label

    @label.setter
    def label(self, value: str) -> None:
        self._label = value
        if self.enabled:
            self._bar.set_description_str(value, refresh=False)

    @property
    def total(self) -> int:
        return self._bar.total

    @total.setter
    def total(self, value: int) -> None:
        self._bar.total = max(int(value), 0)

    @property
    def rate(self) -> float:
        """Computed items per second so far."""
        elapsed = time.perf_counter() - self.start
        return self.computed / elapsed if elapsed > 0 and self.computed else 0.0

    def advance(self, n: int, *, computed: bool = True) -> None:
        self.done += n
        if computed:
            self.computed += n
        elif self.enabled:
            self._bar.initial += n  # counted, not in the rate
        if self.enabled:
            self._bar.update(n)

    def line(self) -> str:
        """The bar's text as drawn now."""
        return tqdm.format_meter(
            n=self.done, total=self.total, elapsed=time.perf_counter() - self.start,
            prefix=self.label, unit=self.unit, initial=self.done - self.computed,
            ascii=".#", bar_format=_BAR_FORMAT % self.width)

    def close(self) -> None:
        """Draw the final state and end the line (nothing when disabled)."""
        self._bar.close()
