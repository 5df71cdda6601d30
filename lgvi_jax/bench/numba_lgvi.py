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

**In scalars.** ``F = cay(w) = I + c_1ŵ + c_2ŵ²`` with ``c_1 = 4/(4+θ²)``, ``c_2 = c_1/2``,
``θ² = w·w``. For symmetric ``A``: ``(ŵA + Aŵ)^∨ = (tr A·I − A)w`` and ``(ŵ²A − Aŵ²)^∨ =
(Aw)×w``; with ``J_d = ½tr(J)I − J`` (so ``tr J_d·I − J_d = J`` and ``J_dw×w = w×Jw``)

.. math::
    (FJ_d - J_dF^\top)^\vee = c_1Jw + c_2\,w\times Jw, \qquad
    (J_dF - F^\top J_d)^\vee = c_1Jw - c_2\,w\times Jw,

``(F − I)ρ_c = c_1 e + c_2 w×e`` with ``e = w×ρ_c``, and ``Fᵀa = a − c_1 w×a + c_2(w(w·a) −
θ²a)``. The ``p_k`` equation gives ``u`` explicitly for a given ``w``, leaving the
``μ_k`` equation: three equations in ``w`` only.

**Solver and loop**: those of the Hamel baselines (:func:`numba_hamel.solver_kernels`),
with this residual: the iteration of the JAX engine (``Newton(chord_steps=8)``: a
complex-step Jacobian at the warm start, the previous step's ``w``, inverted by cofactors
and reused for up to 8 chord iterations, recomputed when an update fails to halve the
previous one), stopping when ``|Δw_i| <= 1e-12 (h + |w_i|)`` (the JAX solver's tolerance on
``ξ = w/h``); everything in scalars, no allocation in the step loop; the batch runs one
contiguous chunk per thread with the GIL released.

The Hamel methods (``hamel``, ``hamel-cayley``, ``hamel-exact``) are in
:mod:`numba_hamel` (their own derivation), dispatched by ``rollout``/``rollout_batch``
below with the same parameters and return values.

**Compositions** (``lgvi@4``, ``hamel-cayley@6``, ...): the sub-steps ``γ_i h`` of
:func:`lgvi_jax.integrators.resolve_method` in the same compiled loop, each Newton solve
warm-started from the previous sub-step's ``w`` scaled by ``γ_i/γ_{i-1}`` (its stopping
test uses ``|γ_i h|``: sub-steps can be negative).

