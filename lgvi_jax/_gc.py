"""Python's cyclic garbage collector paused while the package traces a rollout.

Tracing a rollout builds many short-lived Python objects (tracers, jaxpr equations, the
scalar programs of :mod:`lgvi_jax.scalarize`). Their allocation keeps triggering the
collector, and each full collection walks every object of the process, most of them
JAX's own modules: a sizeable share of a batch's tracing time. No cycle created while
tracing outlives the trace by more than a collection, so the collector can wait until the
trace is done (``docs/engine.md``, compile time).

:func:`paused` is reentrant and safe to use from several threads: the collector is
disabled while any pause is active and re-enabled when the last one ends, unless it was
already disabled when the first began (the caller's setting is kept).
"""

from __future__ import annotations

import contextlib
import gc
import threading
from collections.abc import Iterator

__all__ = ["paused"]

_lock = threading.Lock()
_depth = 0
_restore = False


@contextlib.contextmanager
def paused() -> Iterator[None]:
    """Disable the cyclic garbage collector for the block (module docstring)."""
    global _depth, _restore
    with _lock:
        if _depth == 0:
            _restore = gc.isenabled()
            gc.disable()
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0 and _restore:
                gc.enable()
