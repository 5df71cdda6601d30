"""JAX's persistent compilation cache for the command line.

A CLI run compiles the same programs as the last run with the same options (a sweep's
batched rollout, its initial conditions, the rollouts of ``simulate``), and compiling is
most of a short run's wall clock. :func:`enable` points JAX's persistent cache at a folder, so
that a repeated run loads the compiled programs instead. Only the command line calls it:
``import lgvi_jax`` leaves the process's cache settings alone.

Folder: ``$LGVI_JAX_CACHE_DIR`` if set (``off``, ``0`` or empty: no cache), else
``$XDG_CACHE_HOME/lgvi_jax/xla`` (``~/.cache/lgvi_jax/xla``). Shared between concurrent
processes safely: with a size limit JAX reads and writes entries under a file lock
(``filelock``); the limit, 2 GiB, evicts the least recently used programs. A folder that
cannot be created leaves the cache off (the run is only slower). The key of an entry covers
the program, the JAX/XLA versions and the ``XLA_FLAGS``, so a changed setting recompiles.

JAX's cache starts from the lowered program, so a run still pays for tracing the Python
that builds it (seconds for a sweep's batched rollout). :func:`call` also keeps the **traced**
programs (the sweep's rollout and initial conditions, the fit's derivatives) as
:mod:`jax.export` serialisations in the ``traces`` subfolder, keyed by everything a trace
depends on: the package's source, the versions of JAX, jaxlib, Equinox and NumPy, the
static part of the arguments and the shapes, dtypes and devices of the dynamic part. A
repeated run deserialises the program (milliseconds) instead of tracing it again.
:func:`prepare` does the loading (or tracing and compiling) ahead, from the shapes of
inputs not computed yet, in a thread: the sweep prepares its rollout while it computes the
initial conditions.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

__all__ = ["cache_dir", "call", "enable", "prepare", "program"]

#: Environment variable naming the cache folder (``off`` to disable).
ENV = "LGVI_JAX_CACHE_DIR"
#: Size limit of the folder, bytes (least recently used entries are evicted beyond it).
MAX_SIZE = 2 * 1024**3
#: Programs that compile faster than this are not stored (their entry would cost more to
#: read and write than to recompile). 0.05 s: a model's initial momenta, compiled once per
#: run in ~0.1 s, are loaded by a repeated run; the test suite, whose workers share a
#: cache, is no slower for it (at 0 it was: CHANGELOG).
MIN_COMPILE_S = 0.05
#: Size limit of the traced programs (``traces`` subfolder), bytes; the least recently
#: written are removed beyond it.
MAX_TRACES_SIZE = 256 * 1024**2

_traces: Path | None = None  # set by enable(); None: call() runs the function as it is
_loaded: dict[tuple, Callable] = {}  # (key, compiler options) -> the compiled program


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
    global _traces
    _traces = path / "traces"
    return path


@functools.cache
def _source_digest() -> str:
    """A digest of the package's source files (a traced program depends on all of them)."""
    h = hashlib.sha256()
    root = Path(__file__).parent
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


@functools.cache
def _versions() -> tuple[str, ...]:
    """Versions of the libraries a trace goes through."""
    import equinox
    import jax
    import jaxlib
    import numpy

    return (jax.__version__, jaxlib.__version__, equinox.__version__, numpy.__version__)


_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def _key(name: str, static: Any, leaves: Sequence) -> str | None:
    """The traced program's key, or ``None`` when the static part has no faithful text
    (an object printed by its address: a function, a custom object)."""
    import jax

    s_leaves, s_def = jax.tree.flatten(static)
    text = repr((str(s_def), s_leaves))
    if _ADDRESS.search(text):
        return None
    avals = [(tuple(x.shape), str(x.dtype), str(getattr(x, "sharding", None)))
             for x in leaves]
    parts = (name, _source_digest(), _versions(), jax.default_backend(),
             bool(jax.config.jax_enable_x64), text, repr(avals))
    return hashlib.sha256(repr(parts).encode()).hexdigest()[:40]


def _prune(folder: Path) -> None:
    try:
        files = sorted(folder.glob("*.jaxexport"), key=lambda f: f.stat().st_mtime)
        total = sum(f.stat().st_size for f in files)
        for f in files:
            if total <= MAX_TRACES_SIZE:
                break
            total -= f.stat().st_size
            f.unlink(missing_ok=True)
    except OSError:
        pass


def call(name: str, fn: Callable, *args: Any, compiler_options: dict | None = None) -> Any:
    """``fn(*args)`` through the traced-program cache when :func:`enable` turned it on.

    ``fn`` is a JAX-traceable function of pytrees; their array leaves are the program's
    inputs, everything else (numbers, strings, the structure) is static and part of the key
    with ``name`` (which program). On a miss the program is traced once with
    :func:`jax.export.export`, stored (atomically, so concurrent runs share the folder) and
    run from that export; on a hit it is deserialised. The result equals ``fn(*args)``: it
    is the same program. Without the cache, or for a static part that cannot be keyed, it is
    ``fn(*args)``. ``compiler_options``: XLA's, for compiling the loaded program (pass the
    ones ``fn``'s own ``jit`` uses, so that both compile alike)."""
    return program(name, fn, *args, compiler_options=compiler_options)(*args)


