"""JAX's persistent compilation cache for the command line.

A CLI run compiles the same programs as the last run with the same options (a sweep's
batched rollout, its initial conditions, the rollouts of ``simulate``), and compiling is
most of a short run's wall clock (a 1024-trajectory car-pendulum sweep: ~6.6 s of XLA
compilation in a 13.6 s run). :func:`enable` points JAX's persistent cache at a folder, so
that a repeated run loads the compiled programs instead. Only the command line calls it:
``import lgvi_jax`` leaves the process's cache settings alone.

Folder: ``$LGVI_JAX_CACHE_DIR`` if set (``off``, ``0`` or empty: no cache), else
``$XDG_CACHE_HOME/lgvi_jax/xla`` (``~/.cache/lgvi_jax/xla``). Shared between concurrent
processes safely: with a size limit JAX reads and writes entries under a file lock
(``filelock``); the limit, 2 GiB, evicts the least recently used programs. A folder that
cannot be created leaves the cache off (the run is only slower). The key of an entry covers
the program, the JAX/XLA versions and the ``XLA_FLAGS``, so a changed setting recompiles.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["cache_dir", "enable"]

#: Environment variable naming the cache folder (``off`` to disable).
ENV = "LGVI_JAX_CACHE_DIR"
#: Size limit of the folder, bytes (least recently used entries are evicted beyond it).
MAX_SIZE = 2 * 1024**3
#: Programs that compile faster than this are not stored (their entry would cost more to
#: read and write than to recompile).
MIN_COMPILE_S = 0.2


def cache_dir() -> Path | None:
    """The cache folder the command line uses, or ``None`` when disabled."""
    value = os.environ.get(ENV)
    if value is not None:
        if value.strip().lower() in ("", "0", "off", "none", "false"):
            return None
        return Path(value).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "lgvi_jax" / "xla"


def enable() -> Path | None:
    """Turn JAX's persistent compilation cache on in :func:`cache_dir`; returns the folder,
    or ``None`` if disabled or the folder cannot be created."""
    path = cache_dir()
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK | os.X_OK):
            return None
        import filelock  # noqa: F401  (JAX needs it for the locked, size-limited cache)
    except (OSError, ImportError):
        return None
    import jax

    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_compilation_cache_max_size", MAX_SIZE)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_S)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path
