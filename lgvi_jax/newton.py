r"""Newton's method for the small dense systems of implicit one-step methods.

Every implicit step of this library (Gauss–Legendre stages, Galerkin nodes, Lie-group
increments) reduces to a root-finding problem :math:`F(y; a) = 0` with 2 to ~12 unknowns.
:func:`newton_solve` solves it with Newton's method

.. math::  y_{i+1} = y_i - J(y_i)^{-1} F(y_i), \qquad J = \partial F / \partial y,

where the Jacobian comes from forward-mode autodiff (``jax.jacfwd``) and the linear system
from an unrolled Gaussian elimination with partial pivoting (:func:`small_solve`), which XLA
fuses into a handful of vector operations instead of a LAPACK call.

**Convergence.** The iteration stops successfully when the Newton update is small,
``max_i |Δy_i| / (atol + rtol |y_i|) <= 1``. Newton converges quadratically, so an update of
size ``1e-12`` means the iterate is already at round-off level. It stops with a failure code
when the update or the residual stops being finite (:attr:`RESULTS.nonfinite`) or after
``max_steps`` iterations (:attr:`RESULTS.max_steps_reached`). Failure is a value:
:class:`NewtonSolution` carries the code, the number of iterations and the residual; with
``throw=True`` a failure raises :class:`NewtonError` (eagerly) or an ``EquinoxRuntimeError``
(under ``jit``).

**Differentiation.** The solution map :math:`a \mapsto y^*(a)` is differentiated by the
implicit function theorem, not by unrolling the iterations:

.. math::  \frac{\partial y^*}{\partial a} = -J(y^*)^{-1} \frac{\partial F}{\partial a}(y^*; a).

This is a ``jax.custom_jvp`` rule, so forward mode (``jvp``) works directly and reverse mode
(``grad``) works by JAX's transposition of the (linear) tangent solve. Only the arguments
passed through ``args`` are differentiated: ``fn`` must not close over traced values.

*Why a* ``custom_jvp`` *and not a* ``custom_vjp``. The tangent rule
:math:`\dot y = -J^{-1}\,\partial_a F\,\dot a` is linear in :math:`\dot a`; reverse mode
linearises it (the Jacobian :math:`J(y^*)` and its pivoted elimination are stored as
residuals) and transposes it, which gives exactly the implicit-function-theorem adjoint

.. math::  \bar a = -\left(\partial_a F\right)^{\top} \lambda, \qquad J^{\top}\lambda = \bar y,

one transposed solve and one vector-Jacobian product of ``F`` per solve. The iterations are
never differentiated: JAX cannot reverse-differentiate a ``lax.while_loop`` at all, so that
``grad`` works is itself the proof. A ``custom_vjp`` would compute the same adjoint but lose
forward mode (``jvp``, ``jacfwd``), which trajectory sensitivities and Gauss–Newton fits use.

``Newton(adjoint="unrolled")`` instead runs ``max_steps`` plain Newton iterations as a
``lax.scan`` without any custom rule, so that autodiff differentiates through the iterations
(the derivative of the iterates converges to the implicit one as the iterates converge).
It exists to test the implicit rule against, and costs ``max_steps`` full iterations per
solve, converged or not.

References: C. T. Kelley, *Solving Nonlinear Equations with Newton's Method*, SIAM 2003;
the implicit-function-theorem adjoint as in optimistix (``ImplicitAdjoint``).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import warnings
import weakref
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name
from jax.flatten_util import ravel_pytree

from . import scalarize as sc
from .linalg import small_solve
from .options import Adjoint, JacobianLoop, JacobianMode, LinearSolver
from .trajectory import RESULTS

__all__ = ["ChordInverse", "Newton", "NewtonError", "NewtonSolution", "clear_scalar_programs",
           "newton_solve"]


class NewtonError(RuntimeError):
    """Raised by ``throw=True`` when a Newton solve (or a step of a rollout) fails."""


class Newton(eqx.Module):
    """Newton's method with an autodiff Jacobian.

    Attributes:
        rtol, atol: the iteration has converged when every component of the last update
            satisfies ``|Δy_i| <= atol + rtol |y_i|``.
        max_steps: iteration cap (each iteration = one residual, one Jacobian, one solve).
        chord: if True, the Jacobian is computed and factorised once, at the initial guess
            (the chord or simplified Newton method): cheaper iterations, linear convergence.
        chord_steps: if > 0 (and ``chord`` is False), start with up to ``chord_steps``
            chord iterations; a phase that has not converged by then or whose updates stop
            halving starts again from its iterate with a fresh Jacobian if it reduced the
            residual (at most :data:`CHORD_REFRESHES` times), and otherwise the solve falls
            back to full Newton from the initial guess. As robust as
            Newton, and about twice as fast for the Lie-group VIs at moderate steps
            (``lgvi_jax/bench/throughput.py``). One loop serves both phases, so the
            Jacobian is traced once (``_iterate_chord_refresh``).
        broyden: with a given chord matrix (``jac0``), update its inverse after every
            iteration by Broyden's ("good") rank-one formula instead of keeping it fixed:
            superlinear instead of linear convergence at the cost of a few 5x5 products
            per iteration (:func:`_broyden`). With the continuous Legendre matrix of
            the Lie-group VIs this takes ~5 residuals per step instead of ~8 at
            h = 5e-3. The root and its derivatives do not change.
        unroll: the first ``unroll`` Newton iterations are traced as straight-line code
            (same iterates as the loop); for experiments with XLA scheduling. Plain Newton
            only (ignored with ``chord`` or ``chord_steps``).
        linear_solver: a :class:`~lgvi_jax.options.LinearSolver` (or its string):
            ``"unrolled"`` (:func:`small_solve`, default) or ``"lu"``
            (``jnp.linalg.solve``, LAPACK); see ``experiments/bench_newton.py``.
        adjoint: an :class:`~lgvi_jax.options.Adjoint` (or its string).
            ``"implicit"`` (default): derivatives by the implicit function theorem
            (module docstring). ``"unrolled"``: exactly ``max_steps`` plain Newton
            iterations (``chord``, ``chord_steps`` and ``unroll`` are ignored), differentiated
            through by autodiff; the result code says whether the last update met the
            tolerance. For testing the implicit rule.
        scalar: run the iteration on scalars (:mod:`lgvi_jax.scalarize`): the residual, its
            Jacobian, its factors by blocks and the updates are emitted as scalar
            elementwise operations, so that XLA fuses an iteration into a few kernels (a
            structure of arrays under ``vmap``). Same iterates as the array form to the
            order of floating-point sums, same implicit derivatives. Plain Newton or
            ``chord_steps``; no given chord matrix.
        scalar_jacobian: the autodiff mode of the Jacobian program on scalars, a
            :class:`~lgvi_jax.options.JacobianMode` (or its string): ``"forward"``
            (``jacfwd``), ``"reverse"`` (``jacrev``) or ``"auto"`` (default:
            both traced, the one with fewer operations kept, at the price of tracing the
            other at every compilation). The Lie-group VIs name theirs
            (:class:`~lgvi_jax.integrators.lie.AbstractLieVI`). Same matrix to the order
            of floating-point sums.
        jacobian_loop: a :class:`~lgvi_jax.options.JacobianLoop` (or its string): when the
            chord matrix on scalars is computed in loops over the unknowns (per block of
            them, the JVP along one unknown at a time: a smaller program, compiled faster,
            ~1.2-1.3x the unrolled Jacobian's run-time operations). ``"batched"``
            (default): for a batch of solves (under ``vmap``) on a CPU, whose compilation
            is the longer; one solve, and batches on an accelerator, unrolled.
            ``"never"``, ``"always"``. Same matrix to the order of floating-point sums.
    """

    rtol: float = 1e-12
    atol: float = 1e-12
    max_steps: int = eqx.field(static=True, default=20)
    chord: bool = eqx.field(static=True, default=False)
    chord_steps: int = eqx.field(static=True, default=0)
    linear_solver: LinearSolver = eqx.field(static=True, default=LinearSolver.UNROLLED,
                                            converter=LinearSolver.coerce)
    broyden: bool = eqx.field(static=True, default=False)
    unroll: int = eqx.field(static=True, default=0)
    adjoint: Adjoint = eqx.field(static=True, default=Adjoint.IMPLICIT,
                                 converter=Adjoint.coerce)
    scalar: bool = eqx.field(static=True, default=False)
    scalar_jacobian: JacobianMode = eqx.field(static=True, default=JacobianMode.AUTO,
                                              converter=JacobianMode.coerce)
    jacobian_loop: JacobianLoop = eqx.field(static=True, default=JacobianLoop.BATCHED,
                                            converter=JacobianLoop.coerce)

    @property
    def scalar_compatible(self) -> bool:
        """Whether these settings can run on scalars (``scalar=True``): Newton or
        ``chord_steps``; no ``chord``, ``broyden``, ``unroll`` or unrolled adjoint."""
        return not (self.chord or self.broyden or self.unroll
                    or self.adjoint != Adjoint.IMPLICIT)

    def __check_init__(self):
        # The converters store the member for a valid string and leave anything else as it
        # is, refused here with the owner's name.
        LinearSolver.parse(self.linear_solver, "Newton", "linear_solver")
        Adjoint.parse(self.adjoint, "Newton", "adjoint")
        JacobianMode.parse(self.scalar_jacobian, "Newton", "scalar_jacobian")
        JacobianLoop.parse(self.jacobian_loop, "Newton", "jacobian_loop")
        if self.scalar and not self.scalar_compatible:
            raise ValueError("Newton: scalar=True supports Newton and chord_steps (no chord, "
                             "broyden, unroll or unrolled adjoint)")
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if isinstance(value, jax.core.Tracer):  # a solver rebuilt under jit: checked before
                continue
            if not isinstance(value, (float, int)) or not np.isfinite(value) or value < 0:
                raise ValueError(f"Newton: {name} must be a finite number >= 0, got {value!r}")
        concrete = not any(isinstance(v, jax.core.Tracer) for v in (self.rtol, self.atol))
        if concrete and self.rtol == 0 and self.atol == 0:
            raise ValueError("Newton: rtol and atol cannot both be 0")
        if not isinstance(self.max_steps, int) or self.max_steps < 1:
            raise ValueError(f"Newton: max_steps must be an integer >= 1, got {self.max_steps!r}")


class NewtonSolution(eqx.Module):
    """Outcome of :func:`newton_solve`.

    Attributes:
        value: the last iterate (the root when ``result == RESULTS.successful``).
        result: ``int32`` result code, see :class:`RESULTS`.
        newton_steps: Newton iterations taken (the name of the iteration counts throughout:
            :class:`~lgvi_jax.integrators.StepInfo`, :class:`~lgvi_jax.Trajectory`).
        residual: max-norm of the residual at the last iterate where it was evaluated.
    """

    value: Any
    result: jax.Array
    newton_steps: jax.Array
    residual: jax.Array

    @property
    def ok(self) -> jax.Array:
        return self.result == RESULTS.successful

    @property
    def num_steps(self) -> jax.Array:
        """Deprecated name of :attr:`newton_steps`."""
        warnings.warn("NewtonSolution.num_steps is deprecated; use newton_steps",
                      DeprecationWarning, stacklevel=2)
        return self.newton_steps


_LINEAR_SOLVERS = {LinearSolver.UNROLLED: small_solve, LinearSolver.LU: jnp.linalg.solve}


# ---------------------------------------------------------------------------------------
# Newton iteration
# ---------------------------------------------------------------------------------------


def _residual_and_jacobian(f, y):
    # One forward pass gives both F(y) (as auxiliary output) and the Jacobian.
    return jax.jacfwd(lambda z: (f(z), f(z)), has_aux=True)(y)


#: The chord iteration's convergence threshold, in units of the tolerance (see make_body).
_CHORD_TIGHTEN = 1e-2
#: The same for Broyden's iteration, which converges superlinearly: 0.1 keeps the
#: car-pendulum's vertical angular momentum as well conserved as Newton's, in fewer
#: iterations than the fixed chord (1.0: twice Newton's drift; docs/benchmarks.md).
_BROYDEN_TIGHTEN = 0.1
#: How often a stalled chord phase that made progress starts again from its iterate with
#: a fresh Jacobian (``Newton(chord_steps=...)``) before the solve falls back to full
#: Newton from the initial guess.
CHORD_REFRESHES = 2


def _chord_phase_end(newton, result, refreshes, res, res0, k, cap, max_steps: int):
    """The decision after a phase of the ``chord_steps`` iteration (array and scalar loops
    alike): a chord phase that did not converge starts again from its iterate with a fresh
    Jacobian if it reduced the residual below the guess's (``res < res0``, at most
    :data:`CHORD_REFRESHES` times), else the solve falls back to full Newton from the guess
    with ``max_steps`` more iterations. Returns ``(fallback, newton, cap, refreshes)``."""
    failed = ~newton & (result < 0)
    refresh = failed & (refreshes < CHORD_REFRESHES) & (res < res0)
    fallback = failed & ~refresh
    return fallback, newton | fallback, jnp.where(fallback, k + max_steps, cap), \
        refreshes + refresh


def _inverse(J, solve):
    """``J⁻¹`` of a small matrix, column by column with ``solve``."""
    eye = jnp.eye(J.shape[-1], dtype=J.dtype)
    return jax.vmap(lambda e: solve(J, e), out_axes=1)(eye)


class ChordInverse(eqx.Module):
    """A chord matrix given by its inverse (``newton_solve(jac0=ChordInverse(M⁻¹))``),
    for a caller that has it already (the Lie-group VIs invert the mass matrix once per
    step for both the initial guess and the chord)."""

    inverse: jax.Array


def _chord_inverse(jac0, solver: Newton):
    if isinstance(jac0, ChordInverse):
        return jac0.inverse
    return _inverse(jac0, _LINEAR_SOLVERS[solver.linear_solver])


def _iterate(f, y0, solver: Newton, jac0=None):
    """Run the Newton iteration on a flat ``f: R^n -> R^n``. Returns (y, result, steps, res).

    With ``chord_steps > 0`` see :func:`_iterate_chord_refresh`.
    """
    dtype = y0.dtype
    zero = jnp.asarray(0, jnp.int32)
    solve = _LINEAR_SOLVERS[solver.linear_solver]

    def make_body(J_fixed, limit):
        # A fixed (chord) matrix is inverted once, so that an iteration costs a residual and
        # a matrix-vector product (the chord needs only an approximate inverse anyway: the
        # residual, evaluated exactly, decides the root).
        J_inv = None if J_fixed is None else _chord_inverse(J_fixed, solver)

        def body(carry):
            y, k, _, _, prev = carry
            if J_fixed is None:
                J, F = _residual_and_jacobian(f, y)
                delta = -solve(J, F)
            else:
                F = f(y)
                delta = -(J_inv @ F)
            y_new = y + delta
            res = jnp.max(jnp.abs(F), initial=0.0)
            finite = jnp.all(jnp.isfinite(delta)) & jnp.isfinite(res)
            scale = solver.atol + solver.rtol * jnp.abs(y_new)
            size = jnp.max(jnp.abs(delta) / scale, initial=0.0)
            # A chord iteration contracts only linearly (by rho per iteration): after an update
            # at the tolerance the error is still ~rho * tol, which random-walks into the
            # momentum maps (L_z drift over 1e4 steps 4e-13 -> 6e-11 measured with the mass
            # matrix). Asking 100x less of the last chord update puts the error at round-off.
            converged = size <= (1.0 if J_fixed is None else _CHORD_TIGHTEN)
            k = k + 1
            stalled = k >= limit
            if J_fixed is not None:  # the chord phase also gives up when it stops contracting
                stalled = stalled | (size > 0.5 * prev)
            result = jnp.where(
                ~finite,
                RESULTS.nonfinite,
                jnp.where(
                    converged,
                    RESULTS.successful,
                    jnp.where(stalled, RESULTS.max_steps_reached, -1),
                ),
            ).astype(jnp.int32)
            # A non-finite update is not applied: the last finite iterate is returned.
            y_new = jnp.where(finite, y_new, y)
            return y_new, k, result, res, size

        return body

    def cond(carry):
        return carry[2] < 0

    def start(y, k):
        return (y, k, jnp.asarray(-1, jnp.int32), jnp.asarray(jnp.inf, dtype),
                jnp.asarray(jnp.inf, dtype))

    if solver.chord:
        J0 = _residual_and_jacobian(f, y0)[0] if jac0 is None else jac0
        J0 = J0 if isinstance(J0, ChordInverse) else jnp.asarray(J0, dtype)
        y, k, result, res, _ = jax.lax.while_loop(
            cond, make_body(J0, solver.max_steps), start(y0, zero))
        return y, result, k, res

    if solver.chord_steps and jac0 is None:
        return _iterate_chord_refresh(f, y0, solver)

    if solver.chord_steps:
        # A given chord matrix: the chord phase with it, then full Newton from the initial
        # guess for the solves that did not converge (iterations keep counting; the cap
        # applies to the Newton phase alone). The Jacobian is traced once, in the Newton
        # phase.
        limit = min(solver.chord_steps, solver.max_steps)
        if solver.broyden:
            y, k, result, res = _broyden(f, y0, jac0, limit, solver)
        else:
            chord_body = make_body(jac0, limit)
            y, k, result, res, _ = jax.lax.while_loop(cond, chord_body, start(y0, zero))
        failed = result != RESULTS.successful
        carry = (jnp.where(failed, y0, y), k, jnp.where(failed, -1, result).astype(jnp.int32),
                 res, jnp.asarray(jnp.inf, dtype))
        newton_body = make_body(None, k + solver.max_steps)
    else:
        newton_body = make_body(None, solver.max_steps)
        carry = start(y0, zero)

    def masked_body(carry):
        # An unrolled iteration that leaves a finished solve untouched, so that the iterates
        # are exactly those of the while loop.
        new = newton_body(carry)
        running = cond(carry)
        return jax.tree.map(lambda a, b: jnp.where(running, a, b), new, carry)

    for _ in range(min(solver.unroll, solver.max_steps)):
        carry = masked_body(carry)
    y, k, result, res, _ = jax.lax.while_loop(cond, newton_body, carry)
    return y, result, k, res


def _broyden(f, y0, jac0, limit: int, solver: Newton):
    r"""The chord phase with Broyden's update of the inverse matrix (``Newton.broyden``).

    With ``H ≈ J⁻¹`` (initially ``jac0⁻¹``), an iteration evaluates ``F(y)``, updates ``H``
    with the previous step ``s`` and the residual change ``d = F(y) − F(y − s)`` by the
    "good" Broyden formula (the inverse form of the least change secant update)

    .. math::  H \leftarrow H + \frac{(s - H d)\, s^\top H}{s^\top H d},

    which makes ``H d = s``, and takes the step ``s = −H F(y)``. Convergence is
    superlinear from a good initial matrix (Dennis & Moré, SIAM Review 19, 1977; Kelley,
    2003, ch. 7). A vanishing denominator skips the update. Stops on an update within the
    (tightened) tolerance (successful), or after ``limit`` iterations, on an update not at
    least halving or a non-finite one (``RESULTS.max_steps_reached``: the caller's Newton
    fallback takes over and reports a non-finite problem as such).
    One residual per iteration, as for the plain chord. Returns (y, steps, result, res).
    """
    dtype = y0.dtype
    H0 = _chord_inverse(jac0, solver)
    inf = jnp.asarray(jnp.inf, dtype)

    def body(carry):
        y, k, _, prev, H, s, F_prev = carry
        F = f(y)
        # The secant update with the previous step s (s = 0 on the first iteration, where
        # the denominator vanishes and H stays jac0⁻¹).
        Hd = H @ (F - F_prev)
        denom = s @ Hd
        use = denom != 0
        H = jnp.where(use, H + jnp.outer(s - Hd, s @ H) / jnp.where(use, denom, 1.0), H)
        delta = -(H @ F)
        y_new = y + delta
        scale = solver.atol + solver.rtol * jnp.abs(y_new)
        # NaN propagates into size; every comparison with it is False, so a non-finite
        # iterate counts as stalled and leaves for the caller's Newton fallback (which
        # reports it), at no cost to the finite case.
        size = jnp.max(jnp.abs(delta) / scale, initial=0.0)
        k = k + 1
        # Superlinear convergence: the error left after an update is much smaller than the
        # update, so a milder tightening than the fixed chord's keeps the momentum maps at
        # round-off (_BROYDEN_TIGHTEN).
        converged = size <= _BROYDEN_TIGHTEN
        stalled = (k >= limit) | ~(size <= 0.5 * prev)
        result = jnp.where(converged, RESULTS.successful,
                           jnp.where(stalled, RESULTS.max_steps_reached, -1)).astype(jnp.int32)
        return y_new, k, result, size, H, delta, F

    zero_vec = jnp.zeros_like(y0)
    init = (y0, jnp.asarray(0, jnp.int32), jnp.asarray(-1, jnp.int32), inf, H0,
            zero_vec, zero_vec)
    y, k, result, _, _, _, F = jax.lax.while_loop(lambda c: c[2] < 0, body, init)
    res = jnp.max(jnp.abs(F), initial=0.0)  # at the last iterate where it was evaluated
    return y, k, result, res


def _iterate_chord_refresh(f, y0, solver: Newton):
    """Chord iterations first, full Newton as the fallback (``chord_steps > 0``).

    The chord phase takes a Newton step from the initial guess and then reuses that
    Jacobian for up to ``chord_steps`` iterations; when its updates stop shrinking by at
    least half or it runs out, a phase that has reduced the residual below the initial
    guess's starts again from its iterate with the Jacobian there (at most
    :data:`CHORD_REFRESHES` times: large steps, where the guess is poor and the contraction
    slow), and any other restarts from the initial guess with full Newton (at most
    ``max_steps`` more iterations; iterations keep counting). All phases run in one loop
    whose body evaluates the Jacobian once, followed
    by an inner loop of chord iterations that the Newton phase skips: the Jacobian and the
    residual are each traced once, which keeps the compiled program small (compile time),
    and under ``vmap`` a batch whose members all converge in the chord phase pays for one
    Jacobian each.
    """
    dtype = y0.dtype
    solve = _LINEAR_SOLVERS[solver.linear_solver]
    chord_cap = min(solver.chord_steps, solver.max_steps)
    inf = jnp.asarray(jnp.inf, dtype)

    def update(y, J_inv, F, k, prev, newton, cap, k_phase):
        delta = -(J_inv @ F)
        res = jnp.max(jnp.abs(F), initial=0.0)
        finite = jnp.all(jnp.isfinite(delta)) & jnp.isfinite(res)
        y_new = y + delta
        scale = solver.atol + solver.rtol * jnp.abs(y_new)
        size = jnp.max(jnp.abs(delta) / scale, initial=0.0)
        k = k + 1
        # A chord phase gives up (-> refresh or Newton) when it stops contracting or runs
        # out; the Newton phase fails at its cap.
        stalled = jnp.where(newton, False,
                            (k - k_phase >= chord_cap) | (size > 0.5 * prev))
        result = jnp.where(
            ~finite,
            RESULTS.nonfinite,
            jnp.where(size <= 1.0, RESULTS.successful,
                      jnp.where(newton & (k >= cap), RESULTS.max_steps_reached, -1)),
        ).astype(jnp.int32)
        # A non-finite update is not applied: the last finite iterate is returned.
        y_new = jnp.where(finite, y_new, y)
        return y_new, k, result, res, size, stalled

    def outer_body(carry):
        y, k, _, _, newton, cap, refreshes, res0 = carry
        k_phase = k
        J, F = _residual_and_jacobian(f, y)
        J_inv = _inverse(jnp.asarray(J, dtype), solve)  # once, for the chord iterations
        y, k, result, res, size, stalled = update(y, J_inv, F, k, inf, newton, cap, k_phase)
        res0 = jnp.where(k == 1, res, res0)  # the residual at the initial guess

        def inner_cond(c):
            return (c[2] < 0) & ~c[5]

        def inner_body(c):
            y, k, _, _, prev, _ = c
            return update(y, J_inv, f(y), k, prev, newton, cap, k_phase)

        y, k, result, res, _, stalled = jax.lax.while_loop(
            inner_cond, inner_body, (y, k, result, res, size, stalled | newton))
        fallback, newton, cap, refreshes = _chord_phase_end(
            newton, result, refreshes, res, res0, k, cap, solver.max_steps)
        y = jnp.where(fallback, y0, y)
        return y, k, result, res, newton, cap, refreshes, res0

    zero = jnp.asarray(0, jnp.int32)
    init = (y0, zero, jnp.asarray(-1, jnp.int32), inf, jnp.asarray(False),
            jnp.asarray(solver.max_steps, jnp.int32), zero, inf)
    y, k, result, res, *_ = jax.lax.while_loop(lambda c: c[2] < 0, outer_body, init)
    return y, result, k, res


def _iterate_unrolled(f, y0, solver: Newton):
    """``max_steps`` plain Newton iterations in a ``lax.scan``, with no custom derivative
    rule: autodiff differentiates through every iteration (``Newton(adjoint="unrolled")``).
    A non-finite update is not applied (the last finite iterate is kept), as in
    :func:`_iterate`. Returns (y, result, steps, residual at the returned iterate)."""
    solve = _LINEAR_SOLVERS[solver.linear_solver]

    def body(carry, _):
        y, _, finite_so_far = carry
        J, F = _residual_and_jacobian(f, y)
        delta = -solve(J, F)
        finite = jnp.all(jnp.isfinite(delta))
        y_new = jnp.where(finite, y + delta, y)
        scale = solver.atol + solver.rtol * jnp.abs(y_new)
        size = jnp.max(jnp.abs(delta) / scale, initial=0.0)
        return (y_new, size, finite_so_far & finite), None

    init = (y0, jnp.asarray(jnp.inf, y0.dtype), jnp.asarray(True))
    (y, size, finite), _ = jax.lax.scan(body, init, None, length=solver.max_steps)
    res = jnp.max(jnp.abs(f(y)), initial=0.0)
    finite = finite & jnp.isfinite(res)
    result = jnp.where(
        ~finite,
        RESULTS.nonfinite,
        jnp.where(size <= 1.0, RESULTS.successful, RESULTS.max_steps_reached),
    ).astype(jnp.int32)
    return y, result, jnp.asarray(solver.max_steps, jnp.int32), res


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _newton_core(fn, solver, y0, args, jac0):
    f = functools.partial(fn, args=args)
    return _iterate(f, y0, solver, jac0)


#: The name of a solve's outputs inside its differentiation rule
#: (``jax.ad_checkpoint.checkpoint_name``): a ``jax.checkpoint`` policy that saves them
#: (``simulate``'s ``checkpoint_every``) keeps the backward pass from solving again.
SOLUTION_NAME = "lgvi_jax.newton_solution"


def _solution_tangents(y, result, k, res, y_dot):
    """The primal and tangent outputs of a solve's JVP rule: only the root has a tangent."""
    float0 = jax.dtypes.float0
    return (y, result, k, res), (
        y_dot,
        np.zeros(result.shape, float0),
        np.zeros(k.shape, float0),
        jnp.zeros_like(res),
    )


