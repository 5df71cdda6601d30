"""Linear algebra for the tiny systems of the steps and the models (n ≤ 8): unrolled at
trace time over the static size, so that XLA sees a few fused vector operations (batched
under ``vmap``) instead of LAPACK calls.

* :func:`small_solve`: Gaussian elimination with partial pivoting (any non-singular matrix);
* :func:`spd_inverse`, :func:`spd_solve`: pivot-free Gauss–Jordan for symmetric positive
  definite matrices (mass matrices);
* :func:`ldl_solve`: ``A = L D Lᵀ`` entry by entry, for programs emitted on scalars.

A singular matrix gives non-finite entries, which the solvers report as
``RESULTS.nonfinite`` (:mod:`lgvi_jax.trajectory`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["ldl_solve", "small_solve", "spd_inverse", "spd_solve"]

_UNROLL_MAX = 8  # measured crossover with LAPACK LU (experiments/bench_newton.py)


def small_solve(A: jax.Array, b: jax.Array) -> jax.Array:
    """Solve ``A x = b`` for a small square ``A`` (n <= 8: unrolled elimination).

    Gaussian elimination with partial pivoting, unrolled at trace time over the static size
    ``n``, so that XLA sees a few fused vector operations (and batches them under ``vmap``)
    instead of a LAPACK call. Larger systems fall back to ``jnp.linalg.solve``. A singular
    ``A`` gives non-finite entries, which :func:`newton_solve` reports as
    :attr:`RESULTS.nonfinite`. Linear in ``b``, so it can be transposed (reverse mode).
    """
    n = A.shape[-1]
    if A.shape != (n, n) or b.shape != (n,):
        raise ValueError(f"small_solve: expected A (n, n) and b (n,), got {A.shape}, {b.shape}")
    if n > _UNROLL_MAX:
        return jnp.linalg.solve(A, b)
    rows = jnp.arange(n)
    for k in range(n - 1):
        p = k + jnp.argmax(jnp.abs(A[k:, k]))
        perm = rows.at[k].set(p).at[p].set(k)
        A = A[perm]
        b = b[perm]
        factors = A[k + 1 :, k] / A[k, k]
        A = A.at[k + 1 :, k:].add(-factors[:, None] * A[k, k:])
        b = b.at[k + 1 :].add(-factors * b[k])
    x = [None] * n
    for k in reversed(range(n)):
        acc = b[k]
        for j in range(k + 1, n):
            acc = acc - A[k, j] * x[j]
        x[k] = acc / A[k, k]
    return jnp.stack(x)


def spd_inverse(A: jax.Array) -> jax.Array:
    """Inverse of a small symmetric positive definite matrix (a mass matrix).

    Gauss–Jordan elimination without pivoting, unrolled over the static size: step ``k``
    is the rank-one update ``[A | X] -= (a_k − e_k) ⊗ [A | X]_k / A_kk`` with ``a_k`` the
    current column ``k``, which turns column ``k`` into ``e_k``. For a symmetric positive
    definite matrix every pivot is positive (the pivots are the ratios of leading principal
    minors), so no row exchange is needed, and the whole elimination is a handful of fused
    vector operations without the gathers of pivoting: under ``vmap`` and in a
    single-trajectory loop it costs a fraction of :func:`small_solve` per column. A matrix
    that is not positive definite may give non-finite entries (reported by the solvers as
    :attr:`RESULTS.nonfinite`) or an inaccurate inverse: use :func:`small_solve` then.
    """
    n = A.shape[-1]
    if A.shape != (n, n):
        raise ValueError(f"spd_inverse: expected a square matrix, got shape {A.shape}")
    return _gauss_jordan(A, jnp.eye(n, dtype=A.dtype))


def spd_solve(A: jax.Array, b: jax.Array) -> jax.Array:
    """``A⁻¹ b`` for a small symmetric positive definite ``A`` by the pivot-free elimination
    of :func:`spd_inverse` (the inverse Legendre map of the models)."""
    n = A.shape[-1]
    if A.shape != (n, n) or b.shape != (n,):
        raise ValueError(f"spd_solve: expected A (n, n) and b (n,), got {A.shape}, {b.shape}")
    return _gauss_jordan(A, b[:, None])[:, 0]


def ldl_solve(A: jax.Array, b: jax.Array) -> jax.Array:
    """``A⁻¹ b`` for a small symmetric positive definite ``A`` by ``A = L D Lᵀ`` (no
    pivoting, unrolled entry by entry over the static size; reads only the lower triangle).
    For programs emitted on scalars (:mod:`lgvi_jax.scalarize`): ~n³/3 multiply-adds
    instead of the ~2n³ of :func:`spd_solve`'s Gauss–Jordan sweep, and structural zeros of
    ``A`` fold (the car-pendulum's initial guess, mass matrix and solve: 193 operations
    instead of 295). Array code keeps :func:`spd_solve` (a few vector operations)."""
    n = A.shape[-1]
    if A.shape != (n, n) or b.shape != (n,):
        raise ValueError(f"ldl_solve: expected A (n, n) and b (n,), got {A.shape}, {b.shape}")
    L: dict = {}
    D = []
    for j in range(n):
        d = A[j, j]
        for k in range(j):
            d = d - L[j, k] * L[j, k] * D[k]
        D.append(d)
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s = s - L[i, k] * L[j, k] * D[k]
            L[i, j] = s / d
    y = []
    for i in range(n):  # L y = b
        s = b[i]
        for k in range(i):
            s = s - L[i, k] * y[k]
        y.append(s)
    x = [None] * n
    for i in reversed(range(n)):  # D Lᵀ x = y
        s = y[i] / D[i]
        for k in range(i + 1, n):
            s = s - L[k, i] * x[k]
        x[i] = s
    return jnp.stack(x)


def _gauss_jordan(A, X):
    eye = np.eye(A.shape[-1])
    for k in range(A.shape[-1]):
        col = A[:, k] - eye[k]
        inv_pivot = 1.0 / A[k, k]
        A = A - col[:, None] * (A[k] * inv_pivot)[None, :]
        X = X - col[:, None] * (X[k] * inv_pivot)[None, :]
    return X