**Per-step diagnostics** (:func:`sweep_metrics`, what ``lgvi-jax bench`` times): after every
step the compiled loop measures what ``lgvi-jax sweep`` records (``lgvi_jax.sweep``): the
relative energy error ``|H − H0|/|H0|`` with the car-pendulum's energy written in Numba
(:func:`numba_hamel.energy`: the model's closed-form inverse Legendre map, the same
operations as :meth:`lgvi_jax.CarPendulum.energy`), the drifts of the cart momentum and of
the vertical angular momentum, the orthogonality error ``‖RᵀR − I‖_F``, and the Newton
iterations, reduced to running maxima and final values with the sweep's semantics (a
failed trajectory stops, its final value is NaN, its maxima cover the steps before the
failure). Checked against the sweep's metrics in ``tests/test_numba_baseline.py``.
"""

from __future__ import annotations

import time

import numba
import numpy as np
from numba import njit

from lgvi_jax.bench import numba_hamel as _hamel

METHODS = ("lgvi", *_hamel.METHODS)
METRICS = _hamel.METRICS
metrics_of_states = _hamel.metrics_of_states


def params_from_model(model) -> np.ndarray:
    """``(m, M, g, rho_c (3), J (9))`` as one float64 vector."""
    return np.concatenate([
        np.atleast_1d(np.asarray(model.m, np.float64)),
        np.atleast_1d(np.asarray(model.M, np.float64)),
        np.atleast_1d(np.asarray(model.g, np.float64)),
        np.asarray(model.rho_c, np.float64), np.asarray(model.J, np.float64).ravel()])


@njit(cache=False, error_model="numpy")
def _eval(w0, w1, w2, R0, K0, K1, K2, px, py, h, prm, method):
    """For the increment ``w``: the residual ``μ_k(w) − μ_0`` (``K = μ_0 + (h/2)mg ρ×b_k``),
    ``u``, ``μ_{k+1}`` without gravity (``(c_1Jw − c_2 w×Jw)/h + m ρ×Fᵀa``) and ``(c_1,
    c_2)``: the interface of :func:`numba_hamel._eval` (``method`` is unused). Works for
    float64 and complex128 ``w``."""
    m, M = prm[0], prm[1]
    r0, r1, r2 = prm[3], prm[4], prm[5]
    t2 = w0 * w0 + w1 * w1 + w2 * w2
    c1 = 4.0 / (4.0 + t2)
    c2 = 0.5 * c1
    # (F − I) ρ = c1 e + c2 w × e,  e = w × ρ
    e0 = w1 * r2 - w2 * r1
    e1 = w2 * r0 - w0 * r2
    e2 = w0 * r1 - w1 * r0
    g0 = c1 * e0 + c2 * (w1 * e2 - w2 * e1)
    g1 = c1 * e1 + c2 * (w2 * e0 - w0 * e2)
    g2 = c1 * e2 + c2 * (w0 * e1 - w1 * e0)
    # u = (p − (m/h) P R0 (F − I) ρ) / (m + M), a = R0ᵀ Pᵀ u, Fᵀ a
    u0, u1, a0, a1, a2, b0, b1, b2 = _hamel._cart_coupling(
        px, py, m / h, 1.0 / (m + M), R0, g0, g1, g2, w0, w1, w2, c1, c2, t2)
    # v = J w / h,  x = w × v:  (F J_d − J_d Fᵀ)^∨ / h = c1 v + c2 x,  (J_d F − Fᵀ J_d)^∨ / h
    # = c1 v − c2 x
    ih = 1.0 / h
    v0 = (prm[6] * w0 + prm[7] * w1 + prm[8] * w2) * ih
    v1 = (prm[9] * w0 + prm[10] * w1 + prm[11] * w2) * ih
    v2 = (prm[12] * w0 + prm[13] * w1 + prm[14] * w2) * ih
    x0 = c2 * (w1 * v2 - w2 * v1)
    x1 = c2 * (w2 * v0 - w0 * v2)
    x2 = c2 * (w0 * v1 - w1 * v0)
    y0, y1, y2 = c1 * v0, c1 * v1, c1 * v2
    # residual μ_k − μ_0 = c1 v + c2 x + m ρ × a − (h/2) m g ρ × b_k − μ_0
    res0 = y0 + x0 + m * (r1 * a2 - r2 * a1) - K0
    res1 = y1 + x1 + m * (r2 * a0 - r0 * a2) - K1
    res2 = y2 + x2 + m * (r0 * a1 - r1 * a0) - K2
    # μ_{k+1} without gravity: c1 v − c2 x + m ρ × Fᵀ a
    n0 = y0 - x0 + m * (r1 * b2 - r2 * b1)
    n1 = y1 - x1 + m * (r2 * b0 - r0 * b2)
    n2 = y2 - x2 + m * (r0 * b1 - r1 * b0)
    return res0, res1, res2, u0, u1, n0, n1, n2, c1, c2


_inverse_jacobian, _step, _rollout_range = _hamel.solver_kernels(_eval)


def _resolve(method):
    """``(rollout_range, integer code, gammas)`` of a method name: a base method of
    :data:`METHODS`, or its composition ``METHOD@ORDER`` / ``METHOD@SCHEME`` with the
    sub-steps of :func:`lgvi_jax.integrators.resolve_method` (``lgvi@4``: Suzuki's five)."""
    from lgvi_jax.integrators import RIGID_METHODS, parse_method, resolve_method

    try:
        base, spec = parse_method(method)
    except ValueError:
        base, spec = None, None
    if base not in METHODS:
        raise ValueError(f"numba_lgvi: method must be one of {METHODS} (each also as "
                         f"METHOD@ORDER, e.g. lgvi@4), got {method!r}")
    gammas = (1.0,) if spec is None else resolve_method(method, RIGID_METHODS).gammas
    if base == "lgvi":
        return _rollout_range, 0, gammas
    return _hamel._rollout_range, _hamel.CODES[base], gammas


def _run(method, R, mu, q, p, h, n_steps, params, chord_steps, batch, **kwargs):
    kernel, code, gammas = _resolve(method)
    return _hamel.run_kernel(kernel, code, R, mu, q, p, h, n_steps, params, chord_steps,
                             batch, gammas=gammas, **kwargs)


def rollout(method, R, mu, q, p, h, n_steps, params, chord_steps=_hamel.CHORD_STEPS):
    """One trajectory: ``(R, mu, q, p, newton_iterations_total, result_code)``. ``method``:
    ``lgvi``, a Hamel method, or a composition of one (``lgvi@4``)."""
    R, mu, q, p, its, codes = _run(method, R, mu, q, p, h, n_steps, params, chord_steps,
                                   False)
    return R[0], mu[0], q[0], p[0], int(its[0]), int(codes[0])


def rollout_batch(method, R, mu, q, p, h, n_steps, params, chord_steps=_hamel.CHORD_STEPS):
    """A batch (leading axis) in parallel over ``numba.get_num_threads()`` threads:
    ``(R, mu, q, p, iterations (B,), codes (B,))``."""
    return _run(method, R, mu, q, p, h, n_steps, params, chord_steps, True)


def sweep_metrics(method, R, mu, q, p, h, n_steps, params, *,
                  chord_steps=_hamel.CHORD_STEPS, threads=None):
    """A batch (leading axis) with the per-step diagnostics of ``lgvi-jax sweep``: after
    every step the relative energy error, the drifts of the cart momentum and of the
    vertical angular momentum and the orthogonality error, reduced as the sweep reduces
    them. Returns ``(fields, (R, mu, q, p))``: ``fields`` the sweep's per-trajectory
    arrays (``energy_error_max``, ``energy_error_final``, ``momentum_drift_max``,
    ``angular_momentum_z_drift_max``, ``orthogonality_error_max``, ``newton_mean``,
    ``newton_max``, ``result``, ``failed_step``), the final states after them. ``threads``:
    default ``numba.get_num_threads()`` (1 for one trajectory on one core)."""
    R, mu, q, p, _, _, fields = _run(method, R, mu, q, p, h, n_steps, params, chord_steps,
                                     True, metrics=True, threads=threads)
    return fields, (R, mu, q, p)


def warmup(methods=("lgvi", "hamel")) -> float:
    """Compile the loops of ``methods`` on a tiny problem (all Hamel methods share one:
    the default compiles everything); return the seconds it took."""
    start = time.perf_counter()
    prm = np.array([1.0, 1.0, 9.81, 0.25, 0.25, 1.0, 1.1025, -0.0625, -0.25, -0.0625,
                    1.1025, -0.25, -0.25, -0.25, 0.165])
    R = np.eye(3)
    mu, q, p = np.array([0.1, 0.2, 0.3]), np.zeros(2), np.zeros(2)
    # One compiled loop per residual: ``lgvi``, and all Hamel methods (the method is a
    # run-time code); ``rollout`` and ``rollout_batch`` share it.
    for name in methods:
        rollout(name, R, mu, q, p, 1e-3, 2, prm)
    return time.perf_counter() - start


__all__ = ["METHODS", "METRICS", "metrics_of_states", "numba", "params_from_model", "rollout",
           "rollout_batch", "sweep_metrics", "warmup"]