def _named(outputs):
    """The solve's outputs named :data:`SOLUTION_NAME` (identity otherwise)."""
    return tuple(checkpoint_name(x, SOLUTION_NAME) for x in outputs)


@_newton_core.defjvp
def _newton_core_jvp(fn, solver, primals, tangents):
    # The root does not depend on y0 or on the chord matrix jac0: only args' tangents count.
    y0, args, jac0 = primals
    _, args_dot, _ = tangents
    y, result, k, res = _named(_newton_core(fn, solver, y0, args, jac0))
    # Implicit function theorem at the solution: J dy = -dF/da . da
    J = jax.jacfwd(lambda z: fn(z, args))(y)
    _, dF = jax.jvp(lambda a: fn(y, a), (args,), (args_dot,))
    y_dot = -small_solve(J, dF)
    return _solution_tangents(y, result, k, res, y_dot)


def newton_solve(
    fn: Callable[[Any, Any], Any],
    y0: Any,
    args: Any = None,
    solver: Newton | None = None,
    *,
    throw: bool = False,
    jac0: jax.Array | None = None,
) -> NewtonSolution:
    """Solve ``fn(y, args) = 0`` for ``y`` by Newton's method, starting from ``y0``.

    Args:
        fn: residual function ``fn(y, args)`` returning a pytree with the same structure and
            shapes as ``y``. Everything it depends on that may be traced (parameters, states)
            must come in through ``args``; only ``args`` is differentiated.
        y0: initial guess (a pytree of float arrays; flattened internally).
        args: pytree of arguments, differentiated by the implicit function theorem.
        solver: :class:`Newton` settings (default ``Newton()``).
        throw: if True, a failed solve raises :class:`NewtonError` (or, under ``jit``, an
            ``EquinoxRuntimeError``) instead of only returning the failure code.
        jac0: the matrix of the chord phase (``chord`` or ``chord_steps``), ``(n, n)`` in the
            order of the flattened ``y``: an approximation of the Jacobian that is cheaper
            than the exact one at ``y0`` (the default), or :class:`ChordInverse` of its
            inverse. It changes the iterates, not the
            root (nor its derivatives); a poor one only sends the solve to the Newton phase.

    Returns:
        :class:`NewtonSolution` with the root, the result code, iterations and residual.
    """
    solver = Newton() if solver is None else solver
    y0_flat, unravel = ravel_pytree(y0)
    if y0_flat.size == 0:
        raise ValueError("newton_solve: y0 has no unknowns")
    if not jnp.issubdtype(y0_flat.dtype, jnp.floating):
        raise ValueError(f"newton_solve: y0 must be floating point, got {y0_flat.dtype}")
    flat_fn = _flat_residual(fn, y0, unravel)

    if solver.scalar:
        if jac0 is not None:
            raise ValueError("newton_solve: Newton(scalar=True) takes no chord matrix jac0")
        y, result, k, res = _scalar_core(flat_fn, solver, y0_flat, args)
    elif solver.adjoint == Adjoint.UNROLLED:
        y, result, k, res = _iterate_unrolled(
            functools.partial(flat_fn, args=args), y0_flat, solver
        )
    else:
        if jac0 is not None:
            wrap = ChordInverse if isinstance(jac0, ChordInverse) else (lambda a: a)
            matrix = jac0.inverse if isinstance(jac0, ChordInverse) else jac0
            matrix = jax.lax.stop_gradient(jnp.asarray(matrix, y0_flat.dtype))
            if matrix.shape != (y0_flat.size, y0_flat.size):
                raise ValueError(f"newton_solve: jac0 must have shape {(y0_flat.size,) * 2}, "
                                 f"got {matrix.shape}")
            jac0 = wrap(matrix)
        y, result, k, res = _newton_core(flat_fn, solver, y0_flat, args, jac0)
    sol = NewtonSolution(value=unravel(y), result=result, newton_steps=k, residual=res)
    if throw:
        sol = raise_if_failed(sol)
    return sol


