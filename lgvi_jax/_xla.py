"""XLA CPU settings applied when :mod:`lgvi_jax` is imported (``docs/process-settings.md``
gives the measurements behind each).

* **Small while loops compiled whole**: ``xla_cpu_small_while_loop_byte_threshold`` raised
  to :data:`SMALL_LOOP_BYTES`, so that XLA's ``SmallWhileLoopHoistingPass`` compiles a whole
  rollout as one function instead of dispatching each of its small kernels (the dispatch,
  not the arithmetic, sets the speed of one trajectory).
* **The elemental emitter** (``--xla_cpu_use_fusion_emitters=false``, for the jaxlib
  versions that know it, :data:`EMITTER_FLAG_BEFORE`): shorter compiles.
* **Wide vectors** (``--xla_cpu_prefer_vector_width=512``: 512-bit vectors where the CPU has
  them) and **loops not unrolled** on x86-64 CPUs with AVX2 or AVX-512 (backend option
  ``xla_cpu_disable_loop_unrolling``): shorter compiles of batches (LLVM optimising the
  rollout's many small loops is most of it), with runs as fast.

The options only take effect if set before JAX starts its CPU backend, so they are added
to ``XLA_FLAGS`` at import, when

* the backend has not started yet (otherwise a :class:`XlaSettingWarning` says how to get
  them: import :mod:`lgvi_jax` before running any JAX computation, or set ``XLA_FLAGS``
  yourself),
* ``XLA_FLAGS`` does not already set the option (yours are kept as they are), and
* the environment variable ``LGVI_JAX_XLA_TUNING`` is not ``0`` (the opt-out).

They change how XLA compiles every CPU program of the process, not only lgvi_jax's;
:func:`added` lists what the import added.
"""

from __future__ import annotations

import os
import warnings

#: The ``xla_cpu_small_while_loop_byte_threshold`` set at import (bytes accessed by one pass
#: of a loop body). 64 MiB: every rollout of this package, batched ones included (a batch of
#: 512 car-pendulum trajectories touches well under 1 MiB per step), and not loops over
#: large arrays, whose kernels the thunk runtime may run on several threads.
SMALL_LOOP_BYTES = 64 * 2**20

_OPTION = "xla_cpu_small_while_loop_byte_threshold"
#: The backend option that keeps LLVM from unrolling loops (module docstring). An unknown
#: backend option is ignored, so a jaxlib without it runs as before.
NO_UNROLL_OPTION = "xla_cpu_disable_loop_unrolling"
OPT_OUT = "LGVI_JAX_XLA_TUNING"

#: The ``XLA_FLAGS`` entry of the vector-width setting (module docstring; a flag since
#: before jaxlib 0.4.30, the oldest this package supports: checked in its binary).
VECTOR_FLAG = "--xla_cpu_prefer_vector_width=512"

#: The ``XLA_FLAGS`` entry of the emitter setting (module docstring).
EMITTER_FLAG = "--xla_cpu_use_fusion_emitters=false"
#: The first jaxlib version without that flag (seen: 0.10.2 has it, 0.11.2 aborts on it).
EMITTER_FLAG_BEFORE = (0, 11)


def _emitter_flag_known() -> bool:
    """Whether the installed jaxlib knows :data:`EMITTER_FLAG` (an unreadable version: no,
    since an unknown flag aborts the process and the flag only saves compile time)."""
    from importlib import metadata

    try:
        parts = metadata.version("jaxlib").split(".")[:2]
        return tuple(int(x) for x in parts) < EMITTER_FLAG_BEFORE
    except (metadata.PackageNotFoundError, ValueError):
        return False


class XlaSettingWarning(UserWarning):
    """lgvi_jax could not apply its XLA setting (module docstring)."""


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge
        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # a JAX without this query: assume not started
        return False


def _cpuinfo(field: str) -> str | None:
    """The value of ``field`` for the first CPU in Linux's ``/proc/cpuinfo`` (``None``
    elsewhere, or when it has no such field)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith(field):
                    return line.split(":", 1)[1].strip() if ":" in line else ""
    except OSError:
        pass
    return None


def _cpu_flags() -> set[str]:
    """The CPU's feature flags (Linux's ``/proc/cpuinfo``; elsewhere: none known)."""
    return set((_cpuinfo("flags") or "").split())


def _wide_vectors() -> bool:
    """Whether the CPU has AVX-512 (:func:`_cpu_flags`)."""
    return "avx512f" in _cpu_flags()


def _unrolling_off() -> bool:
    """Whether loops are compiled without unrolling: on CPUs with AVX2 or AVX-512 (where it
    was measured: compiles of batches 35–55 % shorter, runs as fast); elsewhere XLA's
    default stays."""
    return bool(_cpu_flags() & {"avx2", "avx512f"})


def cpu_model() -> str:
    """The CPU's name (``model name`` of ``/proc/cpuinfo``; elsewhere
    :func:`platform.processor`), ``"unknown"`` when neither says."""
    import platform

    return _cpuinfo("model name") or platform.processor() or "unknown"


def flag() -> str:
    """The ``XLA_FLAGS`` entry of the backend options: the small-loop setting and, on a CPU
    with AVX2 or AVX-512, loops not unrolled."""
    extra = f",{NO_UNROLL_OPTION}" if _unrolling_off() else ""
    return f"--xla_backend_extra_options={_OPTION}={SMALL_LOOP_BYTES}{extra}"


def flags() -> list[str]:
    """Every ``XLA_FLAGS`` entry this module adds (where the user's flags leave room)."""
    return [entry for entry, _ in _settings()]


def _settings() -> list[tuple[str, tuple[str, ...]]]:
    """``(entry, option names that mean the user has chosen it already)`` per setting."""
    out = [(flag(), (_OPTION, "xla_backend_extra_options"))]
    if _emitter_flag_known():
        out.append((EMITTER_FLAG, ("xla_cpu_use_fusion_emitters",)))
    out.append((VECTOR_FLAG, ("xla_cpu_prefer_vector_width",)))
    return out


#: The ``XLA_FLAGS`` entries :func:`configure` added in this process.
_ADDED: list[str] = []


def added() -> tuple[str, ...]:
    """The ``XLA_FLAGS`` entries the import of :mod:`lgvi_jax` added in this process (empty
    when it added none: opted out, already set, or JAX started first)."""
    return tuple(_ADDED)


def configure() -> bool:
    """Add :func:`flags` to ``XLA_FLAGS`` where the module docstring says; ``True`` if the
    small-loop setting is (or already was) in effect."""
    current = os.environ.get("XLA_FLAGS", "")
    if os.environ.get(OPT_OUT, "1").strip() == "0":
        return _OPTION in current
    missing = [entry for entry, names in _settings() if not any(n in current for n in names)]
    if not missing:
        return _OPTION in current
    if _backend_started():
        warnings.warn(
            "lgvi_jax was imported after JAX started its backend, so its XLA settings are "
            "off (small-loop compilation: single trajectories run ~3x slower on the CPU; "
            "the elemental emitter: compiles take ~30% longer); import lgvi_jax before the "
            f"first JAX computation, or set XLA_FLAGS='{' '.join(missing)}' (set "
            f"{OPT_OUT}=0 to silence this)", XlaSettingWarning, stacklevel=3)
        return _OPTION in current
    os.environ["XLA_FLAGS"] = " ".join([current.strip(), *missing]).strip()
    _ADDED.extend(missing)
    return _OPTION in os.environ["XLA_FLAGS"]
