r"""Lie group variational integrators on :math:`SO(3) \times \mathbb{R}^n`, built from a
discrete Lagrangian by autodiff.

One engine serves every method. A method supplies

* a map :math:`\tau: \mathbb{R}^3 \to SO(3)` (``exp`` or Cayley) with
  :math:`R_{k+1} = R_k\,\tau(w)`;
* a discrete Lagrangian :math:`G(R_k, R_{k+1}, w, q_k, q_{k+1})` built from the model's
  ``kinetic`` and ``potential`` (``w`` enters only for Hamel methods, as the midpoint
  velocity :math:`\xi = w/h`);
* the variation of ``w`` induced by :math:`\delta R_k = R_k\hat\eta_k`,
  :math:`\delta R_{k+1} = R_{k+1}\hat\eta_{k+1}`:
  :math:`\delta w = A(w)\,\eta_{k+1} - B(w)\,\eta_k`.

Writing :math:`g_k, g_{k+1}` for the left-trivialised derivatives of ``G`` in its explicit
rotation arguments (:func:`~lgvi_jax.models.rigid.left_gradient`) and
:math:`g_w = \partial G/\partial w`, the discrete Legendre transforms
(:math:`\mu_k = -D_1L_d`, :math:`\mu_{k+1} = D_2L_d`, left-trivialised) are

.. math::
    \mu_k = B^\top g_w - g_k, \quad p_k = -\partial G/\partial q_k, \qquad
    \mu_{k+1} = g_{k+1} + A^\top g_w, \quad p_{k+1} = \partial G/\partial q_{k+1}.

One step solves the first pair for the unknown velocities :math:`(\xi, u) = (w/h,
(q_{k+1} - q_k)/h)` by Newton's method (autodiff Jacobian, initial guess the current
velocities) and then evaluates the second pair explicitly. All derivatives come from JAX
autodiff; the hand-derived equations of the paper (eqs. 18–21, 32–35) are test oracles only.

Methods (all second order and symmetric):

``lgvi``  the general-form LGVI of Lee, Leok and McClamroch (2005, 2007):
    :math:`L_d = h[T(R_k, (F-I)/h, q_k, \Delta q/h) - \tfrac12U_k - \tfrac12U_{k+1}]`,
    :math:`F = R_k^\top R_{k+1}`; ``w`` is only the Newton parametrisation of ``F``
    (Cayley). Exactly variational: symplectic, momentum maps conserved.
``hamel-exact``  the Hamel VI with :math:`\tau = \exp` and exact variations
    :math:`A = \mathrm{dexp}^{-1}_w`, :math:`B = \mathrm{dexp}^{-1}_w \exp(w)^\top`:
    exactly variational.
``hamel``  the paper's Hamel VI: ``exp`` with the paper's variation formula (eq. 29)
    :math:`\delta\xi = (\eta_{k+1} - \eta_k)/h + \xi\times(\eta_k + \eta_{k+1})/2`, i.e.
    :math:`A = I + \tfrac12\hat w`, :math:`B = I - \tfrac12\hat w`. This agrees with the
    exact variation only to first order in ``w``: the scheme is not exactly variational and
    its momentum maps are conserved only to :math:`O(h^2)` (measured in the tests).
``hamel-cayley``  the same variation formula with the Cayley map. Since
    :math:`\mathrm{cay}(w)(I - \tfrac12\hat w) = I + \tfrac12\hat w`, the formula has the
    form :math:`\delta w = A(\eta_{k+1} - F^\top\eta_k)`, which vanishes along symmetry
    directions: momentum maps are conserved exactly (discrete Noether).

Hamel discrete Lagrangian: :math:`G = h[\tfrac12T(R_k, \hat\xi, q_k, u) +
\tfrac12T(R_{k+1}, \hat\xi, q_{k+1}, u) - \tfrac12U_k - \tfrac12U_{k+1}]`, the kinetic
energy at the midpoint velocity with configuration-dependent terms averaged over both ends
(for a free body this is the paper's :math:`\tfrac12\xi^\top J\xi + \tfrac m2|u|^2`).

References: J. E. Marsden, M. West, *Discrete mechanics and variational integrators*, Acta
Numerica (2001); T. Lee, M. Leok, N. H. McClamroch, *Lie group variational integrators for
the full body problem*, CMAME 196 (2007); the source paper, sections 2.2–2.3.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from .. import so3
from ..linalg import ldl_solve, spd_inverse
from ..models.rigid import AbstractRigidBodyModel, RigidState
from ..newton import ChordInverse, Newton, newton_solve
from ..options import ChordMatrix, HamelMap, JacobianMode, Variation
from ..scalarize import scalarize
from .base import AbstractIntegrator, StepInfo

__all__ = ["LGVI", "AbstractLieVI", "HamelVI"]


def _vee_AtB(A, B):
    """``2 vee(AᵀB) = −Σ_l a_l × b_l`` over the rows ``a_l, b_l`` (a few fused vector
    operations instead of a matrix product, a transpose and a read of its skew part)."""
    return -jnp.sum(jnp.cross(A, B), axis=-2)


def _vee_ABt(A, B):
    """``2 vee(ABᵀ) = −Σ_l a^l × b^l`` over the columns ``a^l, b^l``."""
    return -jnp.sum(jnp.cross(A, B, axisa=-2, axisb=-2), axis=-2)


#: Past solutions the Newton guess of a rollout's step is extrapolated from (:func:`predict`).
PREDICTOR_POINTS = 5


def _max_abs(tree):
    return functools.reduce(jnp.maximum, [jnp.max(jnp.abs(x), initial=0.0)
                                          for x in jax.tree.leaves(tree)])


def _extrapolate(history, degree: int):
    """The value at the next point of the polynomial of ``degree`` through the equally
    spaced ``history[:degree + 1]`` (newest first): ``Σ_j (−1)^{j+1} C(degree+1, j) s_j``."""
    coeffs = [(-1) ** j * math.comb(degree + 1, j + 1) for j in range(degree + 1)]
    return jax.tree.map(lambda *s: sum(c * x for c, x in zip(coeffs, s, strict=True)),
                        *history[:degree + 1])


def predict(history, count):
    """The Newton guess of a step from the last solutions ``history = (s_1, ..., s_P)``
    (pytrees, newest first; ``P =`` :data:`PREDICTOR_POINTS`), of which ``count`` are
    solutions (the rest: the start's velocities): the extrapolation of the highest degree
    (at most ``P − 1``, error O(h^P)) through the solutions there are, linear
    ``2 s_1 − s_2`` (O(h²)) with two or fewer. A degree above one is taken only where the
    solutions vary smoothly: where its correction to the linear guess is smaller than the
    last change ``s_1 − s_2`` (at steps comparable to the motion's time scale a polynomial
    extrapolation can be worse than a linear one). A guess from past solutions as the
    predictor of BDF codes (Brenan, Campbell & Petzold, *Numerical Solution of
    Initial-Value Problems in DAEs*, SIAM 1996, ch. 5); the solution does not depend on
    it, only the iterations do."""
    linear = _extrapolate(history, 1)
    high = _extrapolate(history, 2)
    for degree in range(3, len(history)):
        high = jax.tree.map(lambda a, b, d=degree: jnp.where(count > d, a, b),
                            _extrapolate(history, degree), high)
    step = _max_abs(jax.tree.map(jnp.subtract, history[0], history[1]))
    smooth = _max_abs(jax.tree.map(jnp.subtract, high, linear)) <= step
    use = (count > 2) & smooth
    return jax.tree.map(lambda a, b: jnp.where(use, a, b), high, linear)


def unresolved(history, count):
    """Whether the last solutions change by as much as they vary from step to step
    (``‖s_1 − 2 s_2 + s_3‖ > ‖s_1 − s_2‖ / 2``, three solutions needed): a step too large
    for the motion, where any extrapolation is a worse Newton guess than the current
    velocities (car-pendulum ``lgvi`` at h = 0.13: the linear guess 2–7 off the solution,
    the velocities 1–3, and Newton from the first fails)."""
    s1, s2, s3 = history[:3]
    first = _max_abs(jax.tree.map(jnp.subtract, s1, s2))
    second = _max_abs(jax.tree.map(lambda a, b, c: a - 2 * b + c, s1, s2, s3))
    return (count > 2) & (second > 0.5 * first)


def where_any(pred, compute: Callable, otherwise, operands):
    """``where(pred, compute(*operands), otherwise)``, with ``compute`` evaluated only where
    it is needed: on one trajectory a ``lax.cond``; under ``vmap`` (where a ``cond`` would
    become a ``select`` of both branches) for the whole batch, and only when ``pred`` holds
    for any of its members. For values that are not differentiated (a Newton guess):
    ``pred``, ``otherwise`` and ``operands`` are arrays (pytrees of them) taken under
    ``stop_gradient``."""
    pred, otherwise, operands = jax.lax.stop_gradient((pred, otherwise, operands))

    @jax.custom_batching.custom_vmap
    def pick(pred, otherwise, operands):
        return jax.lax.cond(pred, lambda: compute(*operands), lambda: otherwise)

    @pick.def_vmap
    def _pick_batched(axis_size, in_batched, pred, otherwise, operands):
        pred_b, otherwise_b, operands_b = in_batched
        axes = jax.tree.map(lambda b: 0 if b else None, operands_b)
        pred = pred if pred_b else jnp.broadcast_to(pred, (axis_size,))
        otherwise = jax.tree.map(
            lambda x, b: x if b else jnp.broadcast_to(x, (axis_size, *jnp.shape(x))),
            otherwise, otherwise_b)

        def computed():
            new = jax.vmap(lambda ops: compute(*ops), in_axes=(axes,),
                           axis_size=axis_size)(operands)
            return jax.tree.map(
                lambda a, b: jnp.where(pred.reshape((-1,) + (1,) * (a.ndim - 1)), a, b),
                new, otherwise)

        out = jax.lax.cond(jnp.any(pred), computed, lambda: otherwise)
        return out, jax.tree.map(lambda _: True, out)

    return pick(pred, otherwise, operands)


class AbstractLieVI(AbstractIntegrator):
    """The discrete-Lagrangian engine; subclasses define the map, the discrete Lagrangian
    and the variation matrices."""

    #: The solver. Chord iterations first, full Newton from the initial guess as the
    #: fallback: the same solutions and robustness as Newton at about half the cost;
    #: ``Newton()`` gives plain Newton. On scalars (``scalar=True``, :mod:`lgvi_jax.scalarize`:
    #: the same iterates as on arrays to the order of floating-point sums, several times
    #: faster at a similar compile time, docs/engine.md); ``Newton(chord_steps=8)`` (or
    #: :func:`~lgvi_jax.integrators.with_scalar_newton` with ``scalar=False``) solves on
    #: small arrays, which the other solver settings need (``chord``, ``broyden``,
    #: ``unroll``, the unrolled adjoint, the mass chord matrix).
    newton: Newton = Newton(chord_steps=8, scalar=True)
    #: The chord matrix, a :class:`~lgvi_jax.options.ChordMatrix` (or its string).
    #: ``"exact"`` (default): the Jacobian at the initial guess
    #: (forward-over-reverse, ~7 residuals' cost). ``"mass"``: the continuous Legendre map's
    #: matrix ∂(μ, p)/∂(ω, v) at the current configuration, which costs no derivative of G
    #: (the discrete Legendre map's Jacobian in the velocity unknowns is this matrix +
    #: O(h)), improved after every iteration by Broyden's update (``Newton.broyden``): more
    #: but cheaper iterations (up to ``max(newton.chord_steps, 20)`` before the Newton
    #: fallback). The same solutions to round-off; faster batched (``lgvi-jax bench``,
    #: ``docs/which-method.md``).
    chord_matrix: ChordMatrix = eqx.field(static=True, default=ChordMatrix.EXACT,
                                          converter=ChordMatrix.coerce)

    def __check_init__(self):
        ChordMatrix.parse(self.chord_matrix, type(self).__name__, "chord_matrix")

    @property
    def on_scalars(self) -> bool:
        """Whether the steps are solved on scalars: ``Newton(scalar=True)`` with the exact
        chord matrix (any other chord matrix runs on arrays)."""
        return self.newton.scalar and self.chord_matrix == ChordMatrix.EXACT

    order: ClassVar[int] = 2
    symmetric: ClassVar[bool] = True
    implicit: ClassVar[bool] = True
    #: The autodiff mode of the Jacobian program on scalars (``Newton.scalar_jacobian``,
    #: where it is ``"auto"``): the smaller one, measured for every model (free body,
    #: heavy top, car-pendulum) and variant (docs/engine.md); naming it saves tracing the
    #: other at every compilation. ``"auto"``: trace both, keep the smaller.
    jacobian_mode: ClassVar[JacobianMode] = JacobianMode.AUTO

    # --- the method ---------------------------------------------------------------------
    def tau_minus_identity(self, w: jax.Array) -> jax.Array:
        """``τ(w) − I`` for the map ``w -> F = R_kᵀ R_{k+1}`` (without cancellation)."""
        raise NotImplementedError

    def discrete_lagrangian(self, model, h, R0, R1, FmI, w, q0, q1, u) -> jax.Array:
        """``G`` for step ``h``. The arguments describe one step redundantly, so that no
        method has to recompute a small difference of large numbers: rotations ``R0, R1``,
        ``FmI = R0ᵀR1 − I``, the Hamel coordinate ``w``, positions ``q0, q1`` and the mean
        velocity ``u = (q1 − q0)/h``."""
        raise NotImplementedError

    def variations(self, w: jax.Array) -> tuple[jax.Array, jax.Array]:
        """``(A, B)`` with ``δw = A η_{k+1} − B η_k``; unused if ``G`` does not depend on
        ``w``."""
        raise NotImplementedError

    def guess_from_velocities(self, velocities):
        """The Newton unknowns of a step at which the motion keeps the velocities
        ``(ω, v)``: the initial guess from the current velocities. The unknowns are the
        velocities ``(ξ, u)`` themselves (the identity); methods with more unknowns per step
        (:class:`~lgvi_jax.integrators.lie_galerkin.LieGalerkinVI`) extend them."""
        return velocities

    def tau(self, w: jax.Array) -> jax.Array:
        """The map ``w -> F = R_kᵀ R_{k+1}``."""
        return jnp.eye(3, dtype=w.dtype) + self.tau_minus_identity(w)

    # --- the engine ---------------------------------------------------------------------
    def check_model(self, model) -> None:
        if not isinstance(model, AbstractRigidBodyModel):
            raise ValueError(
                f"{self.name}: needs a model on SO(3) x R^n (AbstractRigidBodyModel), got "
                f"{type(model).__name__}; Euclidean models use rk4, gl4, verlet, galerkin4"
            )

    def gradients(self, model, R0, w, q0, u, h):
        """Derivatives of ``G`` for the step ``R1 = R0 τ(w)``, ``q1 = q0 + h u``:
        ``(g_k, g_{k+1}, ∂G/∂q_k, ∂G/∂q_{k+1}, g_w)``, the rotation derivatives
        left-trivialised, each taken with the other end point held fixed.

        One reverse pass gives the Euclidean gradients of ``G`` in its redundant arguments
        (``R0, R1, F − I, q0, q1, u, w``, treated as independent); the perturbations
        ``R0 → R0(I + η̂0)``, ``R1 → R1(I + η̂1)`` move them consistently to first order
        (``F − I → F − I − η̂0 F + F η̂1``, ``u → u + (d1 − d0)/h``). With
        ``⟨A, η̂⟩ = 2 vee(A)·η`` (vee reads the skew part):

        ``g_k = 2 vee(R0ᵀ ∂G/∂R0 − ∂G/∂F Fᵀ)``, ``g_{k+1} = 2 vee(R1ᵀ ∂G/∂R1 + Fᵀ ∂G/∂F)``,
        ``∂G/∂q_k = ∂G/∂q0 − (∂G/∂u)/h``, ``∂G/∂q_{k+1} = ∂G/∂q1 + (∂G/∂u)/h``.
        """
        FmI = self.tau_minus_identity(w)
        F = jnp.eye(3, dtype=R0.dtype) + FmI
        R1 = R0 @ F
        q1 = q0 + h * u

        def G(R0, R1, FmI, q0, q1, u, w):
            return self.discrete_lagrangian(model, h, R0, R1, FmI, w, q0, q1, u)

        dR0, dR1, dF, dq0, dq1, du, gw = jax.grad(G, argnums=(0, 1, 2, 3, 4, 5, 6))(
            R0, R1, FmI, q0, q1, u, w
        )
        g0 = _vee_AtB(R0, dR0) - _vee_ABt(dF, F)
        g1 = _vee_AtB(R1, dR1) + _vee_AtB(F, dF)
        return g0, g1, dq0 - du / h, dq1 + du / h, gw

    def legendre(self, model, R0, w, q0, u, h):
        """Both discrete Legendre transforms ``(μ_k, p_k, μ_{k+1}, p_{k+1})`` of the step
        ``(R_k, q_k) -> (R_k τ(w), q_k + h u)``."""
        g0, g1, gq0, gq1, gw = self.gradients(model, R0, w, q0, u, h)
        A, B = self.variations(w)
        return B.T @ gw - g0, -gq0, g1 + A.T @ gw, gq1

    def _residual(self, z, args):
        model, R0, mu0, q0, p0, h = args
        xi, u = z
        mu, p, _, _ = self.legendre(model, R0, h * xi, q0, u, h)
        return (mu - mu0, p - p0)

    def step(self, model, state: RigidState, dt):
        new_state, info, _ = self.solve_step(model, state, dt)
        return new_state, info

    def init_solver_state(self, model, state: RigidState, dt):
        """The last :data:`PREDICTOR_POINTS` solutions ``(ξ, u)`` of a rollout, newest first
        (at its start all the current velocities), and how many of them are solutions."""
        v = self.guess_from_velocities(self._velocities(model, state))
        return (v,) * PREDICTOR_POINTS, jnp.zeros((), jnp.int32)

    def step_with(self, model, state: RigidState, dt, solver_state):
        """A step whose Newton solve starts from the polynomial extrapolation of the last
        solutions (:func:`predict`; the current velocities are an O(h) guess, the linear
        extrapolation O(h²)): fewer Newton iterations per step (docs/engine.md), and no
        inverse Legendre map. Where the solutions vary too much from step to step
        (:func:`unresolved`, steps near the stability limit) from the current velocities
        instead, so that a rollout fails at the same steps as from the velocities (the
        extrapolation alone shrinks the car-pendulum's stability limits). The solution is
        the same to the solver's tolerance."""
        history, count = solver_state
        guess = predict(history, count)
        params, static = eqx.partition(model, eqx.is_array)

        def velocities(params, R, mu, q, p):
            m = eqx.combine(params, static)
            return self.guess_from_velocities(
                self._velocities(m, RigidState(R=R, mu=mu, q=q, p=p)))

        guess = where_any(unresolved(history, count), velocities, guess,
                          (params, state.R, state.mu, state.q, state.p))
        new_state, info, sol = self.solve_step(model, state, dt, guess)
        history = (sol, *history[:-1])
        return new_state, info, (history, jnp.minimum(count + 1, PREDICTOR_POINTS))

    def _velocities(self, model, state: RigidState):
        """The current velocities ``(ω, v)``, on scalars where the solve is."""
        args = (model, state.R, state.mu, state.q, state.p)
        if self.on_scalars:
            return scalarize(self._initial_guess)(*args)
        return self._initial_guess(*args)

    def solve_step(self, model, state: RigidState, dt, guess=None):
        """One step with Newton started from ``guess = (ξ, u)`` (default: the current
        velocities). Returns the new state, the step info and the solution ``(ξ, u)``, so
        that a composition can warm-start its next sub-step from it. The guess changes only
        the Newton iterates, not the solution.

        With ``Newton(scalar=True)`` (and the exact chord matrix) the guess, the Newton
        iteration and the new momenta are evaluated on scalars (:mod:`lgvi_jax.scalarize`):
        the same arithmetic, emitted as elementwise operations that XLA fuses."""
        R0, mu0, q0, p0 = state.R, state.mu, state.q, state.p
        h = jnp.asarray(dt, R0.dtype)
        args = (model, R0, mu0, q0, p0, h)
        if self.on_scalars:
            if guess is None:
                guess = self.guess_from_velocities(self._velocities(model, state))
            solver = self.newton
            if solver.scalar_jacobian == JacobianMode.AUTO:
                solver = dataclasses.replace(solver, scalar_jacobian=self.jacobian_mode)
            sol = newton_solve(self._residual, guess, args, solver)
            new_state = scalarize(self._finish)(model, R0, q0, p0, h, *sol.value)
            return new_state, StepInfo.from_solution(sol), sol.value
        solver = dataclasses.replace(self.newton, scalar=False)
        mass, at_rest = model.mass_matrix(R0, q0)
        # The kinetic-energy Hessian is symmetric positive definite: one pivot-free inverse
        # serves the initial guess and the mass chord (spd_inverse).
        mass_inv = spd_inverse(mass)
        if guess is None:
            x = mass_inv @ (jnp.concatenate([mu0, p0]) - at_rest)
            guess = self.guess_from_velocities((x[:3], x[3:]))
        if self.chord_matrix == ChordMatrix.MASS:
            jac0 = ChordInverse(mass_inv)
            solver = dataclasses.replace(solver, chord_steps=max(solver.chord_steps, 20),
                                         broyden=True)
        else:
            jac0 = None
        sol = newton_solve(self._residual, guess, args, solver, jac0=jac0)
        new_state = self._finish(model, R0, q0, p0, h, *sol.value)
        return new_state, StepInfo.from_solution(sol), sol.value

    def _initial_guess(self, model, R0, mu0, q0, p0):
        """The current velocities ``(ω_k, v_k)`` (inverse Legendre map; emitted on scalars,
        hence the entry-wise solve)."""
        mass, at_rest = model.mass_matrix(R0, q0)
        x = ldl_solve(mass, jnp.concatenate([mu0, p0]) - at_rest)
        return x[:3], x[3:]

    def _finish(self, model, R0, q0, p0, h, xi, u):
        """The new state from the solution ``(ξ, u)``: the second pair of Legendre
        transforms."""
        w = h * xi
        R1 = R0 @ self.tau(w)
        q1 = q0 + h * u
        _, g1, gq0, gq1, gw = self.gradients(model, R0, w, q0, u, h)
        A, _ = self.variations(w)
        mu1 = g1 + A.T @ gw
        # p_{k+1} = ∂G/∂q_{k+1} = p_k + (∂G/∂q_k + ∂G/∂q_{k+1}) at the solution; the sum is
        # exactly 0 in floating point when G depends on q only through u (translation
        # invariance), so that momentum is conserved to the last bit instead of
        # accumulating the Newton residual.
        p1 = p0 + (gq0 + gq1)
        return RigidState(R=R1, mu=mu1, q=q1, p=p1)


class LGVI(AbstractLieVI):
    r"""The general-form Lie group variational integrator (``lgvi``).

    :math:`L_d = h\,[T(R_k, (F_k - I)/h, q_k, (q_{k+1} - q_k)/h) - \tfrac12U(R_k, q_k) -
    \tfrac12U(R_{k+1}, q_{k+1})]`, :math:`F_k = R_k^\top R_{k+1}`. For the free body,
    :math:`T = \tfrac1h\operatorname{tr}[(I - F_k)J_d]` and the discrete Euler–Lagrange
    equations are the paper's eqs. 18–21. Newton solves for ``F`` through its Cayley
    coordinates. Order 2, symmetric, symplectic; momentum maps conserved exactly.
    """

    name: ClassVar[str] = "lgvi"
    symplectic: ClassVar[bool] = True
    #: ``F`` enters the kinetic energy through all nine entries of ``(F - I)/h``: one
    #: reverse pass per residual beats one tangent per unknown (car-pendulum 953 against
    #: 1355 operations; heavy top and free body 608 against 961).
    jacobian_mode: ClassVar[JacobianMode] = JacobianMode.REVERSE

    def tau_minus_identity(self, w):
        return so3.cayley_minus_identity(w)

    def discrete_lagrangian(self, model, h, R0, R1, FmI, w, q0, q1, u):
        T = model.kinetic(R0, FmI / h, q0, u)
        return h * (T - 0.5 * model.potential(R0, q0) - 0.5 * model.potential(R1, q1))

    def variations(self, w):
        eye = jnp.eye(3, dtype=w.dtype)
        return eye, eye  # G does not depend on w: unused (g_w = 0)


class HamelVI(AbstractLieVI):
    r"""Hamel variational integrators (``hamel``, ``hamel-cayley``, ``hamel-exact``).

    ``map`` is a :class:`~lgvi_jax.options.HamelMap` (or its string), ``"exp"`` or
    ``"cayley"`` (:math:`R_{k+1} = R_k\tau(h\xi)`); ``variation`` is a
    :class:`~lgvi_jax.options.Variation` (or its string), ``"paper"`` (the paper's eq. 29)
    or ``"exact"`` (through the inverse right differential of the map). See the module
    docstring for the discrete Lagrangian and the momentum-map properties of each
    combination.
    """

    map: HamelMap = eqx.field(default=HamelMap.EXP, converter=HamelMap.coerce)
    variation: Variation = eqx.field(default=Variation.PAPER, converter=Variation.coerce)
    #: Forward for every map and variation (car-pendulum ``hamel`` 1018 against 1277
    #: operations, heavy top ``hamel`` 259 against 372; tests/test_scalarize.py).
    jacobian_mode: ClassVar[JacobianMode] = JacobianMode.FORWARD

    def __check_init__(self):
        HamelMap.parse(self.map, type(self).__name__, "map")
        Variation.parse(self.variation, type(self).__name__, "variation")

    @property
    def name(self) -> str:
        base = "hamel" if self.map == HamelMap.EXP else "hamel-cayley"
        return f"{base}-exact" if self.variation == Variation.EXACT else base

    @property
    def symplectic(self) -> bool:
        # Exactly variational only with exact variations (see the module docstring).
        return self.variation == Variation.EXACT

    def tau_minus_identity(self, w):
        if self.map == HamelMap.EXP:
            return so3.exp_minus_identity(w)
        return so3.cayley_minus_identity(w)

    def discrete_lagrangian(self, model, h, R0, R1, FmI, w, q0, q1, u):
        Xi = so3.hat(w / h)
        T = 0.5 * (model.kinetic(R0, Xi, q0, u) + model.kinetic(R1, Xi, q1, u))
        return h * (T - 0.5 * model.potential(R0, q0) - 0.5 * model.potential(R1, q1))

    def variations(self, w):
        if self.variation == Variation.PAPER:
            eye = jnp.eye(3, dtype=w.dtype)
            W = 0.5 * so3.hat(w)
            return eye + W, eye - W
        # B = dτ⁻¹(w) τ(w)ᵀ, the inverse left-trivialised differential, equals dτ⁻¹(−w)
        # (J_l(w) = τ(w) J_r(w) = J_r(−w), for exp and Cayley alike): the same matrix
        # without a product with τ(w) (tested against the product), written as the left
        # inverse at w (for exp: one evaluation of the coefficient both share).
        if self.map == HamelMap.EXP:
            return so3.dexp_inv(w), so3.dexp_left_inv(w)
        return so3.dcayley_inv(w), so3.dcayley_left_inv(w)