#: The flattened residual per residual method (its function, with the instance in the inner
#: key) and structure of the unknowns: every solve of the same equations then passes the
#: same function to the solver, whose scalar programs are remembered per function
#: (:func:`_memo`), so that another trace (a batch after one trajectory, a fit's loss after
#: its gradient, a notebook's next ``jit``) does not build them again.
_FLAT: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _flat_residual(fn, y0, unravel):
    """``fn`` on flat vectors of unknowns and residuals (``unravel``: of ``y0``'s
    structure), one function per bound method (:data:`_FLAT`; its instance hashable) and
    structure. Other residuals (closures made per step, which the flattened function
    would keep alive) get a new one at each call."""

    def flat_fn(y_flat, args):
        out = fn(unravel(y_flat), args)
        out_flat, _ = ravel_pytree(out)
        if out_flat.shape != y_flat.shape:
            raise ValueError(
                "newton_solve: fn(y, args) must return as many residuals as unknowns, got "
                f"{out_flat.shape[0]} residuals for {y_flat.shape[0]} unknowns"
            )
        return out_flat

    owner, instance = getattr(fn, "__func__", None), getattr(fn, "__self__", None)
    if owner is None or instance is None:
        return flat_fn
    try:
        return _FLAT.setdefault(owner, {}).setdefault((instance, *sc.signature(y0)), flat_fn)
    except TypeError:  # an instance that cannot be hashed (arrays, tracers)
        return flat_fn


