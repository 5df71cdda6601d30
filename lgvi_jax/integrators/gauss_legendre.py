"""Gauss–Legendre collocation Runge–Kutta methods (order 2s, symplectic)."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from ..newton import Newton, newton_solve
from ._tableaus import collocation_matrix, gauss_legendre
from .base import AbstractIntegrator, StepInfo


class GaussLegendre(AbstractIntegrator):
    r"""The s-stage Gauss–Legendre Runge–Kutta method (``stages=2``: ``gl4``).

    Collocation at the Gauss nodes :math:`c_i` (roots of the shifted Legendre polynomial),
    :math:`a_{ij} = \int_0^{c_i} \ell_j`, :math:`b_j = \int_0^1 \ell_j`. The stage
    derivatives :math:`K_i` solve

    .. math::  K_i = f\Big(y_0 + h \sum_j a_{ij} K_j\Big), \qquad
               y_1 = y_0 + h \sum_i b_i K_i,

    by Newton's method (:func:`lgvi_jax.newton.newton_solve`, initial guess
    :math:`K_i = f(y_0)`). The unknowns are the O(1) stage derivatives, not the stage values,
    so the Newton tolerance is relative to velocities and round-off does not grow like 1/h.
    Order :math:`2s`, symmetric, symplectic, A-stable; conserves quadratic invariants exactly
    (the harmonic oscillator's energy up to round-off). For :math:`s = 2`,
    :math:`c = \tfrac12 \mp \tfrac{\sqrt3}{6}`. Reference: Hairer, Lubich, Wanner,
    *Geometric Numerical Integration* (2006), §II.1.3, §VI.4.
    """

    stages: int = eqx.field(static=True, default=2)
    newton: Newton = Newton()

    symmetric: ClassVar[bool] = True
    symplectic: ClassVar[bool] = True
    implicit: ClassVar[bool] = True

    def __check_init__(self):
        if not isinstance(self.stages, int) or self.stages < 1:
            raise ValueError(f"GaussLegendre: stages must be an integer >= 1, got {self.stages}")

    @property
    def name(self) -> str:
        return f"gl{2 * self.stages}"

    @property
    def order(self) -> int:
        return 2 * self.stages

    def step(self, model, state, dt):
        y0, unravel = ravel_pytree(state)
        c, b = gauss_legendre(self.stages)
        A = collocation_matrix(tuple(c))

        def flat_field(model, y):
            return ravel_pytree(model.vector_field(unravel(y)))[0]

        def residual(K, args):
            model, y0, dt = args
            Y = y0 + dt * (A @ K)
            return K - jax.vmap(lambda y: flat_field(model, y))(Y)

        K0 = jnp.tile(flat_field(model, y0), (self.stages, 1))
        sol = newton_solve(residual, K0, (model, y0, dt), self.newton)
        y1 = y0 + dt * (b @ sol.value)
        return unravel(y1), StepInfo.from_solution(sol)
