r"""A physically consistent, unconstrained parametrisation of rigid-body inertia.

A rigid body's mass distribution has, about its mass centre, the second-moment matrix

.. math::  \Sigma = \int (x - c)(x - c)^\top \, dm \;\succeq\; 0,

and its inertia tensor about the mass centre is :math:`J_c = \operatorname{tr}(\Sigma)\,I -
\Sigma` (inversely :math:`\Sigma = \tfrac12\operatorname{tr}(J_c)\,I - J_c`). In principal
axes, :math:`\Sigma = \operatorname{diag}(\sigma_1, \sigma_2, \sigma_3)` and the principal
moments are :math:`\lambda_i = \sigma_j + \sigma_k`, so

* :math:`\Sigma \succ 0` makes every :math:`\lambda_i > 0` (``J_c`` positive definite), and
* :math:`\lambda_j + \lambda_k - \lambda_i = 2\sigma_i > 0`: the triangle inequalities hold
  strictly.

Conversely every strictly physical ``J_c`` has :math:`\Sigma \succ 0`. Hence the map

.. math::
    \theta \in \mathbb{R}^6 \;\mapsto\; L(\theta) = \begin{pmatrix} e^{\theta_0} & 0 & 0 \\
    \theta_3 & e^{\theta_1} & 0 \\ \theta_4 & \theta_5 & e^{\theta_2} \end{pmatrix}
    \;\mapsto\; \Sigma = LL^\top \;\mapsto\; J_c = \operatorname{tr}(\Sigma)I - \Sigma

(a log-Cholesky factor of the second-moment matrix) is a smooth bijection from
:math:`\mathbb{R}^6` onto the strictly physical inertias, with the inverse
:func:`params_from_inertia` (Cholesky factor of :math:`\Sigma`, log of its diagonal). Any
unconstrained vector, e.g. an optimiser's iterate, is a physical inertia.

About the pivot (the body-frame origin; the models' ``J``), the parallel-axis theorem adds
:math:`m(|\rho_c|^2 I - \rho_c\rho_c^\top)`. With :math:`m = e^{\theta_m} > 0` and any
:math:`\rho_c`, the 4x4 *pseudo-inertia* about the pivot

.. math::
    P = \begin{pmatrix} \Sigma + m\rho_c\rho_c^\top & m\rho_c \\ m\rho_c^\top & m
    \end{pmatrix}

is positive definite (its Schur complement is :math:`\Sigma`), which is the condition of
physical consistency of Wensing, Kim and Slotine; the parametrisation here is the
log-Cholesky parametrisation of :math:`P` of Rucker and Wensing, written in the
variables ``(m, ρ_c, Σ)`` that the identification fits separately.

References: P. M. Wensing, S. Kim, J.-J. E. Slotine, *Linear matrix inequalities for
physically consistent inertial parameter identification*, IEEE RA-L 3 (2018);
C. Rucker, P. M. Wensing, *Smooth parameterization of rigid-body inertia*, IEEE RA-L 7
(2022); J. C. Pinheiro, D. M. Bates, *Unconstrained parametrizations for variance-covariance
matrices*, Statistics and Computing 6 (1996) (the log-Cholesky factor).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ._checks import symmetric_3x3

__all__ = [
    "centroidal_inertia",
    "inertia_from_params",
    "is_physical",
    "parallel_axis",
    "params_from_inertia",
    "pivot_inertia",
    "pseudo_inertia",
    "second_moment",
]

_TRIL = (np.array([1, 2, 2]), np.array([0, 0, 1]))  # below-diagonal entries L10, L20, L21


def _cholesky_factor(theta: jax.Array) -> jax.Array:
    theta = jnp.asarray(theta, jnp.float64)
    if theta.shape[-1:] != (6,):
        raise ValueError(f"inertia: theta must have shape (..., 6), got {theta.shape}")
    L = jnp.zeros((*theta.shape[:-1], 3, 3), theta.dtype)
    L = L.at[..., jnp.arange(3), jnp.arange(3)].set(jnp.exp(theta[..., :3]))
    return L.at[..., _TRIL[0], _TRIL[1]].set(theta[..., 3:])


def second_moment(theta: Any) -> jax.Array:
    """``Σ = L Lᵀ`` (symmetric positive definite) from the unconstrained ``θ`` (``(..., 6)``:
    three log-diagonal entries of ``L``, then ``L10, L20, L21``)."""
    L = _cholesky_factor(theta)
    S = L @ jnp.swapaxes(L, -1, -2)
    return 0.5 * (S + jnp.swapaxes(S, -1, -2))  # exactly symmetric


def inertia_from_params(theta: Any) -> jax.Array:
    """The inertia about the mass centre ``J_c = tr(Σ) I − Σ``, ``Σ = L(θ)L(θ)ᵀ``: positive
    definite and strictly satisfying the triangle inequalities for every finite ``θ``."""
    S = second_moment(theta)
    tr = jnp.trace(S, axis1=-2, axis2=-1)[..., None, None]
    return tr * jnp.eye(3, dtype=S.dtype) - S


def params_from_inertia(J_c: Any) -> jax.Array:
    """Inverse of :func:`inertia_from_params`: ``θ`` with ``inertia_from_params(θ) = J_c``.

    Raises ``ValueError`` naming the problem if ``J_c`` is not a 3x3, finite, symmetric,
    *strictly* physical inertia (``Σ = ½ tr(J_c) I − J_c`` positive definite; a body flat
    in a plane, on the boundary, has no finite ``θ``). Concrete values only.
    """
    arr, scale = symmetric_3x3("J_c", J_c, "params_from_inertia")
    S = 0.5 * np.trace(arr) * np.eye(3) - arr
    sigma = np.linalg.eigvalsh(S)
    if sigma[0] <= 1e-14 * scale:
        moments = np.linalg.eigvalsh(arr)
        raise ValueError(
            "params_from_inertia: J_c is not a strictly physical inertia (principal moments "
            f"{moments.tolist()}; the second moments ½tr(J)−λ must be > 0: positive definite "
            "with strict triangle inequalities)"
        )
    L = np.linalg.cholesky(S)
    return jnp.asarray(np.concatenate([np.log(np.diag(L)), L[_TRIL]]))


def parallel_axis(m: Any, rho_c: Any) -> jax.Array:
    """The parallel-axis term ``m (|ρ_c|² I − ρ_c ρ_cᵀ)``: inertia about the pivot minus
    inertia about the mass centre, for mass ``m`` at body point ``ρ_c``."""
    rho = jnp.asarray(rho_c, jnp.float64)
    return jnp.asarray(m, jnp.float64) * (jnp.dot(rho, rho) * jnp.eye(3) - jnp.outer(rho, rho))


def pivot_inertia(J_c: Any, m: Any, rho_c: Any) -> jax.Array:
    """Inertia about the pivot (body origin), ``J = J_c + m(|ρ_c|² I − ρ_c ρ_cᵀ)``."""
    return jnp.asarray(J_c, jnp.float64) + parallel_axis(m, rho_c)


def centroidal_inertia(J: Any, m: Any, rho_c: Any) -> jax.Array:
    """Inertia about the mass centre from that about the pivot, ``J_c = J − m(|ρ_c|² I −
    ρ_c ρ_cᵀ)``."""
    return jnp.asarray(J, jnp.float64) - parallel_axis(m, rho_c)


def pseudo_inertia(J_c: Any, m: Any, rho_c: Any) -> jax.Array:
    """The 4x4 pseudo-inertia about the pivot (module docstring); positive definite exactly
    when ``(m, ρ_c, J_c)`` is strictly physically consistent."""
    J_c = jnp.asarray(J_c, jnp.float64)
    rho = jnp.asarray(rho_c, jnp.float64)
    m = jnp.asarray(m, jnp.float64)
    S = 0.5 * jnp.trace(J_c) * jnp.eye(3) - J_c + m * jnp.outer(rho, rho)
    top = jnp.concatenate([S, (m * rho)[:, None]], axis=1)
    bottom = jnp.concatenate([m * rho, m[None]])[None, :]
    return jnp.concatenate([top, bottom], axis=0)


def is_physical(J: Any, *, rtol: float = 1e-12) -> bool:
    """True if ``J`` is symmetric (to ``rtol``), positive definite, and its principal moments
    satisfy the triangle inequalities ``λ_i <= λ_j + λ_k`` (to ``rtol`` of the largest)."""
    arr = np.asarray(J, dtype=np.float64)
    if arr.shape != (3, 3) or not np.all(np.isfinite(arr)):
        return False
    scale = max(float(np.max(np.abs(arr))), 1e-300)
    if np.max(np.abs(arr - arr.T)) > rtol * scale:
        return False
    lam = np.linalg.eigvalsh(0.5 * (arr + arr.T))
    return bool(lam[0] > 0 and lam[2] <= lam[0] + lam[1] + rtol * scale)