def raise_if_failed(sol: NewtonSolution) -> NewtonSolution:
    """Raise if ``sol`` failed: :class:`NewtonError` with the numbers when they are concrete,
    an ``EquinoxRuntimeError`` under ``jit`` (where only a fixed message is possible)."""
    if isinstance(sol.result, jax.core.Tracer):
        # Attached to every output, so the check survives whichever output the caller uses.
        return eqx.error_if(
            sol, jnp.any(sol.result != RESULTS.successful), "Newton solve failed (throw=True)"
        )
    code = int(np.max(np.asarray(sol.result)))
    if code != RESULTS.successful:
        raise NewtonError(
            f"Newton solve failed: {RESULTS.describe(code)} "
            f"(iterations {int(np.max(np.asarray(sol.newton_steps)))}, "
            f"residual {float(np.max(np.asarray(sol.residual))):.3e})"
        )
    return sol


# ---------------------------------------------------------------------------------------
# The iteration on scalars (Newton(scalar=True))
# ---------------------------------------------------------------------------------------


def _scalar_matvec(A, x):
    out = []
    for row in A:
        acc = sc.constant(0.0, np.float64)
        for a, b in zip(row, x, strict=True):
            acc = sc.add(acc, sc.mul(a, b))
        out.append(acc)
    return out


