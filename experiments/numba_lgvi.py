r"""Compiled-loop baseline for the throughput benchmark: the car-pendulum ``lgvi`` step in
Numba, from hand-derived discrete equations.

Same discrete Lagrangian as :class:`lgvi_jax.LGVI` (``L_d = h[T(R_k, (F-I)/h, q_k, u) -
½U_k - ½U_{k+1}]``, ``T = ½(m+M)|u|² + ½tr(ΩJ_dΩᵀ) + m uᵀPRΩρ_c``, ``U = -m g e3ᵀRρ_c``),
so the same solution of the same equations. With ``a = R_kᵀPᵀu`` and ``b = R_kᵀe3``, the
discrete Legendre transforms reduce to (derived by hand, checked against the JAX engine in
``tests/test_numba_baseline.py``)

.. math::
    p_k = (m+M)u + \tfrac{m}{h}P R_k(F-I)\rho_c, \qquad
    \mu_k = \tfrac1h(FJ_d - J_dF^\top)^\vee + m\,\rho_c\times a - \tfrac{h}{2}mg\,\rho_c
            \times b,

    \mu_{k+1} = \tfrac1h(J_dF - F^\top J_d)^\vee + m\,\rho_c\times(F^\top a) +
                \tfrac{h}{2}mg\,\rho_c\times R_{k+1}^\top e_3, \qquad p_{k+1} = p_k.

The first equation gives ``u`` explicitly for a given ``F``, leaving three equations for
the Cayley coordinates ``w`` of ``F = cay(w)``, solved by Newton's method with a
complex-step Jacobian (exact to round-off: one complex residual per unknown), warm-started
from the previous step's ``w``, stopping when ``|Δw| <= 1e-12 (h + |w|)`` componentwise
(the tolerance of the JAX solver on ``ξ = w/h``). ``rollout_batch`` runs trajectories in
parallel over all cores (``numba.prange``).

The Hamel methods (``hamel``, ``hamel-cayley``, ``hamel-exact``) are in
:mod:`numba_hamel` (their own derivation), dispatched by ``rollout``/``rollout_batch``
below with the same parameters and return values.
"""

from __future__ import annotations

import time

import numba
import numpy as np
from lgvi_jax.experiments import numba_hamel as _hamel
from numba import njit, prange

METHODS = ("lgvi", *_hamel.METHODS)


def params_from_model(model) -> np.ndarray:
    """``(m, M, g, rho_c (3), J (9))`` as one float64 vector."""
    return np.concatenate([
        np.atleast_1d(np.asarray(model.m, np.float64)),
        np.atleast_1d(np.asarray(model.M, np.float64)),
        np.atleast_1d(np.asarray(model.g, np.float64)),
        np.asarray(model.rho_c, np.float64), np.asarray(model.J, np.float64).ravel()])