def program(name: str, fn: Callable, *args: Any,
            compiler_options: dict | None = None) -> Callable:
    """What :func:`call` runs for arguments shaped like ``args``, loaded (or traced and
    stored) now and compiled with ``compiler_options``: a function of arguments with the
    same static part (without the cache, ``fn`` itself, jitted with ``compiler_options``
    if there are any), which several threads may then call."""
    if _traces is None:
        return _uncached(fn, compiler_options)
    import equinox as eqx
    import jax

    if jax.process_count() > 1:  # a multi-process program: traced by every process
        return _uncached(fn, compiler_options)

    dynamic, static = eqx.partition(args, eqx.is_array)
    leaves, treedef = jax.tree.flatten(dynamic)
    key = _key(name, static, leaves)
    if key is None:
        return _uncached(fn, compiler_options)
    run = _load(key, fn, static, leaves, treedef, compiler_options)

    def loaded(*args):
        return run(*jax.tree.leaves(eqx.filter(args, eqx.is_array)))

    return loaded


_UNCACHED: dict = {}  # (fn, compiler options) -> fn jitted with them


def _uncached(fn: Callable, compiler_options: dict | None) -> Callable:
    """``fn`` as :func:`program` runs it without the cache: as it is, or (with
    ``compiler_options``, which only a top-level ``jit`` takes) jitted with them, once per
    function and options."""
    if not compiler_options:
        return fn
    import equinox as eqx

    key = (fn, _options(compiler_options))
    if key not in _UNCACHED:
        _UNCACHED[key] = eqx.filter_jit(fn, compiler_options=dict(compiler_options))
    return _UNCACHED[key]


def _is_input(x: Any) -> bool:
    import equinox as eqx
    import jax

    return eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct)


def prepare(name: str, fn: Callable, *args: Any, compiler_options: dict | None = None) -> None:
    """Load (or trace and store) and compile the program of ``call(name, fn, *args,
    compiler_options=...)`` without running it, so that the later :func:`call` only runs
    it. ``args`` may hold :class:`jax.ShapeDtypeStruct` leaves (with the sharding the real
    array will have) for inputs not computed yet. Meant for a thread beside the main one's
    other work: XLA reads a cached executable without the interpreter lock. Does nothing
    without the cache; a failure only leaves the work to :func:`call`."""
    if _traces is None:
        return
    import equinox as eqx
    import jax

    if jax.process_count() > 1:
        return
    dynamic, static = eqx.partition(args, _is_input)
    leaves, treedef = jax.tree.flatten(dynamic)
    key = _key(name, static, leaves)
    if key is None:
        return
    try:
        _load(key, fn, static, leaves, treedef, compiler_options)
    except Exception:
        return


def _options(compiler_options: dict | None) -> tuple:
    """``compiler_options`` as part of a key (none: empty)."""
    return tuple(sorted((compiler_options or {}).items()))


def _load(key: str, fn: Callable, static, leaves: Sequence, treedef,
          compiler_options: dict | None) -> Callable:
    """The program ``key`` names, loaded (or traced and stored) and compiled with
    ``compiler_options`` once (now, so that threads calling it at once do not each compile
    it): a function of the flat inputs, kept in :data:`_loaded`."""
    import equinox as eqx
    import jax

    loaded_key = (key, _options(compiler_options))
    if loaded_key not in _loaded:
        def flat(*flat_leaves):
            return fn(*eqx.combine(jax.tree.unflatten(treedef, flat_leaves), static))

        jitted = _load_or_export(key, flat, leaves)
        compiled = jitted.lower(*leaves).compile(compiler_options)
        _loaded.setdefault(loaded_key, _compiled(jitted, compiled))
    return _loaded[loaded_key]


def _compiled(jitted: Callable, compiled: Callable) -> Callable:
    """``compiled``, or ``jitted`` for inputs it was not compiled for."""
    def run(*xs):
        try:
            return compiled(*xs)
        except (TypeError, ValueError):  # inputs placed otherwise than announced
            return jitted(*xs)

    return run


def _load_or_export(key: str, flat: Callable, leaves: Sequence) -> Callable:
    import jax
    from jax import export

    path = _traces / f"{key}.jaxexport"
    refused = _traces / f"{key}.noexport"
    if refused.exists():  # this program could not be exported before: do not try again
        return jax.jit(flat)
    try:
        exported = export.deserialize(bytearray(path.read_bytes()))
    except Exception:  # missing, damaged or from an incompatible version: trace again
        try:
            exported = export.export(jax.jit(flat))(*leaves)
            data = exported.serialize()
        except Exception:  # not exportable (a custom call without a stable ABI, an
            # unregistered pytree node, ...): remembered, so that runs do not retry
            try:
                _traces.mkdir(parents=True, exist_ok=True)
                refused.touch()
            except OSError:
                pass
            return jax.jit(flat)
        try:
            from ._io import atomic_write_bytes

            _traces.mkdir(parents=True, exist_ok=True)
            atomic_write_bytes(path, data)
            _prune(_traces)
        except OSError:
            pass
    return jax.jit(exported.call)
