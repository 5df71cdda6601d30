r"""Compiled-loop baselines for the throughput benchmark: the car-pendulum Hamel VIs
(``hamel``, ``hamel-cayley``, ``hamel-exact``) in Numba, from hand-derived discrete
equations. Dispatched by :mod:`numba_lgvi` (``rollout(name, ...)``).

**Discrete Lagrangian** (:class:`lgvi_jax.HamelVI`). One step ``R_{k+1} = R_k F``,
``F = τ(w)`` (``τ = exp`` or Cayley), ``ξ = w/h``, ``q_{k+1} = q_k + h u``; with the
car-pendulum's ``T = ½(m+M)|v|² + ½ωᵀJω + m vᵀPR(ω×ρ_c)`` and ``U = −m g e3ᵀRρ_c``
(``e3`` down),

.. math::
    G = h\Bigl[\tfrac12(m+M)|u|^2 + \tfrac12\xi^\top J\xi
        + \tfrac m2\,u^\top P(R_k + R_{k+1})(\xi\times\rho_c)
        + \tfrac{mg}2 e_3^\top(R_k + R_{k+1})\rho_c\Bigr],

a function of ``R_k, R_{k+1}, w, q_k, q_{k+1}`` (``w`` and ``R_{k+1}`` independent
arguments, as in the engine). Notation: ``ρ = ρ_c``, ``e = w × ρ`` (so ``hξ×ρ = e``),
``a_k = R_kᵀPᵀu``, ``a_{k+1} = R_{k+1}ᵀPᵀu = Fᵀa_k``, ``b_k = R_kᵀe_3``,
``b_{k+1} = R_{k+1}ᵀe_3``.

**Derivatives.** The left-trivialised derivative of ``R ↦ cᵀRd`` is ``d × Rᵀc``
(``cᵀR η̂ d = (Rᵀc)·(η×d)``), so

.. math::
    g_k = \tfrac m2\, e\times a_k + \tfrac h2 mg\,\rho\times b_k, \qquad
    g_{k+1} = \tfrac m2\, e\times a_{k+1} + \tfrac h2 mg\,\rho\times b_{k+1},

    g_w = \partial G/\partial w = J\xi + \tfrac m2\,\rho\times(a_k + a_{k+1}), \qquad
    \partial G/\partial q_{k+1} = -\partial G/\partial q_k = (m+M)u
        + \tfrac m{2h} P(R_k + R_{k+1})e.

**Variations** ``δw = Aη_{k+1} − Bη_k``, in the form ``Bᵀg``, ``Aᵀg`` with ``x = w × g_w``:

* paper (``hamel``: ``τ = exp``; ``hamel-cayley``: ``τ = cay``): ``A = I + ½ŵ``,
  ``B = I − ½ŵ``, so ``Bᵀg_w = g_w + ½x``, ``Aᵀg_w = g_w − ½x``;
* exact (``hamel-exact``, ``τ = exp``): ``A = dexp⁻¹_w = I + ½ŵ + d(θ)ŵ²``,
  ``B = dexp⁻¹_w exp(w)ᵀ = dexp⁻¹_{−w} = I − ½ŵ + dŵ²`` (``J_l = exp(w)J_r``), so
  ``Bᵀg_w = g_w + ½x + d w×x``, ``Aᵀg_w = g_w − ½x + d w×x``, with
  ``d = 1/θ² − cot(θ/2)/(2θ)`` (Taylor ``1/12 + θ²/720 + …`` for ``θ < 0.1``).

**Discrete Legendre transforms** ``μ_k = Bᵀg_w − g_k``, ``p_k = −∂G/∂q_k``,
``μ_{k+1} = g_{k+1} + Aᵀg_w``, ``p_{k+1} = ∂G/∂q_{k+1}``:

.. math::
    p_k = (m+M)u + \tfrac m{2h}PR_k(I + F)e, \qquad
    \mu_k = B^\top g_w - \tfrac m2\,e\times a_k - \tfrac h2 mg\,\rho\times b_k,

    \mu_{k+1} = A^\top g_w + \tfrac m2\,e\times a_{k+1} + \tfrac h2 mg\,\rho\times b_{k+1},
    \qquad p_{k+1} = p_k.

Cross-check with the paper (eqs. 32–35): without the coupling (``m u`` terms dropped,
``g_w = Jξ``) the paper variation gives ``Jω_k = Jξ + (h/2)ξ×Jξ − (h/2)M_k`` and
``Jω_{k+1} = Jξ − (h/2)ξ×Jξ + (h/2)M_{k+1}`` with the gravity moment
``M = mg ρ×Rᵀe_3``: the paper's scheme.

**Reduction to three unknowns.** With ``F = I + c_1ŵ + c_2ŵ²`` (exp: ``c_1 = sinθ/θ``,
``c_2 = (1−cosθ)/θ²``, Taylor branches for ``θ < 0.1`` as in :mod:`lgvi_jax.so3`; Cayley:
``c_1 = 4/(4+θ²)``, ``c_2 = c_1/2``) and ``w·e = 0``: ``(I+F)e = (2 − c_2θ²)e +
c_1 w×e``, so the ``p_k`` equation gives ``u`` explicitly for a given ``w``,
``a_{k+1} = Fᵀa_k = a_k − c_1 w×a_k + c_2(w(w·a_k) − θ²a_k)``, and the ``μ_k`` equation is
three equations in ``w`` only.

**Solver.** The iteration of the JAX engine (``Newton(chord_steps=8)``), on ``w``: the
Jacobian (complex step, one complex residual per unknown, exact to round-off; ``θ² = w·w``
is the analytic continuation and the series/closed-form branch test reads its real part),
inverted by cofactors, is computed at the warm start and reused for up to 8 chord
iterations; it is recomputed at the current iterate when an update fails to halve the
previous one (Newton from then on). Stop when ``|Δw_i| <= 1e-12 (h + |w_i|)`` (the JAX
solver's ``|Δξ_i| <= 1e-12 (1 + |ξ_i|)`` with ``ξ = w/h``; ``u``, explicit in ``w``, is
then as accurate). Newton starts from the extrapolation of the last steps' ``w`` (the
JAX engine's guess, ``lgvi_jax.integrators.lie.predict``). Typically 2 residuals and one
Jacobian per step at h = 5e-3; ``chord_steps=0`` gives plain Newton (a Jacobian per
iteration: about half the speed).
Then ``R_{k+1} = R_kF``, ``q_{k+1} = q_k + hu``, ``p_{k+1} = p_k`` and the ``μ_{k+1}``
formula. Everything in scalars: no allocation inside the step loop. One compiled loop
serves all three methods (the method is a run-time code) and both entry points
(:func:`solver_kernels` builds it for a residual; :mod:`numba_lgvi` reuses it for
``lgvi``, whose residual has the same form); the batch
runs one contiguous chunk per thread (``numba.get_num_threads()``) with the GIL released,
which avoids a second, ``parallel=True`` compilation. Checked against the JAX engine in
``tests/test_numba_baseline.py``.

The same loop runs compositions (a step of sub-steps ``γ_i h``) and, on request, the
sweep's per-step diagnostics (:func:`energy`, :func:`angular_momentum_z`,
:func:`orthogonality_error`, reduced by :func:`metrics_start`/:func:`metrics_update`); both
are run-time arguments, so they cost no second compilation (see :mod:`numba_lgvi`).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
from numba import njit

from lgvi_jax.integrators.lie import PREDICTOR_POINTS

#: method name -> integer code used inside the compiled loops
CODES = {"hamel": 0, "hamel-cayley": 1, "hamel-exact": 2}
METHODS = tuple(CODES)

_TAYLOR_THETA_SQ = 1e-2  # as lgvi_jax.so3: Taylor branches for theta < 0.1
# The Newton guess of a method's own steps, as lgvi_jax.integrators.lie.predict (on w
# alone: the cart velocity is eliminated here): _BINOMIAL_SIGNED[m, i] is the weight of
# the (i+1)-th newest solution in the extrapolation of degree m.
_PREDICTOR_POINTS = PREDICTOR_POINTS
_BINOMIAL_SIGNED = np.array([[(-1) ** i * math.comb(m + 1, i + 1) if i <= m else 0
                              for i in range(PREDICTOR_POINTS)]
                             for m in range(PREDICTOR_POINTS)], dtype=np.float64)


@njit(cache=False, error_model="numpy")
def _coeffs(t2, method):
    """``(c_1, c_2, d)``: ``F = I + c_1ŵ + c_2ŵ²`` and the dexp⁻¹ coefficient ``d``
    (``0`` unless ``method == 2``), for ``t2 = w·w`` (float or complex)."""
    if method == 1:  # Cayley
        k = 4.0 / (4.0 + t2)
        return k, 0.5 * k, 0.0 * t2
    if t2.real < _TAYLOR_THETA_SQ:
        c1 = 1.0 + t2 * (-1.0 / 6 + t2 * (1.0 / 120 + t2 * (-1.0 / 5040 + t2 * (
            1.0 / 362880 + t2 * (-1.0 / 39916800)))))
        c2 = 0.5 + t2 * (-1.0 / 24 + t2 * (1.0 / 720 + t2 * (-1.0 / 40320 + t2 * (
            1.0 / 3628800 + t2 * (-1.0 / 479001600)))))
        if method == 2:
            d = 1.0 / 12 + t2 * (1.0 / 720 + t2 * (1.0 / 30240 + t2 * (
                1.0 / 1209600 + t2 * (1.0 / 47900160))))
        else:
            d = 0.0 * t2
        return c1, c2, d
    t = np.sqrt(t2)
    sh = np.sin(0.5 * t)
    c1 = np.sin(t) / t
    c2 = 2.0 * sh * sh / t2
    if method == 2:
        d = 1.0 / t2 - np.cos(0.5 * t) / (2.0 * t * sh)
    else:
        d = 0.0 * t2
    return c1, c2, d


@njit(cache=False, error_model="numpy", inline="always")
def _cart_coupling(px, py, k, im, R0, g0, g1, g2, w0, w1, w2, c1, c2, t2):
    """The cart's velocity ``u = (p − k P R0 g) / (m + M)`` (``im = 1/(m + M)``; ``g`` the
    method's rotated pivot term), ``a = R0ᵀ Pᵀ u`` and ``b = Fᵀ a = a − c1 w × a + c2 (w (w·a)
    − θ² a)``: shared by the Hamel and LGVI kernels (inlined by Numba into each)."""
    u0 = (px - k * (R0[0, 0] * g0 + R0[0, 1] * g1 + R0[0, 2] * g2)) * im
    u1 = (py - k * (R0[1, 0] * g0 + R0[1, 1] * g1 + R0[1, 2] * g2)) * im
    a0 = R0[0, 0] * u0 + R0[1, 0] * u1
    a1 = R0[0, 1] * u0 + R0[1, 1] * u1
    a2 = R0[0, 2] * u0 + R0[1, 2] * u1
    wa = w0 * a0 + w1 * a1 + w2 * a2
    b0 = a0 - c1 * (w1 * a2 - w2 * a1) + c2 * (w0 * wa - t2 * a0)
    b1 = a1 - c1 * (w2 * a0 - w0 * a2) + c2 * (w1 * wa - t2 * a1)
    b2 = a2 - c1 * (w0 * a1 - w1 * a0) + c2 * (w2 * wa - t2 * a2)
    return u0, u1, a0, a1, a2, b0, b1, b2


@njit(cache=False, error_model="numpy")
def _eval(w0, w1, w2, R0, K0, K1, K2, px, py, h, prm, method):
    """For the increment ``w``: the residual ``μ_k(w) − μ_0`` (``K = μ_0 + (h/2)mg ρ×b_k``),
    ``u``, and what ``μ_{k+1}`` needs without gravity: ``Aᵀg_w + (m/2) e×a_{k+1}``, and
    ``(c_1, c_2)``. Works for float64 and complex128 ``w``."""
    m, M = prm[0], prm[1]
    r0, r1, r2 = prm[3], prm[4], prm[5]
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    c1, c2, d = _coeffs(t2, method)
    # e = w × ρ;  (I + F) e = (2 − c2 θ²) e + c1 w × e   (w · e = 0)
    e0 = w1 * r2 - w2 * r1
    e1 = w2 * r0 - w0 * r2
    e2 = w0 * r1 - w1 * r0
    f0 = w1 * e2 - w2 * e1
    f1 = w2 * e0 - w0 * e2
    f2 = w0 * e1 - w1 * e0
    s = 2.0 - c2 * t2
    g0 = s * e0 + c1 * f0
    g1 = s * e1 + c1 * f1
    g2 = s * e2 + c1 * f2
    # u = (p − (m/2h) P R0 (I + F) e) / (m + M), a_k = R0ᵀ Pᵀ u, a_{k+1} = Fᵀ a_k
    u0, u1, a0, a1, a2, b0, b1, b2 = _cart_coupling(px, py, 0.5 * m / h, 1.0 / (m + M), R0,
                                                    g0, g1, g2, w0, w1, w2, c1, c2, t2)
    # g_w = J w / h + (m/2) ρ × (a_k + a_{k+1})
    ih = 1.0 / h
    hm = 0.5 * m
    S0, S1, S2 = a0 + b0, a1 + b1, a2 + b2
    gw0 = (prm[6] * w0 + prm[7] * w1 + prm[8] * w2) * ih + hm * (r1 * S2 - r2 * S1)
    gw1 = (prm[9] * w0 + prm[10] * w1 + prm[11] * w2) * ih + hm * (r2 * S0 - r0 * S2)
    gw2 = (prm[12] * w0 + prm[13] * w1 + prm[14] * w2) * ih + hm * (r0 * S1 - r1 * S0)
    # x = w × g_w;  Bᵀ g_w = g_w + x/2 (+ d w × x),  Aᵀ g_w = g_w − x/2 (+ d w × x)
    x0 = w1 * gw2 - w2 * gw1
    x1 = w2 * gw0 - w0 * gw2
    x2 = w0 * gw1 - w1 * gw0
    y0 = gw0 + d * (w1 * x2 - w2 * x1)
    y1 = gw1 + d * (w2 * x0 - w0 * x2)
    y2 = gw2 + d * (w0 * x1 - w1 * x0)
    # residual μ_k − μ_0 = Bᵀ g_w − (m/2) e × a_k − (h/2) m g ρ × b_k − μ_0
    res0 = y0 + 0.5 * x0 - hm * (e1 * a2 - e2 * a1) - K0
    res1 = y1 + 0.5 * x1 - hm * (e2 * a0 - e0 * a2) - K1
    res2 = y2 + 0.5 * x2 - hm * (e0 * a1 - e1 * a0) - K2
    # μ_{k+1} without gravity: Aᵀ g_w + (m/2) e × a_{k+1}
    n0 = y0 - 0.5 * x0 + hm * (e1 * b2 - e2 * b1)
    n1 = y1 - 0.5 * x1 + hm * (e2 * b0 - e0 * b2)
    n2 = y2 - 0.5 * x2 + hm * (e0 * b1 - e1 * b0)
    return res0, res1, res2, u0, u1, n0, n1, n2, c1, c2


# ---------------------------------------------------------------------------------------
# Per-step diagnostics: what ``lgvi-jax sweep`` records (lgvi_jax.sweep.batch._sweep_parts)
# ---------------------------------------------------------------------------------------

#: The per-trajectory fields of :func:`metrics_of_states` and of the rollouts with
#: ``metrics=True``, in this order: the sweep's names (``lgvi_jax.sweep``) for the
#: car-pendulum's invariants (energy, cart momentum ``p``, vertical angular momentum).
METRICS = ("energy_error_max", "energy_error_final", "momentum_drift_max",
           "angular_momentum_z_drift_max", "orthogonality_error_max")

# Slots of the running-metrics accumulator (one float64 vector per trajectory).
_H0, _SCALE, _LZ0, _PX0, _PY0, _EMAX, _EFINAL, _PMAX, _LZMAX, _OMAX = range(10)
_ACC = 10


@njit(cache=False, error_model="numpy")
def energy(R, mu, q, p, prm, A, X):
    """``H = ½(μ·ω + p·v) − m g e3ᵀRρ_c`` of :class:`lgvi_jax.CarPendulum` (``energy``: the
    kinetic energy is quadratic in the velocities), with its closed-form inverse Legendre
    map (``velocities``): the 3x3 Schur complement ``J − m²/(m+M) (|ρ|²I − ρρᵀ − ccᵀ)``,
    ``c = ρ × Rᵀe3``, solved by the same pivot-free Gauss–Jordan elimination
    (:func:`lgvi_jax.linalg.spd_solve`), then ``v = (p − m P R(ω × ρ))/(m+M)``. The same
    operations in the same order as the JAX model, so the two differ by rounding only (XLA
    may contract a product and a sum into one fused multiply-add). ``A`` (3, 3) and ``X``
    (3,) are scratch space."""
    m, M, g = prm[0], prm[1], prm[2]
    rho0, rho1, rho2 = prm[3], prm[4], prm[5]
    total = m + M
    r30, r31, r32 = R[2, 0], R[2, 1], R[2, 2]
    c0 = rho1 * r32 - rho2 * r31  # c = ρ × Rᵀe3
    c1 = rho2 * r30 - rho0 * r32
    c2 = rho0 * r31 - rho1 * r30
    rr = rho0 * rho0 + rho1 * rho1 + rho2 * rho2
    k = m * m / total
    cc = (c0, c1, c2)
    for i in range(3):
        for j in range(3):
            A[i, j] = prm[6 + 3 * i + j] - k * (
                (rr if i == j else 0.0) - prm[3 + i] * prm[3 + j] - cc[i] * cc[j])
    a0 = R[0, 0] * p[0] + R[1, 0] * p[1]  # RᵀPᵀp
    a1 = R[0, 1] * p[0] + R[1, 1] * p[1]
    a2 = R[0, 2] * p[0] + R[1, 2] * p[1]
    f = m / total
    X[0] = mu[0] - f * (rho1 * a2 - rho2 * a1)
    X[1] = mu[1] - f * (rho2 * a0 - rho0 * a2)
    X[2] = mu[2] - f * (rho0 * a1 - rho1 * a0)
    # Gauss–Jordan without pivoting (lgvi_jax.linalg._gauss_jordan): for each k, subtract
    # (A[:, k] − e_k) times row k over the pivot.
    for kk in range(3):
        inv = 1.0 / A[kk, kk]
        r0, r1, r2 = A[kk, 0] * inv, A[kk, 1] * inv, A[kk, 2] * inv
        xk = X[kk] * inv
        for i in range(3):
            col = A[i, kk] - (1.0 if i == kk else 0.0)
            A[i, 0] -= col * r0
            A[i, 1] -= col * r1
            A[i, 2] -= col * r2
            X[i] -= col * xk
    w0, w1, w2 = X[0], X[1], X[2]
    e0 = w1 * rho2 - w2 * rho1  # e = ω × ρ
    e1 = w2 * rho0 - w0 * rho2
    e2 = w0 * rho1 - w1 * rho0
    v0 = (p[0] - m * (R[0, 0] * e0 + R[0, 1] * e1 + R[0, 2] * e2)) / total
    v1 = (p[1] - m * (R[1, 0] * e0 + R[1, 1] * e1 + R[1, 2] * e2)) / total
    return 0.5 * (mu[0] * w0 + mu[1] * w1 + mu[2] * w2 + p[0] * v0 + p[1] * v1) - m * g * (
        r30 * rho0 + r31 * rho1 + r32 * rho2)


@njit(cache=False, error_model="numpy")
def angular_momentum_z(R, mu, q, p):
    """``e3·(Rμ) + x p_y − y p_x`` (``CarPendulum.invariants``)."""
    return R[2, 0] * mu[0] + R[2, 1] * mu[1] + R[2, 2] * mu[2] + q[0] * p[1] - q[1] * p[0]


@njit(cache=False, error_model="numpy")
def orthogonality_error(R):
    """``‖RᵀR − I‖_F`` (:func:`lgvi_jax.so3.orthogonality_error`)."""
    sq = 0.0
    for i in range(3):
        for j in range(3):
            e = R[0, i] * R[0, j] + R[1, i] * R[1, j] + R[2, i] * R[2, j] - (
                1.0 if i == j else 0.0)
            sq += e * e
    return np.sqrt(sq)


@njit(cache=False, error_model="numpy")
def _fmax(a, b):
    """``numpy.fmax``: the larger, ignoring a NaN (as the sweep's running maxima)."""
    if a != a or b > a:
        return b
    return a


@njit(cache=False, error_model="numpy")
def metrics_start(acc, R, mu, q, p, prm, A, X):
    """Initialise the accumulator ``acc`` (:data:`_ACC` slots) at the initial state: the
    invariants' initial values, and maxima at NaN (a trajectory that fails at its first
    step records NaN, not 0, as in the sweep)."""
    h0 = energy(R, mu, q, p, prm, A, X)
    acc[_H0] = h0
    acc[_SCALE] = abs(h0) if h0 != 0.0 else 1.0
    acc[_LZ0] = angular_momentum_z(R, mu, q, p)
    acc[_PX0], acc[_PY0] = p[0], p[1]
    for i in (_EMAX, _EFINAL, _PMAX, _LZMAX, _OMAX):
        acc[i] = np.nan


@njit(cache=False, error_model="numpy")
def metrics_update(acc, R, mu, q, p, prm, A, X):
    """After a successful step: the sweep's per-step measures and running maxima."""
    err = abs(energy(R, mu, q, p, prm, A, X) - acc[_H0]) / acc[_SCALE]
    acc[_EMAX] = _fmax(acc[_EMAX], err)
    acc[_EFINAL] = err
    acc[_PMAX] = _fmax(acc[_PMAX], max(abs(p[0] - acc[_PX0]), abs(p[1] - acc[_PY0])))
    acc[_LZMAX] = _fmax(acc[_LZMAX], abs(angular_momentum_z(R, mu, q, p) - acc[_LZ0]))
    acc[_OMAX] = _fmax(acc[_OMAX], orthogonality_error(R))


@njit(cache=False, error_model="numpy")
def _metrics_of_states(R, mu, q, p, prm, out):
    A, X = np.empty((3, 3)), np.empty(3)
    acc = np.empty(_ACC)
    metrics_start(acc, R[0], mu[0], q[0], p[0], prm, A, X)
    for k in range(1, R.shape[0]):
        metrics_update(acc, R[k], mu[k], q[k], p[k], prm, A, X)
    out[0], out[1], out[2], out[3], out[4] = (acc[_EMAX], acc[_EFINAL], acc[_PMAX],
                                              acc[_LZMAX], acc[_OMAX])


def metrics_of_states(R, mu, q, p, params) -> dict[str, float]:
    """The sweep's metrics (:data:`METRICS`) of a given sequence of car-pendulum states
    (leading axis: the initial state, then one per step), computed by the compiled
    diagnostics of the rollouts (for checking them on states of another integrator)."""
    out = np.empty(len(METRICS))
    arrays = [np.ascontiguousarray(np.asarray(x, np.float64)) for x in (R, mu, q, p)]
    _metrics_of_states(*arrays, np.asarray(params, np.float64), out)
    return dict(zip(METRICS, (float(x) for x in out), strict=True))


def solver_kernels(evaluate):
    """The compiled step and rollout loop for the residual ``evaluate`` (the signature and
    return values of :func:`_eval`: ``(res (3), u (2), μ_{k+1} without gravity (3), c_1,
    c_2)`` for ``F = I + c_1ŵ + c_2ŵ²``, float64 or complex128 ``w``): the chord/Newton
    solve, the explicit update and the batch loop are shared by every method whose
    residual is three equations in ``w`` (the Hamel methods here, ``lgvi`` in
    :mod:`numba_lgvi`). Returns ``(inverse_jacobian, step, rollout_range)``; ``evaluate``
    is a compile-time constant of each, so the calls are direct."""

    @njit(cache=False, error_model="numpy")
    def inverse_jacobian(w0, w1, w2, R0, K0, K1, K2, px, py, h, prm, method, Ji):
        """``Ji`` (9, row-major) = the inverse of the residual's Jacobian at ``w``: complex
        step (one complex residual per column, exact to round-off), inverse by cofactors."""
        eps = 1e-30
        z0, z1, z2 = complex(w0, 0.0), complex(w1, 0.0), complex(w2, 0.0)
        c = evaluate(complex(w0, eps), z1, z2, R0, K0, K1, K2, px, py, h, prm, method)
        j00, j10, j20 = c[0].imag / eps, c[1].imag / eps, c[2].imag / eps
        c = evaluate(z0, complex(w1, eps), z2, R0, K0, K1, K2, px, py, h, prm, method)
        j01, j11, j21 = c[0].imag / eps, c[1].imag / eps, c[2].imag / eps
        c = evaluate(z0, z1, complex(w2, eps), R0, K0, K1, K2, px, py, h, prm, method)
        j02, j12, j22 = c[0].imag / eps, c[1].imag / eps, c[2].imag / eps
        k00 = j11 * j22 - j12 * j21
        k01 = j12 * j20 - j10 * j22
        k02 = j10 * j21 - j11 * j20
        idet = 1.0 / (j00 * k00 + j01 * k01 + j02 * k02)
        Ji[0] = idet * k00
        Ji[1] = idet * (j02 * j21 - j01 * j22)
        Ji[2] = idet * (j01 * j12 - j02 * j11)
        Ji[3] = idet * k01
        Ji[4] = idet * (j00 * j22 - j02 * j20)
        Ji[5] = idet * (j02 * j10 - j00 * j12)
        Ji[6] = idet * k02
        Ji[7] = idet * (j01 * j20 - j00 * j21)
        Ji[8] = idet * (j00 * j11 - j01 * j10)


    @njit(cache=False, error_model="numpy")
    def step(R0, mu0, q0, p0, w, h, prm, method, chord_steps, Ji, R1, mu1, q1, p1):
        """One step in place; ``w`` is the warm start and returns the solution. Returns
        (iterations, code).

        The solver of the JAX engine (``Newton(chord_steps=8)``): the Jacobian at the warm
        start serves up to ``chord_steps`` iterations; it is recomputed at the current iterate
        (from then on: Newton) when an update fails to halve the previous one or the chord
        budget is spent. ``chord_steps = 0``: Newton (a fresh Jacobian every iteration)."""
        m, g = prm[0], prm[2]
        r0, r1, r2 = prm[3], prm[4], prm[5]
        hg = 0.5 * h * m * g
        ah = abs(h)  # a composition's sub-steps can be negative
        # K = μ_0 + (h/2) m g ρ × b_k,  b_k = R0ᵀ e3 (third row of R0)
        bx, by, bz = R0[2, 0], R0[2, 1], R0[2, 2]
        K0 = mu0[0] + hg * (r1 * bz - r2 * by)
        K1 = mu0[1] + hg * (r2 * bx - r0 * bz)
        K2 = mu0[2] + hg * (r0 * by - r1 * bx)
        px, py = p0[0], p0[1]
        w0, w1, w2 = w[0], w[1], w[2]
        code = 1
        its = 0
        since = chord_steps + 1  # iterations with the current Jacobian: none yet
        prev = np.inf
        for it in range(20):
            its = it + 1
            f0, f1, f2, _, _, _, _, _, _, _ = evaluate(w0, w1, w2, R0, K0, K1, K2, px, py,
                                                       h, prm, method)
            if since >= chord_steps:
                inverse_jacobian(w0, w1, w2, R0, K0, K1, K2, px, py, h, prm, method, Ji)
                since = 0
            since += 1
            d0 = -(Ji[0] * f0 + Ji[1] * f1 + Ji[2] * f2)
            d1 = -(Ji[3] * f0 + Ji[4] * f1 + Ji[5] * f2)
            d2 = -(Ji[6] * f0 + Ji[7] * f1 + Ji[8] * f2)
            w0 += d0
            w1 += d1
            w2 += d2
            if not (np.isfinite(d0) and np.isfinite(d1) and np.isfinite(d2)):
                code = 2
                break
            size = max(abs(d0) / (ah + abs(w0)), abs(d1) / (ah + abs(w1)),
                       abs(d2) / (ah + abs(w2))) * 1e12
            if size <= 1.0:
                code = 0
                break
            if size > 0.5 * prev:
                since = chord_steps  # not contracting: a fresh Jacobian next iteration
            prev = size
        w[0], w[1], w[2] = w0, w1, w2
        _, _, _, u0, u1, n0, n1, n2, c1, c2 = evaluate(w0, w1, w2, R0, K0, K1, K2, px, py,
                                                       h, prm, method)
        # R1 = R0 F,  F = I + c1 ŵ + c2 (w wᵀ − θ² I)
        t2 = w0 * w0 + w1 * w1 + w2 * w2
        dg = 1.0 - c2 * t2
        F00, F11, F22 = dg + c2 * w0 * w0, dg + c2 * w1 * w1, dg + c2 * w2 * w2
        F01, F10 = c2 * w0 * w1 - c1 * w2, c2 * w0 * w1 + c1 * w2
        F02, F20 = c2 * w0 * w2 + c1 * w1, c2 * w0 * w2 - c1 * w1
        F12, F21 = c2 * w1 * w2 - c1 * w0, c2 * w1 * w2 + c1 * w0
        for i in range(3):
            a, b, cc = R0[i, 0], R0[i, 1], R0[i, 2]
            R1[i, 0] = a * F00 + b * F10 + cc * F20
            R1[i, 1] = a * F01 + b * F11 + cc * F21
            R1[i, 2] = a * F02 + b * F12 + cc * F22
        q1[0] = q0[0] + h * u0
        q1[1] = q0[1] + h * u1
        p1[0] = px
        p1[1] = py
        # μ_{k+1} = Aᵀ g_w + (m/2) e × a_{k+1} + (h/2) m g ρ × b_{k+1}
        bx, by, bz = R1[2, 0], R1[2, 1], R1[2, 2]
        mu1[0] = n0 + hg * (r1 * bz - r2 * by)
        mu1[1] = n1 + hg * (r2 * bx - r0 * bz)
        mu1[2] = n2 + hg * (r0 * by - r1 * bx)
        for i in range(3):
            if not np.isfinite(mu1[i]):
                code = 2
        return its, code

    @njit(cache=False, nogil=True, error_model="numpy")
    def rollout_range(R, mu, q, p, h, n_steps, prm, method, chord_steps, gammas, metrics,
                      lo, hi, its, codes, failed, its_max, out):
        """Trajectories ``lo:hi`` of a batch, in place (``R, mu, q, p`` hold the initial
        states and receive the final ones). Releases the GIL: the batch runs in threads.

        A step is the sub-steps ``γ_1 h, ..., γ_s h`` (``gammas``; ``(1,)`` for the method
        itself, the composition's fractions for ``METHOD@ORDER``), each warm-started from
        the previous sub-step's ``w`` scaled by ``γ_i/γ_{i-1}`` (a method's own steps: from
        the extrapolation of the last solutions, as the JAX engine's ``lie.predict``). Per
        trajectory: Newton iterations in all (``its``), the most in one step (``its_max``),
        the result code, the index of the failed step (-1 if none) and, with ``metrics``, the
        sweep's metrics (:data:`METRICS`, one row of ``out``) measured after every step."""
        R0, mu0, q0, p0 = np.empty((3, 3)), np.empty(3), np.empty(2), np.empty(2)
        R1, mu1, q1, p1 = np.empty((3, 3)), np.empty(3), np.empty(2), np.empty(2)
        w = np.empty(3)
        hist = np.empty((_PREDICTOR_POINTS, 3))  # the last solutions w, newest first
        lin, high = np.empty(3), np.empty(3)
        Ji = np.empty(9)
        A, X = np.empty((3, 3)), np.empty(3)
        acc = np.empty(_ACC)
        J = prm[6:15]
        n_sub = gammas.shape[0]
        ratio = np.empty(n_sub)
        for i in range(n_sub):
            ratio[i] = gammas[i] / gammas[i - 1]  # i = 0: over the last (a step's wrap)
        # First guess w = γ_s h J⁻¹ μ (cofactors; the first sub-step scales it by γ_1/γ_s);
        # then each sub-step warm-starts from the previous one's w.
        k0 = J[4] * J[8] - J[5] * J[7]
        k1 = J[5] * J[6] - J[3] * J[8]
        k2 = J[3] * J[7] - J[4] * J[6]
        s = h * gammas[n_sub - 1] / (J[0] * k0 + J[1] * k1 + J[2] * k2)
        for b in range(lo, hi):
            for i in range(3):
                for j in range(3):
                    R0[i, j] = R[b, i, j]
                mu0[i] = mu[b, i]
            for i in range(2):
                q0[i] = q[b, i]
                p0[i] = p[b, i]
            w[0] = s * (k0 * mu0[0] + (J[2] * J[7] - J[1] * J[8]) * mu0[1]
                        + (J[1] * J[5] - J[2] * J[4]) * mu0[2])
            w[1] = s * (k1 * mu0[0] + (J[0] * J[8] - J[2] * J[6]) * mu0[1]
                        + (J[2] * J[3] - J[0] * J[5]) * mu0[2])
            w[2] = s * (k2 * mu0[0] + (J[1] * J[6] - J[0] * J[7]) * mu0[1]
                        + (J[0] * J[4] - J[1] * J[3]) * mu0[2])
            if metrics:
                metrics_start(acc, R0, mu0, q0, p0, prm, A, X)
            total = 0
            most = 0
            code = 0
            fail = -1
            for i in range(_PREDICTOR_POINTS):
                for j in range(3):
                    hist[i, j] = w[j]
            count = 0
            for k in range(n_steps):
                if n_sub == 1:
                    # the JAX engine's guess (AbstractLieVI.step_with, lie.predict): the
                    # extrapolation of the highest degree the solutions allow, linear where
                    # they do not vary smoothly
                    if k > 0:
                        for i in range(_PREDICTOR_POINTS - 1, 0, -1):
                            for j in range(3):
                                hist[i, j] = hist[i - 1, j]
                        for j in range(3):
                            hist[0, j] = w[j]
                        count = min(count + 1, _PREDICTOR_POINTS)
                    degree = max(2, min(count, _PREDICTOR_POINTS) - 1)
                    step_size, corr = 0.0, 0.0
                    for j in range(3):
                        lin[j] = 2.0 * hist[0, j] - hist[1, j]
                        acc_h = 0.0
                        for i in range(degree + 1):
                            acc_h += _BINOMIAL_SIGNED[degree, i] * hist[i, j]
                        high[j] = acc_h
                        step_size = max(step_size, abs(hist[0, j] - hist[1, j]))
                        corr = max(corr, abs(high[j] - lin[j]))
                    use = count > 2 and corr <= step_size
                    for j in range(3):
                        w[j] = high[j] if use else lin[j]
                n_its = 0
                for i in range(n_sub):
                    for j in range(3):
                        w[j] *= ratio[i]
                    sub_its, c = step(R0, mu0, q0, p0, w, h * gammas[i], prm, method,
                                      chord_steps, Ji, R1, mu1, q1, p1)
                    n_its += sub_its
                    if c != 0:
                        code = c
                        break
                    R0, R1 = R1, R0
                    mu0, mu1 = mu1, mu0
                    q0, q1 = q1, q0
                    p0, p1 = p1, p0
                total += n_its
                most = max(most, n_its)
                if code != 0:
                    fail = k
                    for i in range(3):
                        mu0[i] = np.nan
                    break
                if metrics:
                    metrics_update(acc, R0, mu0, q0, p0, prm, A, X)
            for i in range(3):
                for j in range(3):
                    R[b, i, j] = R0[i, j]
                mu[b, i] = mu0[i]
            for i in range(2):
                q[b, i] = q0[i]
                p[b, i] = p0[i]
            its[b] = total
            its_max[b] = most
            codes[b] = code
            failed[b] = fail
            if metrics:
                out[b, 0] = acc[_EMAX]
                out[b, 1] = acc[_EFINAL] if code == 0 else np.nan
                out[b, 2] = acc[_PMAX]
                out[b, 3] = acc[_LZMAX]
                out[b, 4] = acc[_OMAX]

    return inverse_jacobian, step, rollout_range


_inverse_jacobian, _step, _rollout_range = solver_kernels(_eval)


#: chord iterations per Jacobian, as the JAX engine's default ``Newton(chord_steps=8)``
CHORD_STEPS = 8


def _prepare(R, mu, q, p, batch):
    arrays = [np.array(x, np.float64, order="C", copy=True) for x in (R, mu, q, p)]
    if not batch:
        arrays = [x[None] for x in arrays]
    n = arrays[0].shape[0]
    return arrays, np.zeros(n, np.int64), np.zeros(n, np.int64)


def run_kernel(rollout_range, method, R, mu, q, p, h, n_steps, params, chord_steps,
               batch, *, gammas=(1.0,), metrics=False, threads=None):
    """Run a ``rollout_range`` of :func:`solver_kernels` with the integer ``method``: one
    trajectory (``batch=False``) or a batch (leading axis) in parallel over ``threads``
    threads (default ``numba.get_num_threads()``; the compiled loop releases the GIL; one
    contiguous chunk per thread). ``gammas``: the sub-steps of a composition (default: the
    method itself). Returns ``(R, mu, q, p, iterations, codes)``, the last two of shape
    ``(B,)`` (``(1,)`` for one trajectory, with a leading axis on the states); with
    ``metrics=True`` also a dict of the sweep's per-trajectory fields (arrays ``(B,)``:
    :data:`METRICS`, ``newton_mean``, ``newton_max``, ``result``, ``failed_step``),
    measured after every step."""
    (R, mu, q, p), its, codes = _prepare(R, mu, q, p, batch)
    B = R.shape[0]
    failed = np.full(B, -1, np.int64)
    its_max = np.zeros(B, np.int64)
    out = np.full((B, len(METRICS)), np.nan)
    n_threads = max(1, min(threads or numba.get_num_threads(), B))
    bounds = [B * i // n_threads for i in range(n_threads + 1)]
    args = (float(h), int(n_steps), np.asarray(params, np.float64), int(method),
            int(chord_steps), np.asarray(gammas, np.float64), bool(metrics))

    def run(i):
        rollout_range(R, mu, q, p, *args, bounds[i], bounds[i + 1], its, codes, failed,
                      its_max, out)

    if n_threads == 1:
        run(0)
    else:
        with ThreadPoolExecutor(n_threads) as pool:
            list(pool.map(run, range(n_threads)))
    if not metrics:
        return R, mu, q, p, its, codes
    fields = {name: out[:, i] for i, name in enumerate(METRICS)}
    done = np.where(failed >= 0, failed + 1, int(n_steps))
    fields.update(newton_mean=its / np.maximum(done, 1), newton_max=its_max,
                  result=codes.copy(), failed_step=failed)
    return R, mu, q, p, its, codes, fields


def rollout(method, R, mu, q, p, h, n_steps, params, chord_steps=CHORD_STEPS):
    """One trajectory: ``(R, mu, q, p, newton_iterations_total, result_code)``."""
    R, mu, q, p, its, codes = run_kernel(_rollout_range, CODES[method], R, mu, q, p, h,
                                         n_steps, params, chord_steps, False)
    return R[0], mu[0], q[0], p[0], int(its[0]), int(codes[0])


def rollout_batch(method, R, mu, q, p, h, n_steps, params, chord_steps=CHORD_STEPS):
    """A batch (leading axis) in parallel over ``numba.get_num_threads()`` threads (the
    compiled loop releases the GIL; one contiguous chunk per thread). Returns
    ``(R, mu, q, p, iterations (B,), codes (B,))``."""
    return run_kernel(_rollout_range, CODES[method], R, mu, q, p, h, n_steps, params,
                      chord_steps, True)


__all__ = ["CHORD_STEPS", "CODES", "METHODS", "METRICS", "angular_momentum_z", "energy",
           "metrics_of_states", "metrics_start", "metrics_update", "orthogonality_error",
           "rollout", "rollout_batch", "run_kernel", "solver_kernels"]