def _scalar_max(values, initial):
    acc = initial
    for v in values:
        acc = sc.maximum(acc, v)
    return acc


def _rows(obj) -> list[list[Any]]:
    return [list(obj[i]) for i in range(obj.shape[0])]


#: The scalar programs built for each residual function (weakly keyed: an entry lives as
#: long as the function), per shapes and dtypes of its arguments. One differentiated solve
#: builds the residual's Jacobian three times otherwise (the solve, the primal solve
#: of its JVP rule, the Jacobian at the solution).
_PROGRAMS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def clear_scalar_programs() -> None:
    """Forget every scalar program built so far (:func:`~lgvi_jax.scalarize.program_for`'s
    and the solver's, :func:`_memo`): the next trace builds them again, as a fresh process
    does (``lgvi-jax bench`` times cold compiles so)."""
    sc.clear_programs()
    _PROGRAMS.clear()
    _FLAT.clear()


def _memo(kind: str, fn, y0, args, build):
    """``build()``, remembered per ``(fn, kind, argument shapes and dtypes)``: the
    programs depend on nothing else, since ``fn`` may not close over traced values (those
    that do, with programs that take traced constants, are built afresh every time)."""
    key = (kind, *sc.signature((y0, args)))
    try:
        per_fn = _PROGRAMS.setdefault(fn, {})
    except TypeError:  # not weakly referable
        return build()
    if key not in per_fn:
        out = build()
        if out.traced_consts:
            return out
        per_fn[key] = out
    return per_fn[key]


