"""Plotting helpers (matplotlib, Agg backend, PNG output). pyplot, slow to import, is
imported on first use, so that importing the styles costs nothing."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt

__all__ = ["METHOD_STYLE", "envelope", "figure", "method_style", "save", "style_for",
           "window_bounds"]

#: One colour and line style per method name, shared by every figure.
METHOD_STYLE: dict[str, dict[str, Any]] = {
    "exact": {"color": "black", "linestyle": ":", "linewidth": 1.2},
    "rk4": {"color": "tab:red", "linestyle": "-"},
    "gl4": {"color": "tab:blue", "linestyle": "--"},
    "gl6": {"color": "tab:cyan", "linestyle": "--"},
    "galerkin4": {"color": "tab:green", "linestyle": "-."},
    "galerkin6": {"color": "tab:olive", "linestyle": "-."},
    "verlet": {"color": "tab:purple", "linestyle": "-"},
    "reference": {"color": "black", "linestyle": ":", "linewidth": 1.2},
    "lgvi": {"color": "tab:blue", "linestyle": "-"},
    "hamel": {"color": "tab:orange", "linestyle": "--"},
    "hamel-cayley": {"color": "tab:green", "linestyle": "-."},
    "hamel-exact": {"color": "tab:purple", "linestyle": ":"},
    "hamel-cayley-exact": {"color": "tab:brown", "linestyle": ":"},
}


def style_for(name: str) -> dict[str, Any]:
    """Line style for a method (a neutral default for unknown names)."""
    return dict(METHOD_STYLE.get(name, {"color": "tab:gray"}))


def figure(nrows: int = 1, ncols: int = 1, *, width: float = 7.0, height: float = 3.6, **kw):
    """A figure with a consistent size; returns ``(fig, axes)``."""
    fig, axes = _pyplot().subplots(nrows, ncols, figsize=(width, height * nrows), **kw)
    return fig, axes


def save(fig, path: Path | str) -> Path:
    """Save ``fig`` (150 dpi, tight; the format from the suffix, PNG by default) through the
    atomic writer, and close it."""
    from ._io import atomic_write

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fmt = path.suffix[1:].lower() or "png"
    atomic_write(path, lambda fh: fig.savefig(fh, format=fmt, dpi=150))
    _pyplot().close(fig)
    return path


def window_bounds(n: int, windows: int) -> np.ndarray:
    """Start indices of ``min(windows, n)`` consecutive windows over ``n`` samples, and ``n``
    at the end: window ``k`` holds samples ``bounds[k]:bounds[k + 1]``. Every sample is in
    exactly one window and the window sizes differ by at most one (as ``numpy.array_split``)."""
    if n < 1 or windows < 1:
        raise ValueError(f"window_bounds: need n >= 1 and windows >= 1, got {n}, {windows}")
    k = min(int(windows), int(n))
    return (np.arange(k + 1) * n) // k


def envelope(t: Any, y: Any, windows: int = 400, *, min_span: float | None = None,
             absolute: bool = True, lower: bool = False) -> tuple[np.ndarray, ...]:
    """The envelope of a long sampled signal: its largest value over each of ``windows``
    consecutive windows of samples (:func:`window_bounds`: every sample in exactly one
    window), so that ``10⁵``–``10⁶`` saved points are drawn as one curve of running maxima
    whose level shows at a glance whether an error stays bounded or drifts.

    ``min_span``: fewer windows if needed, so that each spans at least about ``min_span``
    of ``t``; make it longer than the signal's oscillation period, so that a window's
    maximum is the envelope's level and not wherever the oscillation happens to be.

    Returns ``(t_window, upper)``, or ``(t_window, upper, low)`` with ``lower=True``:
    ``t_window`` the middle of each window's time span, ``upper`` the maximum and ``low``
    the minimum over the window of ``|y|`` (``absolute=True``, for errors on a log axis) or
    of ``y``. With ``windows >= len(y)`` each sample is its own window (the signal itself).
    A NaN in a window makes its maximum and minimum NaN (a failed run is not hidden)."""
    t = np.asarray(t, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if t.ndim != 1 or y.shape != t.shape:
        raise ValueError(f"envelope: t and y must be 1D of the same length, got shapes "
                         f"{t.shape} and {y.shape}")
    values = np.abs(y) if absolute else y
    if min_span is not None and len(t) > 1:
        windows = max(1, min(windows, int((t[-1] - t[0]) // min_span)))
    starts = window_bounds(len(y), windows)
    first, last = starts[:-1], starts[1:] - 1
    t_window = 0.5 * (t[first] + t[last])
    upper = np.maximum.reduceat(values, first)
    if not lower:
        return t_window, upper
    return t_window, upper, np.minimum.reduceat(values, first)


def positive(values: Any, floor: float = 1e-17) -> np.ndarray:
    """``|values|`` clipped below at ``floor``, for log-scale axes (exact zeros would vanish)."""
    return np.maximum(np.abs(np.asarray(values, dtype=np.float64)), floor)


#: One colour per method in these charts (the shared METHOD_STYLE gives lgvi and gl4 the same
#: colour); compositions ``base@k`` are dotted, coloured by their order.
COLOURS = {"lgvi": "tab:blue", "hamel": "tab:orange", "hamel-cayley": "tab:green",
           "hamel-exact": "tab:purple", "hamel-cayley-exact": "tab:brown", "rk4": "tab:red",
           "gl4": "tab:cyan", "gl6": "navy", "rkmk4": "tab:gray", "verlet": "tab:purple",
           "galerkin4": "yellowgreen", "galerkin6": "tab:olive"}
COMPOSED_COLOURS = {"4": "tab:pink", "6": "darkgoldenrod", "8": "teal"}


def method_style(name: str) -> dict:
    """Colour and line style of one of our methods in these charts."""
    base, _, order = name.partition("@")
    style = style_for(base)
    style.pop("linewidth", None)
    if order:
        style.update(color=COMPOSED_COLOURS.get(order, "tab:gray"), linestyle=":")
    elif base in COLOURS:
        style["color"] = COLOURS[base]
    return style
