"""Plotting helpers (matplotlib, Agg backend, PNG output). pyplot is imported on first use
(~0.5 s), so that importing the styles costs nothing."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt

__all__ = ["METHOD_STYLE", "figure", "method_style", "save", "style_for"]

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


def positive(values: Any, floor: float = 1e-17) -> np.ndarray:
    """``|values|`` clipped below at ``floor``, for log-scale axes (exact zeros would vanish)."""
    return np.maximum(np.abs(np.asarray(values, dtype=np.float64)), floor)


#: One colour per method in these charts (the shared METHOD_STYLE gives lgvi and gl4 the same
#: colour); compositions ``base@k`` are dotted, coloured by their order.
COLOURS = {"lgvi": "tab:blue", "hamel": "tab:orange", "hamel-cayley": "tab:green",
           "hamel-exact": "tab:purple", "hamel-cayley-exact": "tab:brown", "rk4": "tab:red",
           "gl4": "tab:cyan", "gl6": "navy", "rkmk4": "tab:gray", "verlet": "tab:purple",
           "galerkin4": "tab:green", "galerkin6": "tab:olive"}
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
