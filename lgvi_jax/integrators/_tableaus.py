"""Nodes, weights and interpolation matrices on [0, 1], computed once in NumPy (float64).

These are trace-time constants: the integrators embed them in the compiled step.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.polynomial import legendre as L


@functools.cache
def gauss_legendre(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes ``c`` and weights ``b`` on [0, 1] (exact for degree 2n−1)."""
    x, w = L.leggauss(n)
    return 0.5 * (x + 1.0), 0.5 * w


@functools.cache
def gauss_lobatto(n: int) -> np.ndarray:
    """The ``n >= 2`` Gauss–Lobatto points on [0, 1]: 0, 1 and the roots of P'_{n−1}."""
    if n < 2:
        raise ValueError("gauss_lobatto: need at least 2 points")
    interior = L.Legendre.basis(n - 1).deriv().roots() if n > 2 else np.array([])
    x = np.sort(np.concatenate([[-1.0], np.real(interior), [1.0]]))
    return 0.5 * (x + 1.0)


def lagrange_matrices(nodes: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values ``V[i, j] = ℓ_j(points_i)`` and derivatives ``D[i, j] = ℓ_j'(points_i)`` of the
    Lagrange basis polynomials on ``nodes``."""
    n = len(nodes)
    V = np.zeros((len(points), n))
    D = np.zeros((len(points), n))
    for j in range(n):
        others = np.delete(nodes, j)
        poly = np.poly1d(others, r=True) / np.prod(nodes[j] - others)
        V[:, j] = poly(points)
        D[:, j] = poly.deriv()(points)
    return V, D


@functools.cache
def collocation_matrix(nodes: tuple[float, ...]) -> np.ndarray:
    """Runge–Kutta collocation coefficients ``a_ij = ∫_0^{c_i} ℓ_j(τ) dτ``."""
    c = np.asarray(nodes)
    s = len(c)
    A = np.zeros((s, s))
    for j in range(s):
        others = np.delete(c, j)
        poly = (np.poly1d(others, r=True) / np.prod(c[j] - others)).integ()
        A[:, j] = poly(c) - poly(0.0)
    return A