def _scalar_jacobian(fn, y0, args, mode: JacobianMode | str = JacobianMode.AUTO,
                     residual: bool = False) -> sc.ScalarFunction:
    """The Jacobian of ``fn`` in ``y`` as a scalar program: forward mode (one tangent per
    unknown), reverse mode (one cotangent per residual) or, with ``mode="auto"``, whichever
    leaves fewer operations after folding and merging (the car-pendulum's ``lgvi``: reverse
    953 against forward 1355 operations; ``hamel``: forward 1018 against 1277). The same
    matrix up to the order of the floating-point sums.

    With ``residual``, where the mode is reverse, the program returns ``(J, fn)``: the
    reverse pass runs the primal to its end, so the residual costs little more (``lgvi``:
    1074 operations for both against 953 + 360), and the first update after each Jacobian
    needs no residual of its own (one trajectory 4–8 % faster, docs/engine.md). In forward
    mode, where sharing measured no faster, the Jacobian alone; ``out_shape`` tells which."""
    if mode == JacobianMode.AUTO:
        forward = _scalar_jacobian(fn, y0, args, JacobianMode.FORWARD)
        reverse = _scalar_jacobian(fn, y0, args, JacobianMode.REVERSE)
        if forward.size <= reverse.size:
            return forward
        if not residual:
            return reverse
        mode = JacobianMode.REVERSE
    if mode == JacobianMode.REVERSE and residual:
        return _memo("jacobian-residual", fn, y0, args, lambda: sc.ScalarFunction(
            lambda y, a: (jax.jacrev(fn)(y, a), fn(y, a)), y0, args))
    jac = jax.jacrev if mode == JacobianMode.REVERSE else jax.jacfwd
    return _memo(f"jacobian:{mode}", fn, y0, args, lambda: sc.ScalarFunction(jac(fn), y0, args))


_BATCHED_TRACE = contextvars.ContextVar("lgvi_jax.newton.batched_trace", default=False)


@contextlib.contextmanager
def batched_trace():
    """While tracing code that ``vmap`` batches (a sweep's block), the solves on scalars
    trace their unbatched form with a batch's programs. ``custom_vmap`` traces that form,
    which a batch never runs, before batching the solve: with a batch's programs, memoised,
    it builds no program of its own (the unrolled Jacobian, for ``jacobian_loop=
    "batched"``). Where it does run, it computes the same matrix up to the order of the
    floating-point sums."""
    token = _BATCHED_TRACE.set(True)
    try:
        yield
    finally:
        _BATCHED_TRACE.reset(token)


def _scalar_programs(fn, y0, args, solver: Newton, lanes: int | None):
    """The residual's scalar program and the chord matrix's, ``(residual, jacobian)``:
    ``jacobian(y, args)`` takes scalars (:func:`~lgvi_jax.scalarize.split`) and returns
    the matrix's rows and the residual at ``y``, unrolled (``solver.scalar_jacobian``:
    :func:`_scalar_jacobian`, the residual from the same program) or by blocks of columns
    in loops (``solver.jacobian_loop``: :func:`_scalar_tangent`; the residual ``None``)
    for a batch of ``lanes`` solves or one (``None``; a batch's within
    :func:`batched_trace`). Each program is traced once per solve."""
    residual = _memo("residual", fn, y0, args, lambda: sc.ScalarFunction(fn, y0, args))
    batched = lanes is not None or _BATCHED_TRACE.get()
    # "batched" on a CPU only: there a batch's compile is LLVM compiling the rollout as one
    # function, which the loops shrink; an accelerator would launch each loop iteration's
    # kernels (and test its predicate) once per column and step.
    loop = (solver.jacobian_loop == JacobianLoop.ALWAYS
            or (solver.jacobian_loop == JacobianLoop.BATCHED and batched
                and jax.default_backend() == "cpu"))
    if loop:
        tangent = _scalar_tangent(fn, y0, args)

        def jacobian(y, a):
            blocks = tangent.on_unit_vectors(y, a, batched=True)  # [block][row][column]
            return [[column for rows in blocks for column in rows[r]]
                    for r in range(len(blocks[0]))], None
    else:
        jac_fn = _scalar_jacobian(fn, y0, args, solver.scalar_jacobian, residual=True)
        with_residual = isinstance(jac_fn.out_shape, tuple)

        def jacobian(y, a):
            out = jac_fn(y, a, batched=True)
            return (_rows(out[0]), list(out[1])) if with_residual else (_rows(out), None)

    return residual, jacobian


def _column_blocks(m: int) -> list[tuple[int, int]]:
    """The blocks of the unknowns of :func:`_scalar_block_factor`: the leading three (the
    rotational unknowns of the Lie-group VIs) and the rest."""
    return [(0, m)] if m <= 3 else [(0, 3), (3, m)]


def _scalar_tangent(fn, y0, args) -> sc.ScalarFunction:
    """``(y, args, d_1, ..., d_k) -> (∂fn/∂y_1 · d_1, ..., ∂fn/∂y_k · d_k)`` for the blocks
    ``y_b`` of the unknowns (:func:`_column_blocks`) as one scalar program (the primal
    operations shared): its
    :meth:`~lgvi_jax.scalarize.ScalarFunction.on_unit_vectors` is the Jacobian, block of
    columns by block of columns. By blocks, each loop's tangent operations fold the other
    blocks' zeros: car-pendulum ``hamel``, 326 per rotational column and 106 per other
    column, against 383 per column for one loop over all five (the unrolled Jacobian:
    1018)."""
    blocks = _column_blocks(y0.shape[-1])

    def tangents(y, a, *ds):
        _, linear = jax.linearize(lambda y: fn(y, a), y)
        m = y.shape[-1]
        return tuple(linear(jnp.concatenate([jnp.zeros(lo, y.dtype), d,
                                             jnp.zeros(m - hi, y.dtype)]))
                     for (lo, hi), d in zip(blocks, ds, strict=True))

    directions = [jax.ShapeDtypeStruct((hi - lo,), y0.dtype) for lo, hi in blocks]
    return _memo("tangent_blocks", fn, y0, args,
                 lambda: sc.ScalarFunction(tangents, y0, args, *directions))