@njit(cache=False, error_model="numpy")
def _cayley(w, F):
    k = 4.0 / (4.0 + w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    x, y, z = w[0], w[1], w[2]
    # cay(w) = I + k (hat(w) + hat(w)^2 / 2), hat(w)^2 = w wᵀ - |w|² I
    n2 = x * x + y * y + z * z
    F[0, 0] = 1.0 + k * 0.5 * (x * x - n2)
    F[1, 1] = 1.0 + k * 0.5 * (y * y - n2)
    F[2, 2] = 1.0 + k * 0.5 * (z * z - n2)
    F[0, 1] = k * (-z + 0.5 * x * y)
    F[1, 0] = k * (z + 0.5 * x * y)
    F[0, 2] = k * (y + 0.5 * x * z)
    F[2, 0] = k * (-y + 0.5 * x * z)
    F[1, 2] = k * (-x + 0.5 * y * z)
    F[2, 1] = k * (x + 0.5 * y * z)


@njit(cache=False, error_model="numpy")
def _residual(w, R0, mu0, p0, h, prm, Jd, out, u_out):
    """Residual μ_k(w) − μ0 (and u); works for float64 and complex128 ``w``."""
    m, M, g = prm[0], prm[1], prm[2]
    rho = prm[3:6]
    F = np.empty((3, 3), dtype=w.dtype)
    _cayley(w, F)
    # c = (F - I) ρ_c, then P R0 c
    c = np.empty(3, dtype=w.dtype)
    for i in range(3):
        c[i] = F[i, 0] * rho[0] + F[i, 1] * rho[1] + F[i, 2] * rho[2] - rho[i]
    u0 = (p0[0] - m * (R0[0, 0] * c[0] + R0[0, 1] * c[1] + R0[0, 2] * c[2]) / h) / (m + M)
    u1 = (p0[1] - m * (R0[1, 0] * c[0] + R0[1, 1] * c[1] + R0[1, 2] * c[2]) / h) / (m + M)
    u_out[0] = u0
    u_out[1] = u1
    a = np.empty(3, dtype=w.dtype)
    for i in range(3):
        a[i] = R0[0, i] * u0 + R0[1, i] * u1
    # (F J_d − J_d Fᵀ)^∨ = 2 vee(F J_d)
    FJ = np.empty((3, 3), dtype=w.dtype)
    for i in range(3):
        for j in range(3):
            FJ[i, j] = F[i, 0] * Jd[0, j] + F[i, 1] * Jd[1, j] + F[i, 2] * Jd[2, j]
    v0 = FJ[2, 1] - FJ[1, 2]
    v1 = FJ[0, 2] - FJ[2, 0]
    v2 = FJ[1, 0] - FJ[0, 1]
    b0, b1, b2 = R0[2, 0], R0[2, 1], R0[2, 2]
    hg = 0.5 * h * m * g
    out[0] = v0 / h + m * (rho[1] * a[2] - rho[2] * a[1]) - hg * (rho[1] * b2 - rho[2] * b1) \
        - mu0[0]
    out[1] = v1 / h + m * (rho[2] * a[0] - rho[0] * a[2]) - hg * (rho[2] * b0 - rho[0] * b2) \
        - mu0[1]
    out[2] = v2 / h + m * (rho[0] * a[1] - rho[1] * a[0]) - hg * (rho[0] * b1 - rho[1] * b0) \
        - mu0[2]


@njit(cache=False, error_model="numpy")
def _solve3(A, b, x):
    # Gaussian elimination with partial pivoting, 3x3.
    M = A.copy()
    r = b.copy()
    for k in range(2):
        p = k
        for i in range(k + 1, 3):
            if abs(M[i, k]) > abs(M[p, k]):
                p = i
        if p != k:
            for j in range(3):
                M[k, j], M[p, j] = M[p, j], M[k, j]
            r[k], r[p] = r[p], r[k]
        for i in range(k + 1, 3):
            f = M[i, k] / M[k, k]
            for j in range(k, 3):
                M[i, j] -= f * M[k, j]
            r[i] -= f * r[k]
    for k in range(2, -1, -1):
        s = r[k]
        for j in range(k + 1, 3):
            s -= M[k, j] * x[j]
        x[k] = s / M[k, k]


@njit(cache=False, error_model="numpy")
def _step(R0, mu0, q0, p0, w, h, prm, Jd, R1, mu1, q1, p1):
    """One step in place; ``w`` is the warm start and returns the solution. Returns
    (iterations, code)."""
    m, g = prm[0], prm[2]
    rho = prm[3:6]
    r = np.empty(3)
    u = np.empty(2)
    rc = np.empty(3, dtype=np.complex128)
    uc = np.empty(2, dtype=np.complex128)
    wc = np.empty(3, dtype=np.complex128)
    J = np.empty((3, 3))
    dw = np.empty(3)
    eps = 1e-30
    code = 1
    its = 0
    for it in range(20):
        its = it + 1
        _residual(w, R0, mu0, p0, h, prm, Jd, r, u)
        for j in range(3):
            for i in range(3):
                wc[i] = w[i]
            wc[j] = w[j] + 1j * eps
            _residual(wc, R0, mu0, p0, h, prm, Jd, rc, uc)
            for i in range(3):
                J[i, j] = rc[i].imag / eps
        _solve3(J, -r, dw)
        finite = True
        done = True
        for i in range(3):
            if not np.isfinite(dw[i]):
                finite = False
            w[i] += dw[i]
            if abs(dw[i]) > 1e-12 * (h + abs(w[i])):
                done = False
        if not finite:
            code = 2
            break
        if done:
            code = 0
            break
    _residual(w, R0, mu0, p0, h, prm, Jd, r, u)
    F = np.empty((3, 3))
    _cayley(w, F)
    for i in range(3):
        for j in range(3):
            R1[i, j] = R0[i, 0] * F[0, j] + R0[i, 1] * F[1, j] + R0[i, 2] * F[2, j]
    q1[0] = q0[0] + h * u[0]
    q1[1] = q0[1] + h * u[1]
    p1[0] = p0[0]
    p1[1] = p0[1]
    a = np.empty(3)
    for i in range(3):
        a[i] = R0[0, i] * u[0] + R0[1, i] * u[1]
    Fa = np.empty(3)
    for i in range(3):
        Fa[i] = F[0, i] * a[0] + F[1, i] * a[1] + F[2, i] * a[2]  # Fᵀ a
    JF = np.empty((3, 3))  # J_d F − Fᵀ J_d, vee
    for i in range(3):
        for j in range(3):
            JF[i, j] = Jd[i, 0] * F[0, j] + Jd[i, 1] * F[1, j] + Jd[i, 2] * F[2, j]
    # (J_d F − Fᵀ J_d)^∨ = 2 vee(J_d F)
    v0 = JF[2, 1] - JF[1, 2]
    v1 = JF[0, 2] - JF[2, 0]
    v2 = JF[1, 0] - JF[0, 1]
    b0, b1, b2 = R1[2, 0], R1[2, 1], R1[2, 2]
    hg = 0.5 * h * m * g
    mu1[0] = v0 / h + m * (rho[1] * Fa[2] - rho[2] * Fa[1]) + hg * (rho[1] * b2 - rho[2] * b1)
    mu1[1] = v1 / h + m * (rho[2] * Fa[0] - rho[0] * Fa[2]) + hg * (rho[2] * b0 - rho[0] * b2)
    mu1[2] = v2 / h + m * (rho[0] * Fa[1] - rho[1] * Fa[0]) + hg * (rho[0] * b1 - rho[1] * b0)
    for i in range(3):
        if not np.isfinite(mu1[i]):
            code = 2
    return its, code


@njit(cache=False, error_model="numpy")
def _jd(prm):
    J = prm[6:15].reshape(3, 3)
    tr = J[0, 0] + J[1, 1] + J[2, 2]
    Jd = -J.copy()
    for i in range(3):
        Jd[i, i] += 0.5 * tr
    return Jd


@njit(cache=False, error_model="numpy")
def _rollout(R, mu, q, p, h, n_steps, prm):
    Jd = _jd(prm)
    R0, mu0, q0, p0 = R.copy(), mu.copy(), q.copy(), p.copy()
    R1, mu1, q1, p1 = np.empty((3, 3)), np.empty(3), np.empty(2), np.empty(2)
    # First guess: w = h J⁻¹ μ (then each step warm-starts from the previous solution).
    w = np.empty(3)
    J = prm[6:15].reshape(3, 3).copy()
    _solve3(J, h * mu0, w)
    total = 0
    code = 0
    for _ in range(n_steps):
        its, c = _step(R0, mu0, q0, p0, w, h, prm, Jd, R1, mu1, q1, p1)
        total += its
        if c != 0:
            code = c
            for i in range(3):
                mu0[i] = np.nan
            break
        R0[:, :] = R1
        mu0[:] = mu1
        q0[:] = q1
        p0[:] = p1
    return R0, mu0, q0, p0, total, code


@njit(cache=False, parallel=True, error_model="numpy")
def _rollout_batch(R, mu, q, p, h, n_steps, prm):
    B = R.shape[0]
    Ro, muo, qo, po = np.empty_like(R), np.empty_like(mu), np.empty_like(q), np.empty_like(p)
    its = np.zeros(B, np.int64)
    codes = np.zeros(B, np.int64)
    for b in prange(B):
        r, m_, q_, p_, t, c = _rollout(R[b], mu[b], q[b], p[b], h, n_steps, prm)
        Ro[b], muo[b], qo[b], po[b] = r, m_, q_, p_
        its[b] = t
        codes[b] = c
    return Ro, muo, qo, po, its, codes


def _check(method):
    if method not in METHODS:
        raise ValueError(f"numba_lgvi: method must be one of {METHODS}, got {method!r}")


def rollout(method, R, mu, q, p, h, n_steps, params):
    """One trajectory: ``(R, mu, q, p, newton_iterations_total, result_code)``."""
    _check(method)
    if method != "lgvi":
        return _hamel.rollout(method, R, mu, q, p, h, n_steps, params)
    return _rollout(np.asarray(R, np.float64), np.asarray(mu, np.float64),
                    np.asarray(q, np.float64), np.asarray(p, np.float64), float(h),
                    int(n_steps), np.asarray(params, np.float64))


def rollout_batch(method, R, mu, q, p, h, n_steps, params):
    """A batch (leading axis) in parallel over all cores."""
    _check(method)
    if method != "lgvi":
        return _hamel.rollout_batch(method, R, mu, q, p, h, n_steps, params)
    return _rollout_batch(np.ascontiguousarray(R, np.float64),
                          np.ascontiguousarray(mu, np.float64),
                          np.ascontiguousarray(q, np.float64),
                          np.ascontiguousarray(p, np.float64), float(h), int(n_steps),
                          np.asarray(params, np.float64))


def warmup() -> float:
    """Compile everything on a tiny problem; return the seconds it took."""
    start = time.perf_counter()
    prm = np.array([1.0, 1.0, 9.81, 0.25, 0.25, 1.0, 1.1025, -0.0625, -0.25, -0.0625,
                    1.1025, -0.25, -0.25, -0.25, 0.165])
    R = np.eye(3)
    mu, q, p = np.array([0.1, 0.2, 0.3]), np.zeros(2), np.zeros(2)
    # One compilation serves all Hamel methods (the method is a run-time code).
    for name in ("lgvi", "hamel"):
        rollout(name, R, mu, q, p, 1e-3, 2, prm)
        rollout_batch(name, R[None], mu[None], q[None], p[None], 1e-3, 2, prm)
    return time.perf_counter() - start


__all__ = ["METHODS", "numba", "params_from_model", "rollout", "rollout_batch", "warmup"]
