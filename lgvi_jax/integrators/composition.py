r"""Symmetric compositions: higher-order methods from any symmetric one-step method.

**Contract.** :class:`Composition` is an integrator built from a symmetric one-step method
``base`` and sub-step fractions :math:`\gamma_1, \dots, \gamma_s` (summing to 1): one step
of size :math:`h` is :math:`s` steps of ``base`` of sizes :math:`\gamma_i h` (negative ones
included), run in one ``lax.scan``. Its ``order`` is computed from the :math:`\gamma`'s and
the base order (:mod:`lgvi_jax.integrators.order_conditions`); ``symmetric``,
``symplectic`` and ``implicit`` follow from the base's. The named coefficient sets and the
construction by order or name (``compose(method, order=6)``, ``lgvi@6``) are in
:mod:`lgvi_jax.integrators.schemes`.

**The maths.** Given a one-step method :math:`\Phi_h` and real numbers
:math:`\gamma_1, \dots, \gamma_s`, the composition method is

.. math::  \Psi_h = \Phi_{\gamma_s h} \circ \dots \circ \Phi_{\gamma_2 h} \circ
           \Phi_{\gamma_1 h}

(HLW §II.4, §V.3). It inherits every property that is closed under composition: a
composition of symplectic maps is symplectic; of maps on :math:`SO(3) \times \mathbb{R}^n`
stays there; of maps that conserve a momentum map conserves it exactly; and the composition
of discrete Lagrangian flows is the flow of a discrete Lagrangian (it is again a variational
integrator, of the composed step). If the base method is symmetric
(:math:`\Phi_{-h} = \Phi_h^{-1}`) and the :math:`\gamma`'s are palindromic
(:math:`\gamma_{s+1-i} = \gamma_i`), the composition is symmetric too, and its order
conditions are those of :mod:`~lgvi_jax.integrators.order_conditions` (a BCH computation
in the base method's error fields).

**Warm starts.** Each sub-step of a Lie-group VI solves for the mean body and cart velocity
:math:`(\xi, u)` over the sub-step, which approximates the velocity at its midpoint. The
base method starts Newton from the velocities of the current state, an :math:`O(\gamma_i h)`
guess. Inside a composition the previous sub-step's solution :math:`\bar v_{i-1}` (the
velocity near the midpoint of the previous sub-step) and the current velocity :math:`v`
give a linear extrapolation to the midpoint of the next one, valid for backward
(:math:`\gamma_i < 0`) sub-steps too since the midpoints are at signed offsets
:math:`-\gamma_{i-1}h/2` and :math:`\gamma_i h/2`:

.. math::  v_{\rm guess} = v + \frac{\gamma_i}{\gamma_{i-1}}\,(v - \bar v_{i-1}),

an :math:`O(h^2)` guess (``warm_start=True``, the default; the first sub-step uses
:math:`v`). The guess changes only the Newton iterates, not the solution.

**Solver settings.** A composition's Lie-group VI sub-steps are solved as its base says,
on scalars where the base's settings allow it (``scalar=True``, the default; the same
solutions to round-off). :func:`~lgvi_jax.integrators.solver_settings.with_chord_matrix`
and :func:`~lgvi_jax.integrators.solver_settings.with_scalar_newton` reach through a
composition to its base: their rule for :class:`Composition` is registered here.

References: E. Hairer, C. Lubich, G. Wanner, *Geometric Numerical Integration*, 2nd ed.,
Springer 2006 (HLW), §II.4 (composition methods), §III.4–III.5 (order conditions via the
BCH formula), §V.3 (symmetric composition methods); H. Yoshida, *Construction of higher
order symplectic integrators*, Phys. Lett. A 150 (1990) 262–268; M. Suzuki, *Fractal
decomposition of exponential operators with applications to many-body theories and Monte
Carlo simulations*, Phys. Lett. A 146 (1990) 319–323; J. E. Marsden, M. West, *Discrete
mechanics and variational integrators*, Acta Numerica 10 (2001) 357–514 (composition
methods as variational integrators).
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp

from ..options import ChordMatrix
from ..trajectory import RESULTS
from .base import AbstractIntegrator, StepInfo
from .lie import AbstractLieVI
from .order_conditions import composition_order
from .solver_settings import with_chord_matrix, with_scalar_newton

__all__ = ["Composition"]


def _merge_info(acc, info):
    """Sum the iterations; keep the first failure's code and residual (else the largest
    residual)."""
    steps, code, res = acc
    first_failure = (code == RESULTS.successful) & (info.result != RESULTS.successful)
    res = jnp.where(first_failure, info.residual,
                    jnp.where(code == RESULTS.successful, jnp.maximum(res, info.residual), res))
    code = jnp.where(first_failure, info.result, code).astype(jnp.int32)
    return steps + info.newton_steps.astype(jnp.int32), code, res


class Composition(AbstractIntegrator):
    r"""The composition :math:`\Phi_{\gamma_s h}\circ\dots\circ\Phi_{\gamma_1 h}` of a
    symmetric one-step method ``base`` (module docstring).

    Args:
        base: a symmetric integrator (``base.symmetric``), e.g. ``LGVI()``.
        gammas: the sub-step fractions, summing to 1 (palindromic for a symmetric result).
        scheme: a label for :attr:`name` (``"<base>@<scheme>"``); default ``"custom"``.
        warm_start: start each Lie-group VI sub-step's Newton solve from the extrapolated
            previous solution (module docstring); no effect for other base methods.
        scalar: solve a Lie-group VI base's sub-steps with the autodiff engine on scalars
            (its Newton settings with ``scalar=True``, :mod:`lgvi_jax.scalarize`): the same
            solutions to round-off, several times faster (``lgvi@4``: ~6x, ``lgvi@8``:
            ~3.5x for one trajectory, docs/engine.md). Used where the base's settings allow
            it (the exact chord matrix; chord-then-Newton or plain Newton); ``False``: on
            small arrays (:func:`~lgvi_jax.integrators.with_scalar_newton` with
            ``scalar=False``).

    ``order`` is computed from ``gammas`` and ``base.order``
    (:func:`~lgvi_jax.integrators.order_conditions.composition_order`);
    ``symmetric`` = base symmetric and palindromic ``gammas``; ``symplectic`` and
    ``implicit`` are the base's. The sub-steps run in a ``lax.scan`` over the array of
    ``gammas`` (one traced copy of the base step, whatever the number of stages).
    ``step`` reports the Newton iterations summed over the sub-steps and the first failing
    sub-step's result code and residual.
    """

    base: AbstractIntegrator
    gammas: tuple[float, ...] = eqx.field(static=True)
    scheme: str = eqx.field(static=True, default="custom")
    warm_start: bool = eqx.field(static=True, default=True)
    scalar: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        if not isinstance(self.base, AbstractIntegrator):
            raise ValueError(f"Composition: base must be an integrator, got {self.base!r}")
        if not self.base.symmetric:
            raise ValueError(
                f"Composition: base method {self.base.name} is not symmetric "
                "(Φ_{-h} ≠ Φ_h^{-1}); composition needs a symmetric base method "
                "(e.g. lgvi, hamel-cayley, hamel-exact, verlet, gl4)"
            )
        if isinstance(self.base, Composition):
            raise ValueError("Composition: base is already a composition; compose the "
                             "underlying method with a higher-order scheme instead")
        gammas = self.gammas
        if (not isinstance(gammas, tuple) or not gammas
                or not all(isinstance(g, float) and math.isfinite(g) for g in gammas)):
            raise ValueError(f"Composition: gammas must be a non-empty tuple of finite floats, "
                             f"got {gammas!r}")
        if abs(math.fsum(gammas) - 1.0) > 1e-12:
            raise ValueError(f"Composition: gammas must sum to 1 (consistency), they sum to "
                             f"{math.fsum(gammas)!r}")

    # --- traits -------------------------------------------------------------------------
    @property
    def name(self) -> str:
        return f"{self.base.name}@{self.scheme}"

    @property
    def stages(self) -> int:
        return len(self.gammas)

    @property
    def order(self) -> int:
        return max(composition_order(self.gammas, self.base.order), self.base.order)

    @property
    def palindromic(self) -> bool:
        g = self.gammas
        return all(abs(a - b) <= 1e-15 * max(1.0, abs(a)) for a, b in zip(g, g[::-1], strict=True))

    @property
    def symmetric(self) -> bool:
        return self.base.symmetric and self.palindromic

    @property
    def symplectic(self) -> bool:
        return self.base.symplectic

    @property
    def implicit(self) -> bool:
        return self.base.implicit

    def check_model(self, model) -> None:
        self.base.check_model(model)

    def describe(self) -> str:
        return f"{super().describe()[:-1]}, {self.stages} stages of {self.base.name})"

    # --- the step -----------------------------------------------------------------------
    def _sub_step_method(self) -> AbstractIntegrator:
        """The base with its solver as :attr:`scalar` says."""
        return with_scalar_newton(self.base, self.scalar)

    def step(self, model, state, dt):
        base = self._sub_step_method()
        gam = jnp.asarray(self.gammas, jnp.float64)
        dt = jnp.asarray(dt, jnp.float64)
        acc0 = (jnp.asarray(0, jnp.int32), jnp.asarray(RESULTS.successful, jnp.int32),
                jnp.zeros((), jnp.float64))

        if not (self.warm_start and isinstance(self.base, AbstractLieVI)):
            def plain(carry, g):
                s, acc = carry
                s, info = base.step(model, s, g * dt)
                return (s, _merge_info(acc, info)), None

            (state, acc), _ = jax.lax.scan(plain, (state, acc0), gam)
            return state, StepInfo(newton_steps=acc[0], result=acc[1], residual=acc[2])

        # Warm start: the previous sub-step's fraction (0 before the first sub-step, where
        # the guess is the current velocity).
        prev_gam = jnp.concatenate([jnp.zeros((1,), jnp.float64), gam[:-1]])

        def warm(carry, xs):
            s, prev_sol, acc = carry
            g, g_prev = xs
            v = base.guess_from_velocities(model.velocities(s.R, s.mu, s.q, s.p))
            ratio = jnp.where(g_prev == 0.0, 0.0, g / jnp.where(g_prev == 0.0, 1.0, g_prev))
            guess = jax.tree.map(lambda a, b: a + ratio * (a - b), v, prev_sol)
            s, info, sol = base.solve_step(model, s, g * dt, guess)
            return (s, sol, _merge_info(acc, info)), None

        zero_sol = jax.tree.map(jnp.zeros_like, base.guess_from_velocities(
            (jnp.zeros_like(state.mu), jnp.zeros_like(state.p))))
        (state, _, acc), _ = jax.lax.scan(warm, (state, zero_sol, acc0), (gam, prev_gam))
        return state, StepInfo(newton_steps=acc[0], result=acc[1], residual=acc[2])


# The solver settings of a composition are its base's (lgvi_jax.integrators.solver_settings).


@with_chord_matrix.register(Composition)
def _(method: Composition, chord_matrix: ChordMatrix | str) -> AbstractIntegrator:
    return dataclasses.replace(method, base=with_chord_matrix(method.base, chord_matrix))


@with_scalar_newton.register(Composition)
def _(method: Composition, scalar: bool = True) -> AbstractIntegrator:
    return dataclasses.replace(method, base=with_scalar_newton(method.base, scalar),
                               scalar=scalar)