def _split_lanes(x, lanes: int | None) -> np.ndarray:
    """:func:`~lgvi_jax.scalarize.split` of one array; with ``lanes``, of an array whose
    leading axis is the batch, into vectors over the batch (one per entry)."""
    if lanes is None:
        return sc.split(x)
    out = np.empty(x.shape[1:], dtype=object)
    for idx in np.ndindex(out.shape):
        out[idx] = x[(slice(None), *idx)]
    return out


def _while_lanes(cond, body, init, lanes: int | None):
    """``lax.while_loop(cond, body, init)``; with ``lanes``, every carry a vector over a
    batch and ``cond`` one predicate per member: the loop runs while any member's holds and
    a member whose predicate fails keeps its carry, so that each member sees its own loop
    (what ``vmap`` makes of a loop, written once instead of batched by JAX's fixed-point
    search over the carries, which retraces the body per search step)."""
    if lanes is None:
        return jax.lax.while_loop(cond, body, init)

    def masked(c):
        active = cond(c)
        return jax.tree.map(lambda new, old: jnp.where(active, new, old), body(c), c)

    return jax.lax.while_loop(lambda c: jnp.any(cond(c)), masked, init)


def _iterate_scalar(programs, y0, args, solver: Newton, lanes: int | None = None):
    """:func:`_iterate_chord_refresh` (``chord_steps > 0``) or plain Newton, written on
    scalars, with the matrix factored by blocks (:func:`_scalar_block_factor`).
    ``programs``: :func:`_scalar_programs`, replayed with their shared values materialised
    (:class:`~lgvi_jax.scalarize.ScalarFunction`). Each outer iteration factors the Jacobian
    at its iterate and runs the updates in an inner loop (chord phase: until convergence or
    stall; Newton phase: one update), so that the residual appears once in the program.

    ``lanes``: ``None`` for one solve; else the solve of a batch of that many (``y0``
    ``[lanes, m]``, ``args`` leaves batched along their leading axis where ``args_batched``
    says so, see :func:`_scalar_core`), every scalar a vector over the batch (a structure of
    arrays) and the loops :func:`_while_lanes`: each member's iterates, result and
    iteration count are those of its own solve. Returns (y, result, steps, residual)."""
    res_fn, jacobian = programs
    args, args_batched = args if lanes is not None else (args, None)
    dtype = y0.dtype
    m = y0.shape[-1]
    shape = () if lanes is None else (lanes,)
    if lanes is None:
        args_s = jax.tree.map(sc.split, args)
    else:
        args_s = jax.tree.map(lambda x, b: _split_lanes(x, lanes if b else None), args,
                              args_batched)
    chord_cap = min(solver.chord_steps, solver.max_steps)
    zero = sc.constant(0.0, dtype)
    atol, rtol = sc.constant(solver.atol, dtype), sc.constant(solver.rtol, dtype)

    def full(value, dt):
        return jnp.full(shape, value, dt)

    def lane(v):
        return jnp.broadcast_to(_jnp(v, dtype), shape)

    def as_obj(y):
        out = np.empty((m,), dtype=object)
        for i, v in enumerate(y):
            out[i] = v
        return out

    def update(y, J_fac, k, prev, newton, cap, k_phase, F=None):
        if F is None:
            F = list(res_fn(as_obj(y), args_s, batched=True))
        delta = [sc.neg(d) for d in _scalar_block_solve(J_fac, F)]
        res = _scalar_max([sc.absolute(f) for f in F], zero)
        finite = sc.isfinite(res)
        for d in delta:
            finite = sc.logical_and(finite, sc.isfinite(d))
        y_new = [sc.add(a, d) for a, d in zip(y, delta, strict=True)]
        size = _scalar_max([sc.div(sc.absolute(d), sc.add(atol, sc.mul(rtol, sc.absolute(a))))
                            for d, a in zip(delta, y_new, strict=True)], zero)
        k = k + 1
        # A chord phase gives up (-> refresh or Newton) when it stops contracting or runs
        # out; the Newton phase takes one update per Jacobian and fails at its cap.
        stop = newton | (k - k_phase >= chord_cap) | (size > 0.5 * prev)
        result = jnp.where(
            ~finite, RESULTS.nonfinite,
            jnp.where(size <= 1.0, RESULTS.successful,
                      jnp.where(newton & (k >= cap), RESULTS.max_steps_reached, -1)),
        ).astype(jnp.int32)
        y_new = [jnp.where(finite, a, b) for a, b in zip(y_new, y, strict=True)]
        return (tuple(lane(v) for v in y_new), k, result, lane(res), lane(size), stop)

    def outer_body(carry):
        y, k, _, _, newton, cap, refreshes, res0 = carry
        k_phase = k
        J, F = jacobian(as_obj(y), args_s)
        J_fac = _scalar_block_factor(J)

        def inner_body(c, F_at_y=None):
            y, k, _, _, prev, _, r0 = c
            out = update(list(y), J_fac, k, prev, newton, cap, k_phase, F_at_y)
            return (*out, jnp.where(out[1] == 1, out[3], r0))  # the residual at the guess

        init = (y, k, full(-1, jnp.int32), full(jnp.inf, dtype), full(jnp.inf, dtype),
                full(False, jnp.bool_), res0)
        if F is not None:  # the first update (it always runs) from the Jacobian's residual
            init = inner_body(init, F)
        y, k, result, res, _, _, res0 = _while_lanes(
            lambda c: (c[2] < 0) & ~c[5], inner_body, init, lanes)
        fallback, newton, cap, refreshes = _chord_phase_end(
            newton, result, refreshes, res, res0, k, cap, solver.max_steps)
        y = tuple(jnp.where(fallback, a, b) for a, b in zip(y0_s, y, strict=True))
        return y, k, result, res, newton, cap, refreshes, res0

    if lanes is None:
        y0_s = tuple(_jnp(v, dtype) for v in sc.split(y0))
    else:
        y0_s = tuple(y0[:, i] for i in range(m))
    init = (y0_s, full(0, jnp.int32), full(-1, jnp.int32), full(jnp.inf, dtype),
            full(solver.chord_steps == 0, jnp.bool_), full(solver.max_steps, jnp.int32),
            full(0, jnp.int32), full(jnp.inf, dtype))
    y, k, result, res, *_ = _while_lanes(lambda c: c[2] < 0, outer_body, init, lanes)
    return jnp.stack(y, axis=-1), result, k, res


