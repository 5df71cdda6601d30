"""The sweep's energy-error plot, drawn in a helper process started early.

Importing matplotlib and drawing come after the rollouts, on one core, in a short command-line
sweep's wall clock. :func:`start` launches a Python process that imports matplotlib (and
draws a first figure) while the command line is still setting up, then waits for the data on
its standard input; :func:`render` sends it the plot's data and receives the PNG. The helper
runs this file as a script: it imports nothing of this package, only NumPy and matplotlib.

Nothing depends on the helper: if it was not started, cannot start, fails or takes more
than :data:`TIMEOUT_S`, :func:`render` draws in this process instead (the same figure). A
helper that is never asked exits when this process does (end of its input).
"""

from __future__ import annotations

import io
import os
import pickle
import subprocess
import sys
from typing import Any

#: The longest :func:`render` waits for the helper before drawing in this process.
TIMEOUT_S = 60.0

_BOOT = "import runpy, sys; runpy.run_path(sys.argv[1], run_name='__main__')"
_helper: subprocess.Popen | None = None


def violin_png(payload: dict[str, Any]) -> bytes:
    """The PNG of a violin plot: ``payload`` has ``data`` (one 1-d array per violin),
    ``labels``, ``colors`` (matplotlib colours), ``ylabel``, ``title``, ``width`` and
    ``height`` (inches)."""
    # A Figure with the Agg canvas directly: pyplot (and choosing its backend) is slower
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(payload["width"], payload["height"]))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    parts = ax.violinplot(payload["data"], showmedians=True, showextrema=True)
    for body, color in zip(parts["bodies"], payload["colors"], strict=True):
        body.set_facecolor(color)
        body.set_alpha(0.5)
    labels = payload["labels"]
    ax.set_xticks(range(1, len(labels) + 1), labels, fontsize=8)
    ax.set_ylabel(payload["ylabel"])
    ax.set_title(payload["title"], fontsize=10)
    ax.grid(alpha=0.3)
    # fixed margins for a 2-line title and 3-line tick labels (tight_layout measures every
    # text box, slowly)
    fig.subplots_adjust(left=0.9 / fig.get_figwidth(), right=0.98, bottom=0.17, top=0.86)
    fh = io.BytesIO()  # in memory: the caller writes the file (atomically)
    fig.savefig(fh, format="png", dpi=120)
    return fh.getvalue()


def start() -> None:
    """Launch the helper (once per process); a failure to launch is ignored."""
    global _helper
    if _helper is not None:
        return
    try:
        _helper = subprocess.Popen([sys.executable, "-c", _BOOT, __file__],
                                   stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                   stderr=subprocess.DEVNULL)
    except OSError:
        _helper = None


def render(payload: dict[str, Any]) -> bytes:
    """:func:`violin_png` of ``payload``, by the helper if :func:`start` launched one."""
    global _helper
    helper, _helper = _helper, None
    if helper is not None:
        try:
            png, _ = helper.communicate(pickle.dumps(payload), timeout=TIMEOUT_S)
            if helper.returncode == 0 and png.startswith(b"\x89PNG"):
                return png
        except (OSError, ValueError, subprocess.SubprocessError):
            helper.kill()
            helper.wait()
    return violin_png(payload)


def _serve() -> None:
    import numpy as np

    # The head start: the imports, and a first figure drawn (fonts, text layout) while the
    # parent is still busy.
    violin_png({"data": [np.linspace(0.0, 1.0, 8)], "labels": ["a\nb"], "colors": ["C0"],
                "ylabel": "$x$", "title": "a\nb", "width": 6.0, "height": 4.2})
    data = sys.stdin.buffer.read()
    if not data:  # never asked: the parent is done
        return
    sys.stdout.buffer.write(violin_png(pickle.loads(data)))
    sys.stdout.buffer.flush()
    os._exit(0)  # the parent waits for the exit: skip the interpreter's teardown


if __name__ == "__main__":
    _serve()
