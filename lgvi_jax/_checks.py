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
    """Convert parameter ``name`` to a float64 JAX array (tracers pass through)."""
    try:
        return jnp.asarray(value, dtype=jnp.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{owner}: {name} must be a number or an array, got {value!r}") from None