def _jnp(v, dtype):
    return jnp.asarray(np.asarray(v) if isinstance(v, np.generic) else v, dtype)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _scalar_core(fn, solver, y0, args):
    # Both one trajectory and a batch replay the programs with their shared values
    # materialised (ScalarFunction's batched layout): left to XLA, one trajectory's
    # fusions recompute them (a slower run and a longer compile). Under vmap the solve is
    # written on vectors over the batch (custom_vmap, _iterate_scalar's lanes) rather than
    # batched by JAX, which retraces the loops' bodies until their carries settle.
    # The shapes of one solve's arguments (what its programs are built for): not the
    # tracers themselves, which custom_vmap's rule would see as batched constants.
    example = jax.tree.map(lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)),
                           (y0, args))

    @jax.custom_batching.custom_vmap
    def solve(y0, args):
        return _iterate_scalar(_scalar_programs(fn, *example, solver, None), y0, args,
                               solver)

    @solve.def_vmap
    def _solve_batched(axis_size, in_batched, y0, args):
        y0_batched, args_batched = in_batched
        if not y0_batched:
            y0 = jnp.broadcast_to(y0, (axis_size, *y0.shape))
        programs = _scalar_programs(fn, *example, solver, axis_size)
        out = _iterate_scalar(programs, y0, (args, args_batched), solver, lanes=axis_size)
        return out, (True,) * len(out)

    return solve(y0, args)


@_scalar_core.defjvp
def _scalar_core_jvp(fn, solver, primals, tangents):
    # The implicit function theorem, as in _newton_core_jvp, on scalars: J ẏ = −∂F/∂a ȧ.
    y0, args = primals
    _, args_dot = tangents
    y, result, k, res = _named(_scalar_core(fn, solver, y0, args))
    jac_fn = _scalar_jacobian(fn, y, args, solver.scalar_jacobian)

    def dF(y, a, a_dot):
        return jax.jvp(lambda b: fn(y, b), (a,), (a_dot,))[1]

    dF_fn = _memo("tangent", fn, y, (args, args_dot),
                  lambda: sc.ScalarFunction(dF, y, args, args_dot))
    y_s, a_s, ad_s = sc.split(y), jax.tree.map(sc.split, args), jax.tree.map(sc.split, args_dot)
    # Shared values materialised, as in the solve (left to XLA, the fusions recompute them:
    # a gradient about twice as slow). The runtime one
    # that materialises them is made from the first input, the solution y: a primal, so
    # that ẏ stays linear in ȧ (transposable for grad).
    J_fac = _scalar_block_factor(_rows(jac_fn(y_s, a_s, batched=True)))
    y_dot = [sc.neg(v) for v in _scalar_block_solve(J_fac, list(dF_fn(y_s, a_s, ad_s,
                                                                        batched=True)))]
    y_dot = jnp.stack([_jnp(v, y.dtype) for v in y_dot])
    return _solution_tangents(y, result, k, res, y_dot)


def _scalar_adjugate_inverse(A):
    """Inverse of a 1x1, 2x2 or 3x3 matrix of scalars by cofactors: a few products each,
    no chain of dependent eliminations (which XLA would recompute in every consumer)."""
    m = len(A)
    one = sc.constant(1.0, np.float64)
    if m == 1:
        return [[sc.div(one, A[0][0])]]
    if m == 2:
        (a, b), (c, d) = A
        idet = sc.div(one, sc.sub(sc.mul(a, d), sc.mul(b, c)))
        return [[sc.mul(d, idet), sc.neg(sc.mul(b, idet))],
                [sc.neg(sc.mul(c, idet)), sc.mul(a, idet)]]

    def cof(i, j):
        r = [k for k in range(3) if k != i]
        c = [k for k in range(3) if k != j]
        minor = sc.sub(sc.mul(A[r[0]][c[0]], A[r[1]][c[1]]), sc.mul(A[r[0]][c[1]], A[r[1]][c[0]]))
        return minor if (i + j) % 2 == 0 else sc.neg(minor)

    C = [[cof(i, j) for j in range(3)] for i in range(3)]
    det = sc.add(sc.add(sc.mul(A[0][0], C[0][0]), sc.mul(A[0][1], C[0][1])),
                 sc.mul(A[0][2], C[0][2]))
    idet = sc.div(one, det)
    return [[sc.mul(C[j][i], idet) for j in range(3)] for i in range(3)]


def _scalar_matmul(A, B):
    return [[_dot([A[i][k] for k in range(len(B))], [B[k][j] for k in range(len(B))])
             for j in range(len(B[0]))] for i in range(len(A))]


def _dot(a, b):
    acc = sc.constant(0.0, np.float64)
    for x, y in zip(a, b, strict=True):
        acc = sc.add(acc, sc.mul(x, y))
    return acc


def _scalar_block_factor(A):
    """``A`` factored by blocks for :func:`_scalar_block_solve`: ``A = [[P, Q], [R, S]]``
    with ``P`` its leading 3x3 block (the rotational unknowns of the Lie-group VIs) gives
    ``(P⁻¹, P⁻¹Q, R, factor of T)``, ``P⁻¹`` by cofactors and the Schur complement
    ``T = S − R P⁻¹ Q`` factored the same way (a matrix of at most 3x3: ``(A⁻¹,)`` by
    cofactors). Half the operations of forming ``A⁻¹`` (car-pendulum, 5x5), and a solve
    costs what a product with ``A⁻¹`` would. No pivoting: for the Newton matrices of the
    VIs, the kinetic-energy Hessian plus O(h) terms, ``P`` and ``T`` are near positive
    definite; a singular block gives non-finite entries (reported by the solver as
    non-finite)."""
    m = len(A)
    if m <= 3:
        return (_scalar_adjugate_inverse(A),)
    P = [row[:3] for row in A[:3]]
    Q = [row[3:] for row in A[:3]]
    R = [row[:3] for row in A[3:]]
    S = [row[3:] for row in A[3:]]
    Pi = _scalar_adjugate_inverse(P)
    PiQ = _scalar_matmul(Pi, Q)
    T = [[sc.sub(S[i][j], _dot(R[i], [PiQ[k][j] for k in range(3)])) for j in range(m - 3)]
         for i in range(m - 3)]
    return Pi, PiQ, R, _scalar_block_factor(T)


def _scalar_block_solve(factor, f):
    """``A⁻¹ f`` from :func:`_scalar_block_factor`: ``g = P⁻¹ f₁``,
    ``x₂ = T⁻¹ (f₂ − R g)``, ``x₁ = g − P⁻¹Q x₂``."""
    if len(factor) == 1:
        return _scalar_matvec(factor[0], f)
    Pi, PiQ, R, Tf = factor
    g = _scalar_matvec(Pi, f[:3])
    x2 = _scalar_block_solve(Tf, [sc.sub(a, b) for a, b in zip(f[3:], _scalar_matvec(R, g),
                                                                   strict=True)])
    x1 = [sc.sub(a, b) for a, b in zip(g, _scalar_matvec(PiQ, x2), strict=True)]
    return x1 + x2
