"""XLA CPU settings applied when :mod:`lgvi_jax` is imported.

**Small while loops compiled whole.** XLA's CPU runtime runs a compiled program as a
sequence of *thunks*, one per kernel (a fusion, a loop, a branch), and pays a dispatch cost
for each, tens of nanoseconds, whatever the kernel computes. A rigid-body step on one
trajectory is some 30-80 such kernels of a few scalar operations each (a Newton iteration
alone 5-7), so the dispatch, not the arithmetic, sets its speed. XLA's
``SmallWhileLoopHoistingPass`` (``xla/service/cpu/small_while_loop_hoisting_pass.cc``)
instead compiles a ``while`` loop whose body accesses fewer than
``xla_cpu_small_while_loop_byte_threshold`` bytes into a single function (one kernel, no
dispatch inside); the default threshold, 1 kB, catches only the innermost Newton loop of
one trajectory. Raised to :data:`SMALL_LOOP_BYTES`, it catches whole rollouts: measured on
the 2-core CPU (``lgvi-jax bench``) car-pendulum steps written in scalars (the
hand-reduced steps since retired; the scalar engine's are of the same kind) run 2.5-3x
faster for one trajectory and 1.2-1.4x faster in a batch of 1024, with the same results to
rounding (the test suite runs with it). Loops that contain what the single-
function emitter cannot compile (custom calls such as LAPACK solves, sorts, scatters, and
the YNN library's fusions that XLA makes of small matrix products, as in the general
engine's steps) keep the thunk runtime.

**The classic elemental emitter.** ``--xla_cpu_use_fusion_emitters=false``: XLA CPU then
generates each fusion's code with its elemental IR emitter instead of the newer MLIR
fusion emitters, which also wrap single operations into fusions of their own. Measured on
the 2-core CPU (``lgvi-jax bench``, same run): compiles 20-35 % faster (``hamel-exact``
on arrays, one trajectory, 3.04 -> 2.08 s; a batch of scalar steps 1.50 -> 1.33 s), the
same or higher throughput, the test suite 7.4 -> 5.3 min, trajectories equal to rounding.
XLA has since retired that emitter and its flag (jaxlib 0.11 aborts at the first
computation on an unknown ``XLA_FLAGS`` entry), so the flag is added only for the jaxlib
versions that know it (:data:`EMITTER_FLAG_BEFORE`).

**Wide vectors, loops not unrolled.** A batch on scalars is a long sequence of small
loops, one per fusion, over the trajectories of a block (``sweep.batch.SCALAR_BLOCK`` on a CPU):
the compiled rollout is one function of some 400 such loops, and LLVM's optimisation of
that function is most of the compile time. ``--xla_cpu_prefer_vector_width=512`` lets LLVM
use 512-bit vectors where the CPU has them (XLA's default is 256; no effect on a CPU
without AVX-512), and the backend option ``xla_cpu_disable_loop_unrolling`` keeps each
loop rolled.
Measured on the 2-core AVX-512 CPU, car-pendulum, 1024 trajectories on 2 devices,
compiled ahead of time, each configuration in its own process, alternated, two rounds:
XLA's compile 4.8-6.2 -> 3.0-4.5 s (35-45 % less) for ``lgvi``, ``hamel``, ``hamel-exact``
and ``lgvi@4``, and the run as fast (``lgvi``) or 7-17 % faster (the others); one
trajectory unchanged within noise. The vector width alone: the batch faster, the compile
not. Unrolling off on AVX2 code (``--xla_cpu_max_isa=AVX2``): compile 20 % less, the batch
7 % slower; so loops stay unrolled on CPUs without AVX-512 (:func:`_wide_vectors`).

The options only take effect if set before JAX starts its CPU backend, so they are added
to ``XLA_FLAGS`` here, at import, when

* the backend has not started yet (otherwise a :class:`XlaSettingWarning` says how to get
  them: import :mod:`lgvi_jax` before running any JAX computation, or set ``XLA_FLAGS``
  yourself),
* ``XLA_FLAGS`` does not already set the option (``xla_backend_extra_options``,
  ``xla_cpu_use_fusion_emitters``, ``xla_cpu_prefer_vector_width``: yours are kept as they
  are), and
* the environment variable ``LGVI_JAX_XLA_TUNING`` is not ``0`` (the opt-out).

They change how XLA compiles every CPU program of the process, not only lgvi_jax's.
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


def _wide_vectors() -> bool:
    """Whether the CPU has AVX-512 (Linux's ``/proc/cpuinfo``; elsewhere: assumed not)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return "avx512f" in line.split()
    except OSError:
        pass
    return False


def flag() -> str:
    """The ``XLA_FLAGS`` entry of the backend options: the small-loop setting and, on a CPU
    with AVX-512, loops not unrolled."""
    extra = f",{NO_UNROLL_OPTION}" if _wide_vectors() else ""
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
    return _OPTION in os.environ["XLA_FLAGS"]
