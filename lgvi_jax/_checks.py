"""Input validation shared by the library: clear ``ValueError``s that name the argument.

Checks run only on concrete values; under ``jit``/``vmap``/``grad`` tracing the values are
unknown and the checks are skipped (validate at the boundary, before tracing).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np


def is_concrete(x: Any) -> bool:
    """True when ``x`` holds a value (not a tracer), so it can be checked."""
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(x))


def check_positive(name: str, value: Any, owner: str) -> None:
    """Raise ``ValueError`` unless every entry of ``value`` is finite and > 0."""
    if not is_concrete(value):
        return
    arr = np.asarray(value)
    if not np.issubdtype(arr.dtype, np.number):
        raise ValueError(f"{owner}: {name} must be a number, got {value!r}")
    if not np.all(np.isfinite(arr)) or not np.all(arr > 0):
        shown = arr.tolist() if arr.ndim else arr.item()
        raise ValueError(f"{owner}: {name} must be finite and > 0, got {shown!r}")


def check_finite(name: str, value: Any, owner: str) -> None:
    """Raise ``ValueError`` unless every entry of ``value`` is finite."""
    if is_concrete(value) and not np.all(np.isfinite(np.asarray(value))):
        arr = np.asarray(value)
        shown = arr.tolist() if arr.ndim else arr.item()
        raise ValueError(f"{owner}: {name} must be finite, got {shown!r}")


def check_float64_finite(name: str, tree: Any, owner: str) -> None:
    """Raise ``ValueError`` unless every floating leaf of ``tree`` is finite float64."""
    if not is_concrete(tree):
        return
    for leaf in jax.tree.leaves(tree):
        arr = np.asarray(leaf)
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"{owner}: {name} must hold floating-point arrays, got {arr.dtype}")
        if arr.dtype != np.float64:
            raise ValueError(
                f"{owner}: {name} must be float64 (got {arr.dtype}); long-horizon invariant "
                "checks are meaningless in lower precision. Convert with jnp.float64 / "
                "np.asarray(..., dtype=np.float64)."
            )
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{owner}: {name} contains non-finite values (NaN or inf)")


def as_float_array(name: str, value: Any, owner: str) -> jax.Array:
    """Convert parameter ``name`` to a float64 JAX array (tracers pass through). Real
    numbers (Python, NumPy, nested sequences) are converted on the host and placed with
    ``device_put``: ``jnp.asarray`` would compile a conversion program per shape and dtype,
    on the critical path of every command's start."""
    if not isinstance(value, (jax.Array, str, bytes)) and value is not None:
        try:
            host = np.asarray(value)
        except Exception:  # left to jnp.asarray, which names the problem
            host = None
        if host is not None and host.dtype.kind in "fiu":  # real numbers, not bools
            return jax.device_put(host.astype(np.float64))
    try:
        return jnp.asarray(value, dtype=jnp.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}: {name} must be a number or an array, got {value!r}") from None


def symmetric_3x3(name: str, value: Any, owner: str) -> tuple[np.ndarray, float]:
    """``value`` as a symmetric 3x3 float64 NumPy matrix and its largest entry's size;
    ``ValueError`` naming ``owner`` and ``name`` unless it is 3x3, finite and symmetric to
    1e-12 of that size (the checks shared by every inertia). Concrete values only."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3, 3):
        raise ValueError(f"{owner}: {name} must be a 3x3 matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{owner}: {name} must be finite, got {arr.tolist()}")
    scale = max(float(np.max(np.abs(arr))), 1e-300)
    if np.max(np.abs(arr - arr.T)) > 1e-12 * scale:
        raise ValueError(f"{owner}: {name} must be symmetric, got {arr.tolist()}")
    return 0.5 * (arr + arr.T), scale


def check_nonnegative(name: str, value: Any, owner: str) -> None:
    """Raise ``ValueError`` unless the scalar ``value`` is finite and >= 0."""
    # Compared on the host (a JAX comparison would compile a program).
    if is_concrete(value) and not (np.isfinite(host := np.asarray(value)) and host >= 0):
        raise ValueError(f"{owner}: {name} must be finite and >= 0, got {float(value)!r}")
